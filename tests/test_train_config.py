"""`mrrig train --config FILE`: the config's feature and training options reach the model, a
flag wins over the file, and a bad file stops with one line naming the file and the field."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import pytest

from mrrig.cli.main import main as mrrig_main
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series, dataset_b
from mrrig.offline.train_config import ConfigError, TrainConfig, load_train_config
from mrrig.offline.training import (
    load_training_data,
    series_fingerprint,
    train_and_validate,
)
from tests.conftest import REPO
from tests.data_files import write_tidy

TINY = dict(amplitudes_m=(0.015,), freqs_hz=(2.0, 5.0), currents_a=(0.0, 0.6, 1.2))
FAST = ["--epochs", "3", "--no-supervised"]


@pytest.fixture(scope="module")
def tiny() -> Series:
    """Six short runs with their exact kinematics (no estimation in the way)."""
    b = dataset_b(duration_s=0.3, **TINY)
    return Series(
        t=b.t, x=b.x, xd=b.xd, xdd=b.xdd, current=b.current, force=b.force_meas, run_id=b.run_id
    )


@pytest.fixture
def data(tmp_path, tiny) -> Path:
    path = tmp_path / "char.csv"
    write_tidy(path, tiny)
    return path


def _config(tmp_path, text: str) -> Path:
    path = tmp_path / "train.toml"
    path.write_text(text)
    return path


def _train(data: Path, out: Path, *options: str) -> MLP:
    assert mrrig_main(["train", str(data), "--out", str(out), *options]) == 0
    return MLP.load(out)


# ------------------------------------------------------------------------------------ defaults
def test_example_config_is_the_built_in_defaults():
    assert load_train_config(REPO / "configs" / "train.toml") == TrainConfig()


def test_built_in_defaults_are_the_librarys():
    """Without --config `mrrig train` trains as train_and_validate's defaults do, but for the
    current input: the lagged current, which the daemon's default inversion inverts."""
    lib = {k: p.default for k, p in inspect.signature(train_and_validate).parameters.items()}
    f, t = TrainConfig().features, TrainConfig().training
    assert f.current_input == "lagged"
    assert (f.lag_tau_s, f.history_samples, f.history_signals) == (
        lib["lag_tau_s"],
        lib["history_samples"],
        lib["history_signals"],
    )
    assert (t.epochs, t.seed, t.restarts, t.n_train, t.n_val, t.i_max_a, t.supervised) == (
        lib["max_epochs"],
        lib["seed"],
        lib["restarts"],
        lib["n_train"],
        lib["n_val"],
        lib["i_max"],
        lib["supervised"],
    )


# ------------------------------------------------------------------------- values reach model
def test_config_history_reaches_the_model_inputs_and_meta(tmp_path, data):
    cfg = _config(tmp_path, '[features]\nhistory_samples = 2\nhistory_signals = ["xd", "xdd"]\n')
    m = _train(data, tmp_path / "fwd.json", "--config", str(cfg), *FAST)
    assert m.input_names == ["x", "xd", "xdd", "current", "xd_1", "xdd_1", "xd_2", "xdd_2"]
    assert m.meta["history_samples"] == 2 and m.meta["history_signals"] == ["xd", "xdd"]
    assert m.meta["train_config"] == str(cfg)


def test_config_lagged_current_and_training_options_reach_the_model(tmp_path, data, tiny):
    cfg = _config(
        tmp_path,
        '[features]\ncurrent_input = "lagged"\nlag_tau_s = 0.004\n'
        '[training]\nepochs = 3\nseed = 2\nsplit = "random"\nn_train = 300\nn_val = 100\n'
        "supervised = false\n",
    )
    m = _train(data, tmp_path / "fwd.json", "--config", str(cfg))
    assert m.meta["current_input"] == "lagged"
    assert m.meta["lag_tau_s"] == pytest.approx(0.004)
    assert m.meta["split_seed"] == 2
    assert (m.meta["n_train"], m.meta["n_val"]) == (300, 100)  # the random split's sizes
    assert m.meta["split"] == "random"
    assert m.input_names == ["x", "xd", "xdd", "current"]


def test_config_csv_column_map_and_units_load_a_foreign_csv(tmp_path, tiny):
    s = tiny
    other = tmp_path / "other.csv"
    header = ["time_ms", "Pos", "I", "F"]
    cols = [s.t * 1e3, s.x * 1e2, s.current * 1e3, s.force * 1e-3]
    values = zip(*(c.tolist() for c in cols), strict=True)
    rows = [",".join(header)] + [",".join(map(repr, r)) for r in values]
    other.write_text("\n".join(rows) + "\n")
    columns = dict(t="time_ms", x="Pos", current="I", force="F")
    units = dict(t="ms", x="cm", current="mA", force="kN")
    cfg = _config(
        tmp_path,
        '[csv]\ncolumns = { t = "time_ms", x = "Pos", current = "I", force = "F" }\n'
        'units = { t = "ms", x = "cm", current = "mA", force = "kN" }\n',
    )
    m = _train(other, tmp_path / "fwd.json", "--config", str(cfg), "--features", "manual", *FAST)
    expected = load_training_data([other], columns, units)
    assert m.meta["data_fingerprint"] == series_fingerprint(expected)


