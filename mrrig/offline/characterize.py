"""`mrrig characterize`: the characterization test matrix (modeling spec 4 B) on the rig.

For each run (amplitude x frequency x current, paper Table 1): constant current, actuator sine,
arm, wait `settle_s` (actuator ramp, coil lag), keep `duration_s` of ARMED samples, disarm.
Each finished run is written to `DIR/run-NNN.rrd`, appended to `DIR/matrix.csv` (tidy:
`mrrig.offline.datasets.TIDY_HEADER`) and then listed in `DIR/done.json` (written last, atomically):
a rerun skips the runs listed there and drops any rows of unlisted runs from matrix.csv, so a
run interrupted midway is redone from scratch. A run with a fault or missing samples is tried
again (`attempts`), then left for the next invocation (exit 1). Ctrl-C/SIGTERM: SAFE, actuator
STOP, exit 130.

The daemon's loop runs in a process of its own (`mrrig.rigio.rig_session.RigSession`); the tool
drives it with control requests between runs (never per frame).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
import os
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from mrrig import json_text
from mrrig.catalog.record import CHARACTERIZATION_PLAN
from mrrig.cli_args import HelpFormatter
from mrrig.config import DaemonConfig, load_config
from mrrig.errors import MrrigError
from mrrig.loop.samples import RigState
from mrrig.loop.summary import summarize
from mrrig.offline.datasets import TIDY_HEADER, dataset_b_conditions
from mrrig.rigio.recording import Recorder
from mrrig.rigio.rig_session import (
    Interrupted,
    RigError,
    RigSession,
    RunFailed,
    rig_overrides,
    stop_on_signals,
)
from mrrig.typed_config import ConfigError, load_toml, parse

log = logging.getLogger(__name__)

FLUSH_MARGIN_S = 0.1  # the loop hands samples over in batches of telemetry_batch frames
MIN_SAMPLE_FRACTION = 0.95  # a run with fewer samples than this of duration/period is redone
# Disarmed pause before another attempt: the firmware reports a watchdog trip in its next
# RigStatus (10 Hz); arming again at once would fault on that old trip.
RETRY_PAUSE_S = 1.0
KERNEL_NEAR_S = 1.0  # a failed attempt keeps the loop's kernel-measured stalls this long before
MAX_FAILED_IN_A_ROW = 3  # then the rig is taken to be unusable and the tool stops
RUN_OVERHEAD_S = 0.5  # requests and file writing per run, for the first time-left estimate
DONE_FILE = "done.json"
MATRIX_FILE = "matrix.csv"
EXIT_INTERRUPTED = 130


# ---------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class MatrixSection:
    """Paper Table 1: 3 amplitudes x 5 frequencies x 10 currents = 150 runs."""

    amplitudes_m: tuple[float, ...] = (0.010, 0.015, 0.020)
    freqs_hz: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 6.0)
    currents_a: tuple[float, ...] = tuple(round(0.2 * k, 1) for k in range(10))
    settle_s: float = 1.0  # after arming: the actuator's 0.5 s ramp and the coil's lag
    duration_s: float = 2.0  # kept per run
    attempts: int = 3  # tries per run before the tool stops

    def check(self) -> None:
        if not (self.amplitudes_m and self.freqs_hz and self.currents_a):
            raise ValueError("amplitudes_m, freqs_hz, currents_a: must not be empty")
        if not all(0 < a <= 0.04 for a in self.amplitudes_m):
            raise ValueError("amplitudes_m: each must be in (0, 0.04] m")
        if not all(0 < f <= 20 for f in self.freqs_hz):
            raise ValueError("freqs_hz: each must be in (0, 20] Hz")
        if not all(i >= 0 for i in self.currents_a):
            raise ValueError("currents_a: each must be >= 0 A")
        if not (self.settle_s >= 0 and self.duration_s > 0):
            raise ValueError("settle_s, duration_s: settle_s >= 0 and duration_s > 0")
        if self.attempts < 1:
            raise ValueError("attempts: must be at least 1")


@dataclass(frozen=True)
class OutputSection:
    directory: Path = Path("recordings/characterization")


@dataclass(frozen=True)
class CharacterizeConfig:
    matrix: MatrixSection = field(default_factory=MatrixSection)
    output: OutputSection = field(default_factory=OutputSection)


def load_characterize_config(path: str | Path) -> CharacterizeConfig:
    return parse(CharacterizeConfig, load_toml(path), str(path))


@dataclass(frozen=True)
class Run:
    run_id: int
    amplitude_m: float
    freq_hz: float
    current_a: float

    def label(self) -> str:
        return f"{self.amplitude_m * 1e3:g} mm, {self.freq_hz:g} Hz, {self.current_a:.2f} A"


def matrix_runs(m: MatrixSection) -> list[Run]:
    """The runs in paper Table 1's order (current outermost); the index is the run id."""
    rows = dataset_b_conditions(m.amplitudes_m, m.freqs_hz, m.currents_a)
    return [Run(k, float(a), float(f), float(i)) for k, (a, f, i) in enumerate(rows)]


