import numpy as np
import pytest
from scipy.signal import correlate

from mrrig.offline.datasets import (
    DATASET_A_VALIDATION_NAMES,
    DataError,
    Series,
    columns_from_header,
    csv_header,
    dataset_a_training,
    dataset_a_validation,
    dataset_b,
    dataset_b_conditions,
    load_csv,
)


@pytest.fixture(scope="module")
def training():
    return dataset_a_training()


@pytest.fixture(scope="module")
def validation():
    return dataset_a_validation()


@pytest.fixture(scope="module")
def rig():
    return dataset_b()


def _at(s, t_s):
    return s.current[round(t_s / 1e-3)]


@pytest.mark.long
def test_dataset_a_training_follows_the_voltage_schedule(training):
    assert len(training) == 100_000
    np.testing.assert_allclose(np.diff(training.t), 1e-3)
    for t_s, v in [(60.0, 12.0), (65.0, 12.0), (69.999, 12.0), (70.0, 6.0), (79.999, 6.0)]:
        assert _at(training, t_s) == v
    for t_s in (80.0, 85.0, 89.999):
        assert _at(training, t_s) == 0.0
    late = training.t >= 90.0
    np.testing.assert_allclose(
        training.current[late], 6 * np.sin(4 * np.pi * training.t[late]) + 6, atol=1e-12
    )
    early = training.current[training.t < 60.0]
    assert early.min() >= 0.0 and early.max() <= 12.0 + 1e-12
    assert abs(early.mean() - 6.0) < 1.0 and early.std() > 1.0
    assert np.max(np.abs(training.x)) == pytest.approx(0.025)
    assert np.all(np.isfinite(training.force)) and np.abs(training.force).max() > 1000.0


@pytest.mark.long
def test_dataset_a_training_is_reproducible_from_its_seed(training):
    again = dataset_a_training()
    np.testing.assert_array_equal(again.x, training.x)
    np.testing.assert_array_equal(again.current, training.current)
    np.testing.assert_array_equal(again.force, training.force)


@pytest.mark.long
def test_dataset_a_validation_has_the_seven_cases_of_table_6(validation):
    assert tuple(s.name for s in validation) == DATASET_A_VALIDATION_NAMES
    assert DATASET_A_VALIDATION_NAMES == ("1,k=1", "1,k=2", "1,k=3", "2", "3,k=1", "3,k=2", "3,k=3")
    t = validation[0].t
    assert all(len(s) == 6000 for s in validation)
    for k, s in zip((1, 2, 3), validation[:3], strict=True):
        np.testing.assert_allclose(s.x, 0.01 * np.sin(2 * k * np.pi * t), atol=1e-15)
        assert np.all(s.current == 1.5)
    set2 = validation[3]
    assert np.max(np.abs(set2.x)) == pytest.approx(0.02)
    assert set2.current.min() >= 0.0 and set2.current.max() <= 4.0 + 1e-12
    for k, s in zip((1, 2, 3), validation[4:], strict=True):
        np.testing.assert_array_equal(s.x, set2.x)
        np.testing.assert_allclose(s.current, 1.5 + 0.75 * np.sin(2 * k * np.pi * t))
    reseeded = dataset_a_validation()
    np.testing.assert_array_equal(reseeded[3].force, set2.force)


@pytest.mark.long
def test_dataset_a_validation_displacement_is_not_in_the_training_series(training, validation):
    train = training.x
    energy_win = np.convolve(train**2, np.ones(6000), mode="valid")
    worst = np.inf
    for s in validation:
        e_val = np.sum(s.x**2)
        dist2 = e_val + energy_win - 2 * correlate(train, s.x, mode="valid", method="fft")
        worst = min(worst, dist2.min() / e_val)
    print(f"closest training window to a validation displacement: {worst:.3f} (relative)")
    assert worst > 0.05


