"""`mrrig characterize` and `mrrig validate`: the matrix, its files, resuming, model switching,
and the rig workflow characterize -> train -> validate from the command line."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.offline.characterize import (
    TIDY_HEADER,
    CharacterizeConfig,
    Interrupted,
    MatrixSection,
    MatrixStore,
    Run,
    append_tidy,
    characterize,
    load_characterize_config,
    matrix_runs,
)
from mrrig.offline.review import read_recording
from mrrig.offline.training import load_tidy
from mrrig.offline.validate import track_with_attempts
from mrrig.rigio.rig_session import SERVER_NICE, RigSession
from mrrig.typed_config import ConfigError
from tests.conftest import REPO, OutputWatch, rig_config, stall
from tests.rig_harness import ThreadRig
from tests.stall_proof import explain

TINY = MatrixSection(
    amplitudes_m=(0.015,),
    freqs_hz=(3.0,),
    currents_a=(0.0, 1.2),
    settle_s=0.6,
    duration_s=0.4,
    attempts=3,
)


# ------------------------------------------------------------------------------ the matrix
def test_default_matrix_is_the_papers_150_runs_current_outermost():
    cfg = load_characterize_config(REPO / "configs/characterize.toml")
    assert cfg.matrix == CharacterizeConfig().matrix  # the file states the defaults
    runs = matrix_runs(cfg.matrix)
    assert len(runs) == 150
    assert [r.run_id for r in runs] == list(range(150))
    assert {r.amplitude_m for r in runs} == {0.010, 0.015, 0.020}
    assert {r.freq_hz for r in runs} == {2.0, 3.0, 4.0, 5.0, 6.0}
    assert sorted({r.current_a for r in runs}) == pytest.approx([0.2 * k for k in range(10)])
    assert runs[0] == Run(0, 0.010, 2.0, 0.0)
    assert runs[1] == Run(1, 0.015, 2.0, 0.0)  # amplitude innermost
    assert runs[15].current_a == pytest.approx(0.2)  # current outermost


def test_matrix_out_of_range_values_are_refused_with_the_field_named(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text("[matrix]\namplitudes_m = [0.05]\n")
    with pytest.raises(ConfigError, match="matrix.amplitudes_m"):
        load_characterize_config(path)


# ------------------------------------------------------------------------------ the files
def _samples(n: int, t0_s: float, current_a: float) -> np.ndarray:
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = t0_s + 0.002 * np.arange(n)
    s["x"] = 0.01 * np.sin(2 * np.pi * 3 * s["t"])
    s["x_est"] = s["x"] + 1e-6
    s["xd"] = 0.01 * 2 * np.pi * 3 * np.cos(2 * np.pi * 3 * s["t"])
    s["xdd"] = -((2 * np.pi * 3) ** 2) * s["x"]
    s["f_meas"] = 1000.0 * s["xd"] * (1 + current_a)
    s["i_cmd"] = current_a
    s["i_meas"] = current_a * 0.98
    s["state"] = RigState.ARMED
    return s


def test_tidy_rows_are_the_daemons_estimates_and_load_back_exactly(tmp_path):
    s = _samples(50, 12.5, 0.8)
    path = tmp_path / "m.csv"
    with path.open("w") as fh:
        fh.write(",".join(TIDY_HEADER) + "\n")
        append_tidy(fh, 7, s, t0_s=12.5)
    back = load_tidy(path)
    assert np.all(back.run_id == 7)
    np.testing.assert_array_equal(back.t, s["t"] - 12.5)
    np.testing.assert_array_equal(back.x, s["x_est"])  # the Kalman estimate, not the sensor
    np.testing.assert_array_equal(back.xd, s["xd"])
    np.testing.assert_array_equal(back.xdd, s["xdd"])
    np.testing.assert_array_equal(back.force, s["f_meas"])
    np.testing.assert_array_equal(back.current, s["i_cmd"])
    meas = np.loadtxt(path, delimiter=",", skiprows=1)[:, 7]
    np.testing.assert_array_equal(meas, s["i_meas"])


def test_rerun_drops_rows_of_an_unfinished_run_and_keeps_the_finished_ones(tmp_path):
    runs = matrix_runs(TINY)
    store = MatrixStore(tmp_path, TINY)
    store.save("test", runs[0], _samples(200, 3.0, 0.0), attempts=1)
    rrd = store.rrd_path(runs[0])
    assert read_recording(rrd).samples.size == 200
    # a crash after run 1's rows were appended, before done.json listed it
    with store.csv_path.open("a") as fh:
        append_tidy(fh, 1, _samples(120, 9.0, 1.2), t0_s=9.0)
        fh.write("1,0.5,0.001")  # and a row cut off midway
    again = MatrixStore(tmp_path, TINY)
    assert set(again.done) == {0}
    data = load_tidy(again.csv_path)
    assert set(data.run_id.tolist()) == {0}
    assert data.t.size == 200


def test_a_done_run_without_its_rows_is_redone(tmp_path):
    runs = matrix_runs(TINY)
    store = MatrixStore(tmp_path, TINY)
    store.save("test", runs[0], _samples(200, 3.0, 0.0), attempts=1)
    store.csv_path.unlink()
    assert MatrixStore(tmp_path, TINY).done == {}


def test_an_output_directory_of_another_matrix_is_refused(tmp_path):
    store = MatrixStore(tmp_path, TINY)
    store.save("test", matrix_runs(TINY)[0], _samples(200, 3.0, 0.0), attempts=1)
    other = MatrixSection(amplitudes_m=(0.02,), freqs_hz=(3.0,), currents_a=(0.0, 1.2))
    with pytest.raises(ConfigError, match="another matrix"):
        MatrixStore(tmp_path, other)


def _watch(store: MatrixStore, n_done: int, stop: threading.Event) -> threading.Thread:
    """Set `stop` (as Ctrl-C would) once `n_done` runs are recorded."""

    def run() -> None:
        end = time.monotonic() + 60
        while len(store.done) < n_done and time.monotonic() < end:
            time.sleep(0.005)
        stop.set()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


@pytest.mark.process
def test_interrupted_matrix_resumes_without_repeating_finished_runs(tmp_path):
    runs = matrix_runs(TINY)
    out = tmp_path / "char"
    with ThreadRig() as rig:
        cfg = rig.daemon_config(tmp_path, controller={"name": "constant", "current_a": 0.0})
        store = MatrixStore(out, TINY)
        stop = threading.Event()
        with RigSession(cfg) as session:
            _watch(store, 1, stop)
            with pytest.raises(Interrupted):
                characterize(session, store, runs, stop)
            assert session.state() is not RigState.ARMED  # SAFE after the interruption
            rig.explain_faults(session)
        assert set(store.done) == {0}
        first = dict(store.done[0])
        mtime = store.rrd_path(runs[0]).stat().st_mtime_ns
        store = MatrixStore(out, TINY)
        with RigSession(cfg) as session:
            characterize(session, store, runs, threading.Event())
            rig.explain_faults(session)
    assert set(store.done) == {0, 1}
    assert store.done[0] == first  # not repeated
    assert store.rrd_path(runs[0]).stat().st_mtime_ns == mtime
    data = load_tidy(store.csv_path)
    for r in runs:
        rows = data.run_id == r.run_id
        assert rows.sum() == store.done[r.run_id]["samples"]  # each run's rows once
        assert np.all(data.current[rows] == r.current_a)
        assert read_recording(store.rrd_path(r)).samples.size == rows.sum()
    f0 = np.abs(data.force[data.run_id == 0]).max()
    f1 = np.abs(data.force[data.run_id == 1]).max()
    print(f"peak force: {f0:.0f} N at 0 A, {f1:.0f} N at 1.2 A; samples per run: {store.done}")
    assert f1 > 2 * f0  # the current reached the damper


@pytest.mark.process
def test_a_run_that_succeeds_on_its_second_attempt_is_no_failed_run(tmp_path):
    runs = matrix_runs(TINY)
    with ThreadRig() as rig:
        cfg = rig.daemon_config(tmp_path, controller={"name": "constant", "current_a": 0.0})
        store = MatrixStore(tmp_path / "char", TINY)

        def stall_the_last_run() -> None:  # 0.2 s without a sensor frame, 0.5 s into it
            end = time.monotonic() + 60
            while len(store.done) < 1 and time.monotonic() < end:
                time.sleep(0.005)
            time.sleep(0.5)
            rig.hold(0.2)

        threading.Thread(target=stall_the_last_run, daemon=True).start()
        with RigSession(cfg) as session:
            failed = characterize(session, store, runs, threading.Event())
            rig.explain_faults(session)
    assert failed == []
    last = store.done[runs[-1].run_id]
    # the injected stall failed one attempt; a stall of the machine may fail another, and
    # explain_faults above has put each such fault inside a stall the simulator measured
    assert last["attempts"] == len(last["failed_attempts"]) + 1 >= 2, last


def clean_window(session: RigSession) -> dict:
    """A tracking window as `mrrig validate` keeps it: tried again (3 windows at most) while
    only a transport fault faulted it; the test then proves those faults were stalls."""
    return track_with_attempts(session, 0.6, 1.0, 3, threading.Event())


@pytest.mark.process
def test_validate_switches_models_with_set_model_while_disarmed(tmp_path, sim_model):
    other = tmp_path / "other-model.json"
    shutil.copy(sim_model, other)
    with ThreadRig() as rig:
        cfg = rig.daemon_config(
            tmp_path,
            controller={"name": "network_inversion", "model": str(sim_model)},
            actuator={"waveform": "sine", "amplitude_m": 0.015, "frequency_hz": 2.0},
            control={"model_dirs": [str(tmp_path)]},
        )
        with RigSession(cfg) as session:
            first = clean_window(session)
            session.request(cmd="reset")  # a transport fault of its last window, if any
            session.request(cmd="arm")
            refused = session.ask({"cmd": "set_model", "path": str(other)})
            assert not refused["ok"] and "not armed" in refused["error"]
            session.request(cmd="disarm")
            session.request(cmd="set_model", path=str(other))
            assert session.loop.daemon.cfg.controller.model == other
            second = clean_window(session)
            rig.explain_faults(session)
    print(f"Et with the model: {first['et']:.4f}; after set_model: {second['et']:.4f}")
    for r in (first, second):
        assert r["armed_frames"] >= 450
        assert math.isfinite(r["et"]) and r["et"] < 0.2
        assert r["faults"] == []


# ------------------------------------------------------------------------------ processes
def _mrrig(procs, *args: str) -> subprocess.Popen:
    return procs(
        ["-m", "mrrig", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


SHORT = REPO / "configs/characterize-short.toml"
N_SHORT = len(matrix_runs(load_characterize_config(SHORT).matrix))


def _four_short_runs(path: Path) -> Path:
    """A matrix of four of the short matrix's runs (its settle and duration, its two
    amplitudes, its first frequency, its lowest and highest current): what resuming needs,
    runs before the interruption and after it (the short matrix's 20 took 38 s more of the rig)."""
    m = load_characterize_config(SHORT).matrix
    path.write_text(
        f"[matrix]\namplitudes_m = {list(m.amplitudes_m)}\nfreqs_hz = [{m.freqs_hz[0]}]\n"
        f"currents_a = [{m.currents_a[0]}, {m.currents_a[-1]}]\nsettle_s = {m.settle_s}\n"
        f"duration_s = {m.duration_s}\nattempts = {m.attempts}\n"
    )
    return path


def _sim(procs, bridge: str, stats: Path) -> subprocess.Popen:
    """The simulator, measuring its stalls (and the bridge's) into `stats` at its exit."""
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--measure-echo", "--stats", str(stats)]
    )  # fmt: skip
    time.sleep(1.0)
    assert sim.poll() is None
    return sim