# ---------------------------------------------------------------------------------- one run
def record_run(
    session: RigSession, run: Run, m: MatrixSection, stop: threading.Event
) -> np.ndarray:
    """One run on the rig: its ARMED samples of the kept window (RunFailed if not clean)."""
    session.request(cmd="disarm")
    session.request(cmd="set_controller", name="constant", current_a=run.current_a)
    session.request(
        cmd="actuator", waveform="sine", amplitude_m=run.amplitude_m, frequency_hz=run.freq_hz
    )
    session.take(math.inf, math.inf)  # drop what came before this run
    # the tool's documented choice, explicit: a fault of the attempt or run before (the
    # daemon's log names it) is acknowledged, and the run tried on it
    session.request(cmd="reset")
    session.request(cmd="arm")
    t_start = session.now() + m.settle_s
    t_end = t_start + m.duration_s
    try:
        session.wait_until(t_end + FLUSH_MARGIN_S, stop)
        session.wait_samples(t_end, stop)
    finally:
        session.request(cmd="disarm")
    s, events = session.take(t_start, t_end)
    faults = [e for e in events if e["kind"] == "fault"]
    if faults:
        raise RunFailed(f"fault: {faults[0]['reason']}", faults[0])
    expected = m.duration_s / session.period_s
    if s.size < MIN_SAMPLE_FRACTION * expected:
        raise RunFailed(f"{s.size} samples, expected about {expected:.0f}")
    if np.any(s["state"] != RigState.ARMED):
        raise RunFailed("not ARMED for the whole window")
    return s


def append_tidy(fh: TextIO, run_id: int, s: np.ndarray, t0_s: float) -> None:
    """Rows of `TIDY_HEADER`: x = the daemon's Kalman displacement, its xd/xdd, the load
    cell, the commanded and measured current; time from the window's start."""
    cols = (
        s["t"] - t0_s,
        s["x_est"],
        s["xd"],
        s["xdd"],
        s["f_meas"],
        s["i_cmd"],
        s["i_meas"],
    )
    rows = zip(*(c.tolist() for c in cols), strict=True)
    fh.writelines(f"{run_id}," + ",".join(map(repr, r)) + "\n" for r in rows)


def write_run_recording(path: Path, rig: str, run: Run, s: np.ndarray, m: MatrixSection) -> None:
    tmp = path.with_name(path.name + ".part")
    rec = Recorder(tmp, rig)
    try:
        rec.add_event(
            float(s["t"][0]),
            "info",
            f"characterization run {run.run_id}: {run.label()}",
            kind="run",
            **asdict(run),
            settle_s=m.settle_s,
            duration_s=m.duration_s,
        )
        rec.add_samples(s)
        rec.add_summary({**summarize(s, []), "run": asdict(run)})
    finally:
        rec.close()
    os.replace(tmp, path)


