"""Rerun recording: written by Recorder, checked by verify_rrd, read back exactly by review (a
writer process ended by SIGTERM: tests/test_recording_signals.py, a process module)."""

from __future__ import annotations

import datetime as dt
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mrrig.loop.samples import FIELDS, SAMPLE_DTYPE, RigState
from mrrig.loop.summary import format_summary, summarize
from mrrig.offline.review import ReviewError, plot_recording, read_recording, verify_rrd
from mrrig.rigio.recording import FIELD_ENTITIES, Recorder, recording_path

REPO = Path(__file__).resolve().parents[1]
PERIOD_S = 0.002


def synthetic_run(n: int, seed: int = 0) -> np.ndarray:
    """IDLE, then ARMED force tracking, then a FAULT with a non-finite model force."""
    rng = np.random.default_rng(seed)
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = 0.1 + np.arange(n) * PERIOD_S + rng.uniform(0.0, 1e-4, n)
    s["counter"] = np.arange(n) % 15
    w = 2 * np.pi * 2.0 * s["t"]
    s["x"] = 0.01 * np.sin(w) + rng.normal(0, 1e-5, n)
    s["x_est"] = 0.01 * np.sin(w)
    s["xd"] = 0.01 * 2 * np.pi * 2.0 * np.cos(w)
    s["xdd"] = -0.01 * (2 * np.pi * 2.0) ** 2 * np.sin(w)
    s["f_des"] = 800.0 * np.tanh(s["xd"] / 0.02)
    s["f_meas"] = s["f_des"] + rng.normal(0, 25.0, n)
    s["f_model"] = s["f_des"] + rng.normal(0, 10.0, n)
    s["i_cmd"] = np.clip(np.abs(s["f_des"]) / 400.0, 0.0, 2.0)
    s["i_meas"] = s["i_cmd"] + rng.normal(0, 0.01, n)
    s["latency_us"] = rng.gamma(4.0, 30.0, n)
    s["state"] = RigState.IDLE
    s["state"][n // 10 : 9 * n // 10] = RigState.ARMED
    s["state"][9 * n // 10 :] = RigState.FAULT
    s["i_cmd"][s["state"] != RigState.ARMED] = 0.0
    s["f_model"][9 * n // 10] = np.nan
    return s


def run_events(s: np.ndarray) -> list[dict]:
    n = s.size
    t_arm, t_fault = float(s["t"][n // 10]), float(s["t"][9 * n // 10])
    return [
        {"t": t_arm, "level": "INFO", "text": "state IDLE -> ARMED", "kind": "state"},
        # a fault and its state change in the same cycle: two events at one time
        {
            "t": t_fault,
            "level": "ERROR",
            "text": "fault: non-finite model force",
            "kind": "fault",
            "reason": "non_finite",
        },
        {"t": t_fault, "level": "WARN", "text": "state ARMED -> FAULT", "kind": "state"},
    ]


def write_recording(path: Path, s: np.ndarray, events: list[dict], summary: dict | None) -> None:
    with Recorder(path, "rig1", flush_interval_s=0.5) as rec:
        for k in range(0, s.size, 10):  # 20 ms batches, as the sidecar hands them over
            batch = s[k : k + 10]
            rec.add_samples(batch)
            for ev in events:
                if batch["t"][0] <= ev["t"] <= batch["t"][-1]:
                    extra = {k: v for k, v in ev.items() if k not in ("t", "level", "text")}
                    rec.add_event(ev["t"], ev["level"], ev["text"], **extra)
        if summary is not None:
            rec.add_summary(summary)


def assert_same(a: object, b: object) -> None:
    """Equality of nested summary values with NaN equal to NaN."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            assert_same(a[k], b[k])
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b)
    else:
        assert a == b


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, list[dict], dict]:
    path = tmp_path_factory.mktemp("rec") / "rig1-run.rrd"
    s = synthetic_run(4000)
    events = run_events(s)
    summary = summarize(s, events, {"frames_received": 4003, "invalid_frames": 3})
    write_recording(path, s, events, summary)
    return path, s, events, summary


@pytest.fixture(scope="module")
def read_back(run: tuple[Path, np.ndarray, list[dict], dict]):
    return read_recording(run[0])


def test_every_sample_field_has_an_entity() -> None:
    assert set(FIELD_ENTITIES) == set(FIELDS)
    assert len(set(FIELD_ENTITIES.values())) == len(FIELDS)


def test_recording_path_is_rig_and_utc_time() -> None:
    now = dt.datetime(2025, 1, 14, 10, 30, 12, tzinfo=dt.timezone(dt.timedelta(hours=1)))
    p = recording_path("recordings", "rig1", now)
    assert p == Path("recordings/rig1-20250114T093012Z.rrd")


def test_closed_recording_verifies(run) -> None:
    verify_rrd(run[0])


def test_verify_rejects_a_file_that_is_not_rrd(tmp_path: Path) -> None:
    bad = tmp_path / "notes.rrd"
    bad.write_text("not a recording\n")
    with pytest.raises(ReviewError, match="notes.rrd"):
        verify_rrd(bad)


def test_verify_rejects_a_truncated_recording(run, tmp_path: Path) -> None:
    cut = tmp_path / "cut.rrd"
    data = run[0].read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ReviewError, match="cut.rrd"):
        verify_rrd(cut)


def test_read_back_gives_every_sample_bit_equal(run, read_back) -> None:
    s = run[1]
    got = read_back.samples
    assert got.dtype == SAMPLE_DTYPE
    assert got.size == s.size
    for field in FIELDS:
        # bit equality, NaN payloads included
        assert got[field].tobytes() == s[field].tobytes(), field


def test_read_back_gives_events_in_order_with_fields(run, read_back) -> None:
    assert read_back.events == run[2]


def test_read_back_gives_the_stored_summary(run, read_back) -> None:
    assert_same(read_back.summary, run[3])


def test_summary_of_read_back_equals_summary_of_original(run, read_back) -> None:
    _, s, events, _ = run
    counters = {"frames_received": 4003}
    assert_same(
        summarize(read_back.samples, read_back.events, counters), summarize(s, events, counters)
    )


def test_read_recording_rejects_missing_and_non_rrd_files(tmp_path: Path, capfd) -> None:
    with pytest.raises(ReviewError, match="absent.rrd"):
        read_recording(tmp_path / "absent.rrd")
    for name, content in (("junk.rrd", b"\x00" * 4096), ("notes.rrd", b"# mrrig notes\n")):
        bad = tmp_path / name
        bad.write_bytes(content)
        with pytest.raises(ReviewError, match=f"{name}: not an .rrd file") as e:
            read_recording(bad)
        assert "\n" not in str(e.value)
    # the one-line error alone: the reader was not started, so it logged no warning of its own
    assert capfd.readouterr().err == ""


_READS = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from mrrig.offline.review import read_recording

    def counts():
        sockets = 0
        for fd in Path("/proc/self/fd").iterdir():
            try:
                sockets += os.readlink(fd).startswith("socket:")
            except OSError:
                continue
        return sockets, len(os.listdir("/proc/self/task"))

    def settled(within):
        # the last read's client connection closes on rerun's runtime after read_recording
        # returns, and the runtime's idle blocking threads end after 10 s idle (more of them
        # start on a loaded machine): wait up to 12 s for the counts to come back within the
        # bounds; a server or thread left per read stays
        t_end = time.monotonic() + 12.0
        while not within(now := counts()) and time.monotonic() < t_end:
            time.sleep(0.2)
        return now

    reads = int(sys.argv[2])
    for _ in range(5):
        read_recording(sys.argv[1])
    before = counts()
    for _ in range(reads):
        read_recording(sys.argv[1])
    print(*before, *settled(lambda c: c[0] <= before[0] and c[1] - before[1] < reads // 4))
    """
)


def test_read_recording_leaves_no_server_or_new_threads(run) -> None:
    # in an interpreter of its own: the worker's threads from other tests (torch's, zenoh's)
    # come and go on their own. The first reads start rerun's shared runtime pool (it can grow
    # lazily to its size); a server or thread left behind per read grows with every read
    reads = 20
    out = subprocess.run(
        [sys.executable, "-c", _READS, str(run[0]), str(reads)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout.split()
    sockets, threads, sockets_after, threads_after = map(int, out)
    assert sockets_after <= sockets
    assert threads_after - threads < reads // 4


def test_recording_without_samples_reads_back_empty(tmp_path: Path) -> None:
    path = tmp_path / "empty.rrd"
    with Recorder(path, "rig1") as rec:
        rec.add_event(0.5, "INFO", "started", kind="state")
    verify_rrd(path)
    back = read_recording(path)
    assert back.samples.size == 0 and back.summary is None
    assert back.events == [{"t": 0.5, "level": "INFO", "text": "started", "kind": "state"}]


def test_data_after_close_is_dropped_and_close_is_idempotent(tmp_path: Path) -> None:
    path = tmp_path / "twice.rrd"
    s = synthetic_run(300)
    rec = Recorder(path, "rig1")
    rec.add_samples(s[:200])
    rec.close()
    rec.add_samples(s[200:])
    rec.close()
    assert read_recording(path).samples.size == 200


_WRITER = textwrap.dedent(
    """
    import signal, sys, time
    import numpy as np
    from mrrig.rigio.recording import Recorder
    from mrrig.loop.samples import SAMPLE_DTYPE

    path, handled = sys.argv[1], sys.argv[2] == "handled"
    rec = Recorder(path, "rig1", flush_interval_s=0.2)
    handed = 0
    if handled:
        def on_term(signum, frame):
            rec.close()
            print("handed", handed, flush=True)
            sys.exit(0)
        signal.signal(signal.SIGTERM, on_term)
    batch = np.zeros(10, dtype=SAMPLE_DTYPE)
    while True:
        batch["t"] = (handed + np.arange(10)) * 0.002
        batch["f_meas"] = np.sin(batch["t"])
        batch["counter"] = (handed + np.arange(10)) % 15
        rec.add_samples(batch)
        handed += 10
        if handed == 200:
            print("ready", flush=True)
        time.sleep(0.002)
    """
)


def _start_writer(path: Path, mode: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path), mode],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def test_plot_recording_writes_a_png(read_back, tmp_path: Path) -> None:
    out = plot_recording(read_back, tmp_path / "run.png")
    data = out.read_bytes()
    assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 10_000


def test_format_summary_names_every_metric(run) -> None:
    text = format_summary(run[3])
    for word in ("Et", "frames", "p95", "p99.9", "non_finite", "frames_received"):
        assert word in text


def test_a_recording_from_before_the_later_fields_reads_them_as_nan(tmp_path, monkeypatch):
    """Recordings made before the adaptation's and the temperature's fields still load."""
    import mrrig.rigio.recording as recording
    from mrrig.rigio.recording import LATER_FIELDS

    s = synthetic_run(300)
    older = {k: v for k, v in FIELD_ENTITIES.items() if k not in LATER_FIELDS}
    monkeypatch.setattr(recording, "FIELD_ENTITIES", older)
    path = tmp_path / "old.rrd"
    write_recording(path, s, run_events(s), None)
    monkeypatch.undo()
    back = read_recording(path).samples
    assert back.size == s.size
    for field in LATER_FIELDS:
        assert np.isnan(back[field]).all()
    np.testing.assert_array_equal(back["f_meas"], s["f_meas"])


@pytest.mark.parametrize("window", [300, 1 << 16])
def test_a_later_field_is_not_written_until_its_first_value_and_reads_back_nan_before_it(
    tmp_path, window
):
    """A run without adaptation or HIL writes none of their series (a series costs about 24
    bytes a frame in the file, NaN or not); adaptation that starts mid-run is written from its
    first value, and every frame reads back, NaN before it (issue 42: recordings' size)."""
    from mrrig.offline.rrd_scan import open_rrd, scan_recording
    from mrrig.rigio.recording import LATER_FIELDS

    s = synthetic_run(1000)
    for field in LATER_FIELDS:
        if field != "temp_degc":
            s[field] = np.nan
    s["adapt_gain"][600:] = 1.0 + np.arange(400) * 1e-4  # adaptation from frame 600 on
    path = tmp_path / "sparse.rrd"
    write_recording(path, s, run_events(s), None)
    got: list[np.ndarray] = []
    scan = scan_recording(path, got.append, window=window)
    back = np.concatenate(got)
    absent = {f for f in LATER_FIELDS if f not in ("temp_degc", "adapt_gain")}
    series = {c.entity_path for c in open_rrd(path).stream() if not c.is_static}
    assert not {f"/{FIELD_ENTITIES[f]}" for f in absent} & series  # no series written
    assert f"/{FIELD_ENTITIES['adapt_gain']}" in series
    assert back.size == s.size and scan.dropped == 0  # every frame, none dropped
    assert np.isnan(back["adapt_gain"][:600]).all()
    np.testing.assert_array_equal(back["adapt_gain"][600:], s["adapt_gain"][600:])
    for field in absent:
        assert np.isnan(back[field]).all()
    np.testing.assert_array_equal(back["f_meas"], s["f_meas"])
    np.testing.assert_array_equal(back["temp_degc"], s["temp_degc"])