def _sim_stats(sim: subprocess.Popen, stats: Path) -> dict:
    sim.send_signal(signal.SIGTERM)
    assert sim.wait(timeout=30) == 0
    return json.loads(stats.read_text())


def _failed_attempts(out: Path) -> list[dict]:
    """characterize's failed attempts (done.json), their faults timed on CLOCK_MONOTONIC."""
    runs = json.loads((out / "done.json").read_text())["runs"].values()
    failed = [a for r in runs for a in r["failed_attempts"]]
    print(f"characterize: failed attempts {failed}")
    assert all("clock_s" in a for a in failed), failed  # each failed on a fault, with its time
    return [{"t": a["clock_s"], "reason": a["fault"]} for a in failed]


def _failed_attempts_stalls(out: Path) -> dict:
    """The loop's kernel-measured stalls before each failed attempt's fault, on
    CLOCK_MONOTONIC (a daemon summary's `kernel_stalls` with time zero 0)."""
    runs = json.loads((out / "done.json").read_text())["runs"].values()
    failed = [a for r in runs for a in r["failed_attempts"]]
    return {"windows": [w for a in failed for w in a.get("kernel_windows", [])]}


def _report_faults(r: dict) -> list[dict]:
    """A validate report's faults, kept and discarded, with `t` on its daemon's clock."""
    return [*r["faults"], *r["discarded_faults"]]