def register_tool_run(cfg: DaemonConfig, started_utc: dt.datetime, **fields: Any) -> None:
    """One run of this tool (or `validate`) into the rig config's catalog (`[catalog]`, where
    the daemon's own runs go), with the config's specimen, tags and operator; a catalog that
    cannot take it is logged and the tool goes on. `fields`: `mrrig.api.register_run`'s."""
    if not cfg.catalog.enabled:
        return
    from mrrig.api import register_run
    from mrrig.rigio.run_identity import catalog_urls

    url, spool = catalog_urls(cfg)
    if cfg.rig.operator:
        fields["operator"] = cfg.rig.operator
    try:
        register_run(
            cfg.rig.name,
            started_utc,
            ended_utc=dt.datetime.now(dt.UTC),
            catalog=url,
            spool=spool,
            specimen=cfg.rig.specimen,
            tags=list(cfg.rig.tags),
            config=cfg.source,
            **fields,
        )
    except MrrigError as exc:
        log.error(
            "%s %s not registered in the catalog: %s", fields.get("plan"), fields.get("step"), exc
        )


# ---------------------------------------------------------------------------------- the output
class MatrixStore:
    """DIR/done.json (the truth about finished runs), DIR/matrix.csv, DIR/run-NNN.rrd."""

    def __init__(self, directory: Path, m: MatrixSection) -> None:
        self.dir = directory
        self.dir.mkdir(parents=True, exist_ok=True)
        self.m = m
        self.done_path = self.dir / DONE_FILE
        self.csv_path = self.dir / MATRIX_FILE
        self.done: dict[int, dict[str, Any]] = {}
        if self.done_path.is_file():
            data = json.loads(self.done_path.read_text(encoding="utf-8"))
            if data.get("matrix") != _matrix_json(m):
                raise ConfigError(
                    f"{self.dir}: recorded with another matrix ({self.done_path}); "
                    "use another --out or remove that directory"
                )
            self.done = {int(k): v for k, v in data["runs"].items()}
        self._clean_csv()

    def _clean_csv(self) -> None:
        """Keep only rows of runs in done.json; a done run without rows is not done."""
        header = ",".join(TIDY_HEADER) + "\n"
        if not self.csv_path.is_file():
            if self.done:
                log.warning("%s is missing: redoing every run", self.csv_path)
                self.done.clear()
            self.csv_path.write_text(header, encoding="utf-8")
            self._write_done()
            return
        with self.csv_path.open(encoding="utf-8") as fh:
            lines = fh.readlines()
        if not lines or lines[0] != header:
            raise ConfigError(f"{self.csv_path}: not a tidy characterization file")
        keep = [header]
        present: set[int] = set()
        for line in lines[1:]:
            if not line.endswith("\n"):
                continue  # a row cut off by a crash
            rid = int(line.split(",", 1)[0])
            if rid in self.done:
                keep.append(line)
                present.add(rid)
        missing = set(self.done) - present
        for rid in missing:
            log.warning(
                "run %d is in %s but has no rows in %s: redoing it", rid, DONE_FILE, MATRIX_FILE
            )
            del self.done[rid]
        if len(keep) != len(lines):
            log.info(
                "%s: dropped %d rows of unfinished runs", self.csv_path, len(lines) - len(keep)
            )
            tmp = self.csv_path.with_suffix(".csv.part")
            tmp.write_text("".join(keep), encoding="utf-8")
            os.replace(tmp, self.csv_path)
        if missing:
            self._write_done()

    def _write_done(self) -> None:
        data = {
            "matrix": _matrix_json(self.m),
            "runs": {str(k): v for k, v in sorted(self.done.items())},
        }
        tmp = self.done_path.with_suffix(".json.part")
        tmp.write_text(json_text.dumps(data, indent=1), encoding="utf-8")
        os.replace(tmp, self.done_path)

    def rrd_path(self, run: Run) -> Path:
        return self.dir / f"run-{run.run_id:03d}.rrd"

    def save(
        self, rig: str, run: Run, s: np.ndarray, attempts: int, failed: list[dict] | None = None
    ) -> None:
        """Recording, then the CSV rows, then done.json: a crash before the last redoes it.
        `failed`: the attempts before this one, each with its reason (and fault time)."""
        t0 = float(s["t"][0])
        write_run_recording(self.rrd_path(run), rig, run, s, self.m)
        with self.csv_path.open("a", encoding="utf-8") as fh:
            append_tidy(fh, run.run_id, s, t0)
            fh.flush()
            os.fsync(fh.fileno())
        self.done[run.run_id] = {
            **asdict(run),
            "samples": int(s.size),
            "attempts": attempts,
            "failed_attempts": failed or [],
            "finished_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        }
        self._write_done()


def _matrix_json(m: MatrixSection) -> dict[str, Any]:
    d = asdict(m)
    d.pop("attempts")  # how often to try does not change the data
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


# ---------------------------------------------------------------------------------- progress
class Progress:
    """One line per run on stderr: run k/N, its conditions, the time left."""

    def __init__(self, n_todo: int, n_total: int, m: MatrixSection, out: TextIO = sys.stderr):
        self.n_todo, self.n_total = n_todo, n_total
        self.out = out
        self.t0 = time.monotonic()
        self.first_guess_s = m.settle_s + m.duration_s + RUN_OVERHEAD_S
        self.k = 0

    def start(self, run: Run) -> None:
        per_run = (time.monotonic() - self.t0) / self.k if self.k else self.first_guess_s
        left_s = per_run * (self.n_todo - self.k)
        width = 20
        fill = round(width * self.k / max(self.n_todo, 1))
        bar = "#" * fill + "." * (width - fill)
        self.out.write(
            f"[{bar}] run {self.k + 1}/{self.n_todo} (id {run.run_id} of {self.n_total}): "
            f"{run.label()}; about {_hms(left_s)} left\n"
        )
        self.out.flush()

    def finish(self) -> None:
        self.k += 1


def _hms(s: float) -> str:
    s = max(0, round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


# ---------------------------------------------------------------------------------- main
def characterize(
    session: RigSession, store: MatrixStore, runs: list[Run], stop: threading.Event
) -> list[Run]:
    """Every run of `runs` not yet in the store; returns the runs that failed `attempts` times
    (left for the next invocation). RigError after `MAX_FAILED_IN_A_ROW` such runs in a row."""
    todo = [r for r in runs if r.run_id not in store.done]
    if len(todo) < len(runs):
        log.info(
            "%d of %d runs already recorded in %s: skipping them",
            len(runs) - len(todo),
            len(runs),
            store.dir,
        )
    progress = Progress(len(todo), len(runs), store.m)
    rig = session.cfg.rig.name
    failed: list[Run] = []
    in_a_row = 0
    for run in todo:
        progress.start(run)
        attempts_failed: list[dict] = []
        for attempt in range(1, store.m.attempts + 1):
            started_utc = dt.datetime.now(dt.UTC)
            try:
                s = record_run(session, run, store.m, stop)
            except RunFailed as exc:
                log.warning("run %d, attempt %d: %s", run.run_id, attempt, exc)
                attempts_failed.append(_failed_attempt(session, attempt, exc))
                session.wait_until(session.now() + RETRY_PAUSE_S, stop, fail_on_fault=False)
                continue
            store.save(rig, run, s, attempt, attempts_failed)
            register_tool_run(
                session.cfg,
                started_utc,
                plan=CHARACTERIZATION_PLAN,
                step=f"run-{run.run_id:03d}",
                campaign=store.dir.name,
                controller="constant",
                controller_params=asdict(run),
                summary=summarize(s, []),
                recording=store.rrd_path(run),
                verdict="ok",
            )
            in_a_row = 0
            break
        else:
            log.error("run %d (%s): %d attempts failed; left for the next invocation",
                      run.run_id, run.label(), store.m.attempts)  # fmt: skip
            failed.append(run)
            in_a_row += 1
            if in_a_row == MAX_FAILED_IN_A_ROW:
                raise RigError(f"{in_a_row} runs in a row failed; last: {run.label()}")
        progress.finish()
    return failed


def _failed_attempt(session: RigSession, attempt: int, exc: RunFailed) -> dict[str, Any]:
    """One failed attempt for done.json; a fault's time also on CLOCK_MONOTONIC (`clock_s`),
    to set it beside the rig's own record of the same moment."""
    out: dict[str, Any] = {"attempt": attempt, "reason": str(exc)}
    if exc.fault is not None:
        t, t0 = float(exc.fault["t"]), session.clock_t0_s
        out.update(fault=exc.fault["reason"], t_s=t, clock_s=t0 + t)
        # the loop's own stalls (the kernel's) in the second before it, on CLOCK_MONOTONIC
        windows = session.kernel_stalls().get("windows") or []
        near = [w for w in windows if t - KERNEL_NEAR_S <= w[1] and w[0] <= t]
        out["kernel_windows"] = [[t0 + w[0], t0 + w[1], *w[2:]] for w in near]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig characterize",
        description=__doc__.splitlines()[0],
    )
    ap.add_argument(
        "--config",
        type=Path,
        default=Path("configs/characterize.toml"),
        help="the test matrix (TOML)",
    )
    ap.add_argument(
        "--rig-config", type=Path, default=Path("configs/rig.toml"), help="daemon config (TOML)"
    )
    ap.add_argument(
        "-c",
        "--channel",
        "--bus-channel",
        dest="bus_channel",
        help="python-can channel (overrides bus.channel of the rig config)",
    )
    ap.add_argument("--out", type=Path, help="output directory (default: output.directory)")
    ap.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    args = ap.parse_args(argv)
    ccfg = load_characterize_config(args.config)
    m = ccfg.matrix
    overrides = rig_overrides(
        args.bus_channel,
        args.no_telemetry,
        controller={"name": "constant", "current_a": 0.0},
        actuator={"waveform": "stop"},
    )
    cfg = load_config(args.rig_config, overrides)
    if max(m.currents_a) > cfg.loop.i_max_a:
        raise ConfigError(
            f"{args.config}: matrix.currents_a: {max(m.currents_a):g} A is above the rig's "
            f"loop.i_max_a {cfg.loop.i_max_a:g} A ({args.rig_config})"
        )
    store = MatrixStore(args.out or ccfg.output.directory, m)
    runs = matrix_runs(m)
    with stop_on_signals() as stop:
        try:
            with RigSession(cfg) as session:
                failed = characterize(session, store, runs, stop)
        except Interrupted:
            print(
                f"interrupted: {len(store.done)} of {len(runs)} runs recorded in {store.dir}; "
                "run the same command again to resume",
                file=sys.stderr,
            )
            return EXIT_INTERRUPTED
        except RigError as exc:
            print(
                f"error: {exc}\n{len(store.done)} of {len(runs)} runs recorded in {store.dir}; "
                "run the same command again to resume",
                file=sys.stderr,
            )
            return 1
    if failed:
        print(
            f"{len(failed)} runs failed (ids {', '.join(str(r.run_id) for r in failed)}); "
            f"{len(store.done)} of {len(runs)} runs recorded in {store.dir}; "
            "run the same command again to retry them",
            file=sys.stderr,
        )
        return 1
    n = sum(r["samples"] for r in store.done.values())
    print(
        f"characterization complete: {len(runs)} runs, {n} samples in {store.csv_path}\n"
        f"train the forward model: mrrig train {store.csv_path} --out models/forward.json"
    )
    return 0