def test_dataset_b_has_150_runs_with_ids_conditions_noise_and_quantisation(rig):
    n_keep = 500
    assert len(rig) == 150 * n_keep
    np.testing.assert_array_equal(rig.run_id, np.repeat(np.arange(150), n_keep))
    cond = dataset_b_conditions((0.010, 0.015, 0.020), (2, 3, 4, 5, 6), np.arange(10) * 0.2)
    assert cond.shape == (150, 3)
    per_run = rig.current.reshape(150, n_keep)
    assert np.all(per_run == per_run[:, :1])
    np.testing.assert_allclose(per_run[:, 0], cond[:, 2])
    np.testing.assert_allclose(rig.x.reshape(150, n_keep).max(axis=1), cond[:, 0], rtol=0.01)
    np.testing.assert_allclose(rig.t[:n_keep], np.arange(n_keep) / 500.0, atol=1e-12)
    assert np.std(rig.x_meas - rig.x) == pytest.approx(1e-5, rel=0.05)
    assert np.std(rig.force_meas - rig.force) == pytest.approx(2.0, rel=0.05)
    for meas, lsb in ((rig.x_meas, 1e-6), (rig.force_meas, 0.01)):
        steps = meas / lsb
        assert np.max(np.abs(steps - np.round(steps))) < 1e-6


def test_dataset_b_without_noise_only_quantises():
    s = dataset_b(
        (0.01,),
        (2.0,),
        (0.0, 1.0),
        duration_s=0.2,
        settle_s=0.1,
        force_noise_n=0.0,
        displacement_noise_m=0.0,
    )
    assert len(s) == 200
    assert np.max(np.abs(s.x_meas - s.x)) <= 0.5e-6 + 1e-12
    assert np.max(np.abs(s.force_meas - s.force)) <= 0.005 + 1e-9
    assert np.any(s.x_meas != s.x)


def _write(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows))
    return path


@pytest.fixture
def si_and_cm_csv(tmp_path):
    t = np.arange(5) * 0.002
    x, xd, xdd = 0.01 * np.sin(t * 9), 0.09 * np.cos(t * 9), -0.81 * np.sin(t * 9)
    i, f = np.linspace(0, 1, 5), np.linspace(-900, 1200, 5)
    si = _write(
        tmp_path / "si.csv",
        ["time", "pos", "vel", "acc", "I", "F"],
        zip(t, x, xd, xdd, i, f, strict=True),
    )
    cm = _write(
        tmp_path / "cm.csv",
        ["F_kN", "x_cm", "v_cm_s", "a_cm_s2", "t_ms", "i_mA"],
        zip(f / 1e3, x * 100, xd * 100, xdd * 100, t * 1e3, i * 1e3, strict=True),
    )
    return si, cm


def test_csv_in_cm_kn_ms_ma_loads_equal_to_si(si_and_cm_csv):
    si, cm = si_and_cm_csv
    a = load_csv(
        si, {"t": "time", "x": "pos", "xd": "vel", "xdd": "acc", "current": "I", "force": "F"}, {}
    )
    b = load_csv(
        cm,
        {
            "t": "t_ms",
            "x": "x_cm",
            "xd": "v_cm_s",
            "xdd": "a_cm_s2",
            "current": "i_mA",
            "force": "F_kN",
        },
        {"t": "ms", "x": "cm", "xd": "cm/s", "xdd": "cm/s^2", "current": "mA", "force": "kN"},
    )
    for field in ("t", "x", "xd", "xdd", "current", "force"):
        np.testing.assert_allclose(getattr(b, field), getattr(a, field), rtol=1e-12, atol=1e-15)
    assert a.name == "si" and len(a) == 5


def test_csv_without_velocity_columns_leaves_them_none(si_and_cm_csv):
    s = load_csv(si_and_cm_csv[0], {"t": "time", "x": "pos", "current": "I", "force": "F"})
    assert s.xd is None and s.xdd is None


_COLS = {"t": "time", "x": "pos", "current": "I", "force": "F"}