_TOOL = """
import sys, time
from mrrig.config import load_config
from mrrig.rigio.rig_session import RigSession, rig_overrides
cfg = load_config(sys.argv[1], rig_overrides(None, True))
with RigSession(cfg) as session:
    session.request(cmd="arm")
    print(session.loop.pid, flush=True)
    time.sleep(60)
"""


@pytest.mark.process
def test_the_loop_process_ends_safe_when_its_tool_is_killed(tmp_path, bridge, procs):
    """A tool's daemon loop runs in a process of its own; SIGKILL of the tool (no close, no
    disarm) still ends that loop, SAFE: the closed pipe stops it, and its last commands to
    the firmware are SAFE ones, not ACTIVE."""
    sim_stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, sim_stats)
    rig = rig_config(tmp_path, bridge, None, controller={"name": "constant", "current_a": 0.5})
    tool = procs(["-c", _TOOL, str(rig)], stdout=subprocess.PIPE, text=True)
    line = tool.stdout.readline()
    assert line.strip().isdigit(), f"the tool printed no loop pid: {line!r}"
    loop_pid = int(line)
    time.sleep(0.5)
    if os.geteuid() == 0:  # permitted: the pipe server (the process's main thread) favoured
        stat = Path(f"/proc/{loop_pid}/task/{loop_pid}/stat").read_text()
        assert int(stat.rsplit(")", 1)[1].split()[16]) == SERVER_NICE, stat
    tool.kill()
    tool.wait(timeout=10)
    end = time.monotonic() + 10
    while time.monotonic() < end and _alive(loop_pid):
        time.sleep(0.05)
    assert not _alive(loop_pid), "the loop process outlived its killed tool"
    events = [e["event"] for e in _sim_stats(sim, sim_stats)["fault_events"]]
    print(events)
    assert any("after SAFE commands" in e for e in events), events
    assert not any("after ACTIVE commands" in e for e in events), events