# ------------------------------------------------------------------------------ flags win
def test_a_flag_given_wins_over_the_config(tmp_path, data):
    cfg = _config(
        tmp_path,
        '[features]\ncurrent_input = "lagged"\nhistory_samples = 2\nhistory_signals = ["x"]\n'
        "[training]\nseed = 2\nsupervised = false\n",
    )
    m = _train(
        data,
        tmp_path / "fwd.json",
        "--config",
        str(cfg),
        "--current-input",
        "commanded",
        "--history-signals",
        "xd",
        "--seed",
        "5",
        "--epochs",
        "3",
    )
    assert m.meta["current_input"] == "commanded" and m.meta["lag_tau_s"] is None
    assert m.input_names[4:] == ["xd_1", "xd_2"]  # samples from the file, signals from the flag
    assert m.meta["split_seed"] == 5
    m0 = _train(data, tmp_path / "fwd0.json", "--config", str(cfg), "--history", "0", *FAST)
    assert m0.input_names == ["x", "xd", "xdd", "current"] and m0.meta["history_samples"] == 0


def test_supervised_flag_wins_over_a_config_without_it(tmp_path, data):
    cfg = _config(tmp_path, "[training]\nsupervised = false\nepochs = 3\n")
    sup = tmp_path / "sup.json"
    argv = ["--config", str(cfg), "--supervised", "--supervised-out", str(sup)]
    argv += ["--features", "manual"]
    _train(data, tmp_path / "fwd.json", *argv)
    assert MLP.load(sup).output_name == "current"


# -------------------------------------------------------------------------------- bad files
BAD = [
    ("[training]\nrestarts = 0\n", "training.restarts: ", ">= 1"),
    ("[features]\nhistory_samples = -1\n", "features.history_samples: ", ">= 0"),
    ('[features]\nhistory_samples = "two"\n', "features.history_samples: ", "an integer"),
    ('[features]\nhistory_signals = ["x", "force"]\n', "features.history_signals: ", "unknown"),
    ('[features]\nhistory_signals = ["x", "x"]\n', "features.history_signals: ", "given twice"),
    ('[features]\nhistory_signals = "x"\n', "features.history_signals: ", "expected a list"),
    (
        "[features]\nhistory_samples = 1\nhistory_signals = []\n",
        "features.history_signals: ",
        "none given",
    ),
    ('[features]\ncurrent_input = "measured"\n', "features.current_input: ", "expected one of"),
    ("[features]\nlag_tau_s = 0.0\n", "features.lag_tau_s: ", "must be positive"),
    ("[features]\nlag_tau_s = -0.005\n", "features.lag_tau_s: ", "must be positive"),
    ("[features]\nhistory = 2\n", "features.history: ", "unknown field"),
    ("[training]\nepochs = 0\n", "training.epochs: ", ">= 1"),
    ("[training]\nseed = -1\n", "training.seed: ", ">= 0"),
    ("[training]\nn_val = 0\n", "training.n_val: ", ">= 1"),
    ("[training]\ni_max_a = -1.0\n", "training.i_max_a: ", "must be positive"),
    ('[training]\nsupervised = "yes"\n', "training.supervised: ", "true or false"),
    ('[training]\nsplit = "shuffled"\n', "training.split: ", "'blocks' or 'random'"),
    ("[training]\nholdout_fraction = 0.6\n", "training.holdout_fraction: ", "(0, 0.5)"),
    ('[features]\nmode = "guess"\n', "features.mode: ", "'auto' or 'manual'"),
    ("[features]\nhistory_stride = 0\n", "features.history_stride: ", ">= 1"),
    ("[features]\nhidden = 0\n", "features.hidden: ", ">= 1"),
    ('[csv]\ncolumns = { pos = "Pos" }\n', "csv.columns.pos: ", "unknown field"),
    ("[csv]\ncolumns = { x = 3 }\n", "csv.columns.x: ", "non-empty string"),
    ('[csv]\nunits = { x = "inch" }\n', "csv.units.x: ", "unknown unit 'inch'"),
    ("[model]\nhidden = 30\n", "model: ", "unknown field"),
    ("history_samples = 2\n", "history_samples: ", "unknown field"),
    ("[features\n", "", "not valid TOML"),
]


@pytest.mark.parametrize(("text", "field", "words"), BAD)
def test_bad_config_field_is_one_config_error_naming_file_and_field(tmp_path, text, field, words):
    cfg = _config(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_train_config(cfg)
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(f"{cfg}: {field}") and words in msg, msg


@pytest.mark.parametrize(("text", "field", "words"), BAD[:3] + BAD[-3:])
def test_mrrig_train_stops_on_a_bad_config_with_one_line_and_exit_2(
    tmp_path, data, capsys, text, field, words
):
    cfg, out = _config(tmp_path, text), tmp_path / "fwd.json"
    rc = mrrig_main(["train", str(data), "--config", str(cfg), "--out", str(out), *FAST])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith(f"error: {cfg}: {field}"), err
    assert words in err and "\n" not in err
    assert not out.exists()


@pytest.mark.process
def test_mrrig_train_process_exits_2_with_one_line_on_a_bad_config(tmp_path, data):
    cfg, out = _config(tmp_path, "[features]\nhistory_samples = -1\n"), tmp_path / "fwd.json"
    r = subprocess.run(
        [sys.executable, "-m", "mrrig", "train", str(data), "--config", str(cfg)]
        + ["--out", str(out), *FAST],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"error: {cfg}: features.history_samples: ")
    assert "must be >= 0" in lines[0]
    assert not out.exists()


def test_a_missing_config_file_is_one_line_naming_it(tmp_path, data, capsys):
    missing = tmp_path / "no-such.toml"
    rc = mrrig_main(["train", str(data), "--config", str(missing), "--out", str(tmp_path / "m")])
    assert rc == 2
    assert capsys.readouterr().err.strip() == f"error: {missing}: file not found"