@pytest.mark.parametrize(
    ("case", "columns", "units", "names"),
    [
        ("missing file", _COLS, {}, ["nope.csv"]),
        ("missing column", _COLS | {"force": "Fz"}, {}, ["'Fz'", "'force'"]),
        ("unknown unit", _COLS, {"x": "inch"}, ["'x'", "'inch'"]),
        ("unknown field", _COLS | {"temp": "T"}, {}, ["'temp'"]),
        ("no column for a field", {"t": "time", "x": "pos", "current": "I"}, {}, ["'force'"]),
        ("non-numeric value", _COLS | {"current": "bad"}, {}, ["'bad'", "'current'", "line 3"]),
        ("empty value", _COLS | {"current": "gap"}, {}, ["'gap'", "line 4"]),
    ],
)
def test_each_bad_csv_input_gives_a_one_line_data_error(tmp_path, case, columns, units, names):
    good = _write(
        tmp_path / "rec.csv",
        ["time", "pos", "I", "F", "bad", "gap"],
        [(0, 0, 0, 0, 1, 1), (0.002, 0, 0, 0, "1.2.3", 1), (0.004, 0, 0, 0, 1, "")],
    )
    path = tmp_path / "nope.csv" if case == "missing file" else good
    with pytest.raises(DataError) as err:
        load_csv(path, columns, units)
    msg = str(err.value)
    print(f"{case}: {msg}")
    assert "\n" not in msg and path.name in msg
    for name in names:
        assert name in msg
    assert isinstance(err.value, ValueError)


def test_csv_with_blank_lines_trailing_commas_bom_comments_and_quotes_reads_as_plain(
    si_and_cm_csv, tmp_path
):
    plain = load_csv(si_and_cm_csv[0], _COLS)
    lines = si_and_cm_csv[0].read_text().splitlines()
    header = ",".join(f'"{h}"' for h in lines[0].split(","))  # quoted headers
    body = [line + "," for line in lines[1:]]  # a trailing comma on every data row
    messy = tmp_path / "messy.csv"
    text = "# rig 1, test 7\n" + header + ",\n" + body[0] + "\n\n# a note\n"
    text += "\n".join(body[1:]) + "\n\n"  # blank lines inside and at the end
    messy.write_bytes(b"\xef\xbb\xbf" + text.encode())  # a BOM
    got = load_csv(messy, _COLS)
    for field in ("t", "x", "current", "force"):
        np.testing.assert_array_equal(getattr(got, field), getattr(plain, field))


def test_bad_value_after_comment_and_blank_lines_names_its_file_line(tmp_path):
    path = tmp_path / "late.csv"
    path.write_text("# header next\ntime,pos,I,F\n0,0,0,0\n\n# note\n0.002,0,x,0\n")
    with pytest.raises(DataError, match=r"late.csv: line 6: column 'I' \(field 'current'\)"):
        load_csv(path, _COLS)


def test_csv_is_read_in_chunks_equal_to_one_read(si_and_cm_csv, monkeypatch):
    import mrrig.offline.datasets as ds

    whole = load_csv(si_and_cm_csv[0], _COLS)
    monkeypatch.setattr(ds, "CSV_CHUNK_ROWS", 2)  # 5 rows: chunks of 2, 2, 1
    chunked = load_csv(si_and_cm_csv[0], _COLS)
    np.testing.assert_array_equal(chunked.force, whole.force)
    np.testing.assert_array_equal(chunked.t, whole.t)


def test_headers_with_units_name_the_fields_and_a_voltage_command_stays_volts(tmp_path):
    path = tmp_path / "dyke.csv"
    path.write_text("t_s,x_cm,command_v,force_n\n0,1.5,2.0,10\n0.001,1.6,2.5,11\n")
    columns, units = columns_from_header(csv_header(path))
    s = load_csv(path, columns, units)
    assert s.current_unit == "V"
    np.testing.assert_allclose(s.x, [0.015, 0.016])
    np.testing.assert_array_equal(s.current, [2.0, 2.5])


def test_csv_with_header_only_is_a_data_error(tmp_path):
    path = _write(tmp_path / "empty.csv", ["time", "pos", "I", "F"], [])
    with pytest.raises(DataError, match="empty.csv: no data rows"):
        load_csv(path, _COLS)


def test_series_rejects_unequal_lengths():
    with pytest.raises(ValueError, match="force"):
        Series(
            t=np.zeros(3), x=np.zeros(3), xd=None, xdd=None, current=np.zeros(3), force=np.zeros(2)
        )