def _alive(pid: int) -> bool:
    """The process exists and is no zombie (its parent, killed, no longer reaps it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.process
def test_characterize_train_validate_from_the_command_line(tmp_path, bridge, procs):
    """The acceptance test of issue 5: three commands in separate processes on the simulator.
    Each command runs once; every fault it met lies inside a stall the simulator measured."""
    sim_stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, sim_stats)
    rig = rig_config(tmp_path, bridge, None)
    out, model, report = tmp_path / "char", tmp_path / "model.json", tmp_path / "val.json"
    t0 = time.monotonic()
    p = _mrrig(procs, "characterize", "--config", str(SHORT), "--rig-config", str(rig),
               "--out", str(out))  # fmt: skip
    log_char, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log_char
    t1 = time.monotonic()
    p = _mrrig(procs, "train", str(out / "matrix.csv"), "--out", str(model), "--no-supervised",
               "--features", "manual")  # fmt: skip
    log_train, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log_train
    t2 = time.monotonic()
    p = _mrrig(
        procs, "validate", str(model), "--rig-config", str(rig),
        "--duration", "5", "--json", str(report),
    )  # fmt: skip
    log_val, _ = p.communicate(timeout=120)
    t3 = time.monotonic()
    print(log_val)
    print(f"characterize {t1 - t0:.1f} s, train {t2 - t1:.1f} s, validate {t3 - t2:.1f} s")
    st = _sim_stats(sim, sim_stats)
    explain(st, _failed_attempts(out), 0.0, _failed_attempts_stalls(out))
    (r,) = json.loads(report.read_text())["reports"]
    explain(st, _report_faults(r), r["clock_t0_s"], r["kernel_stalls"])
    assert p.returncode == 0, log_val  # the kept window has no fault
    assert 1 <= r["attempts"] <= 3 and (r["attempts"] > 1) == bool(r["discarded_faults"])
    done = json.loads((out / "done.json").read_text())
    assert len(done["runs"]) == N_SHORT
    assert sorted(out.glob("run-*.rrd")) == [out / f"run-{k:03d}.rrd" for k in range(N_SHORT)]
    assert json.loads(model.read_text())["meta"]["data_files"] == [str(out / "matrix.csv")]
    assert r["model"] == str(model)
    assert "Et " in log_val and r["armed_frames"] >= 2400
    print(f"validate: Et {r['et']:.4f}, |error| p95 {r['tracking_error_n']['p95']:.1f} N")
    # the trained inversion beats a constant 0.8 A, the reference's mean current (Et 0.28 in
    # the same setup; docs/measurements.md)
    assert math.isfinite(r["et"]) and r["et"] < 0.25


@pytest.mark.process
def test_validate_tries_a_window_again_after_a_transport_fault(tmp_path, bridge, procs, sim_model):
    """The simulator stopped for 100 ms while validate tracks: that window faults (no sensor
    frame within the timeout) and is tried again; the report keeps the discarded fault, and
    the simulator measured the stall that explains it."""
    sim_stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, sim_stats)
    rig = rig_config(tmp_path, bridge, None)
    report = tmp_path / "val.json"
    p = _mrrig(
        procs, "validate", str(sim_model), "--rig-config", str(rig),
        "--duration", "2", "--json", str(report),
    )  # fmt: skip
    out = OutputWatch(p, "state: armed (was IDLE)")
    assert out.seen.wait(60), out.text()
    time.sleep(0.5)
    stall(sim.pid, 0.1)
    rc = p.wait(120)
    out.join()
    log = out.text()
    print(log[-2500:])
    st = _sim_stats(sim, sim_stats)
    (r,) = json.loads(report.read_text())["reports"]
    explained = explain(st, _report_faults(r), r["clock_t0_s"], r["kernel_stalls"])
    assert any(w.end_s - w.start_s >= 0.09 for _, w in explained), explained  # ours
    assert r["attempts"] >= 2, log
    assert "trying the window again" in log and "windows discarded for a transport fault" in log
    assert rc == 0 and r["faults"] == [], log
    assert r["armed_frames"] >= 950, log


@pytest.mark.process
def test_interrupted_characterize_command_resumes_without_repeating_runs(tmp_path, bridge, procs):
    sim_stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, sim_stats)
    rig = rig_config(tmp_path, bridge, None)
    out = tmp_path / "char"
    four = _four_short_runs(tmp_path / "characterize-four.toml")
    n_runs = len(matrix_runs(load_characterize_config(four).matrix))
    assert n_runs == 4
    args = ("--config", str(four), "--rig-config", str(rig))
    p = _mrrig(procs, "characterize", *args, "--out", str(out))
    done_path = out / "done.json"
    end = time.monotonic() + 60
    while time.monotonic() < end:
        if done_path.is_file() and json.loads(done_path.read_text())["runs"]:
            break
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    log, _ = p.communicate(timeout=30)
    assert p.returncode == 130, log
    assert "run the same command again to resume" in log
    first = json.loads(done_path.read_text())["runs"]
    assert 1 <= len(first) < n_runs
    mtimes = {k: (out / f"run-{int(k):03d}.rrd").stat().st_mtime_ns for k in first}
    p = _mrrig(procs, "characterize", *args, "--out", str(out))
    log, _ = p.communicate(timeout=120)
    assert p.returncode == 0, log
    assert f"{len(first)} of {n_runs} runs already recorded" in log
    explain(_sim_stats(sim, sim_stats), _failed_attempts(out), 0.0, _failed_attempts_stalls(out))
    runs = json.loads(done_path.read_text())["runs"]
    assert set(runs) == {str(k) for k in range(n_runs)}
    for k, entry in first.items():
        assert runs[k] == entry
        assert (out / f"run-{int(k):03d}.rrd").stat().st_mtime_ns == mtimes[k]
    data = load_tidy(out / "matrix.csv")
    counts = np.bincount(data.run_id)
    assert counts.tolist() == [runs[str(k)]["samples"] for k in range(n_runs)]
