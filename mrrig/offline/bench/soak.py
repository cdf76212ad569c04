"""`mrrig bench soak --minutes N`: the memory of a long recorded run and of its review.

Runs `mrrig demo` (the python-can-remote bridge, firmware_sim, the daemon and its telemetry
sidecar recording to an .rrd) for N minutes of force tracking, re-arming after transport
faults as the demo does (the run itself is not what is measured), on a copy of the daemon's
config with a Zenoh port of its own and without SCHED_FIFO (a soak beside other work must not
preempt it). The sidecar's resident set is sampled every `--sample-s` seconds; printed are its
RSS after the warm-up and at the end of the run and the growth between them, in %. Then
`mrrig review` of the recording runs under `/usr/bin/time -v`, plain and with `--html`, and
their peak RSS (Maximum resident set size) is printed.

Exit code 1 when the growth is 5 % or more, a review peaks at 1 GB or more, or something did
not run (no sidecar found, no recording, a review that failed).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mrrig.cli_args import HelpFormatter, positive

log = logging.getLogger(__name__)

GROWTH_LIMIT_PCT = 5.0
REVIEW_LIMIT_MB = 1024.0
WARMUP_MAX_MIN = 2.0
SIDECAR_MODULE = "mrrig.rigio.sidecar_process"
_MAX_RSS_RE = re.compile(r"Maximum resident set size \(kbytes\): (\d+)")
_REARMS_RE = re.compile(r"re-armed the daemon (\d+) times")


@dataclasses.dataclass
class RssTrace:
    """The sidecar's RSS (MB) at times (s since it was found)."""

    t_s: list[float] = dataclasses.field(default_factory=list)
    rss_mb: list[float] = dataclasses.field(default_factory=list)

    def growth(self, warmup_s: float) -> tuple[float, float, float]:
        """(RSS after the warm-up, RSS at the end, growth in %): the first sample at or after
        `warmup_s` against the last one."""
        t = np.asarray(self.t_s)
        after = np.flatnonzero(t >= warmup_s)
        if after.size < 2:
            raise ValueError(f"{len(self.t_s)} RSS samples: none after the {warmup_s:g} s warm-up")
        start, end = self.rss_mb[after[0]], self.rss_mb[-1]
        return start, end, (end - start) / start * 100.0

    def slope_mb_per_min(self, warmup_s: float) -> float:
        """Least-squares slope of the RSS after the warm-up."""
        t = np.asarray(self.t_s)
        keep = t >= warmup_s
        return float(np.polyfit(t[keep] / 60.0, np.asarray(self.rss_mb)[keep], 1)[0])


def rss_mb(pid: int) -> float | None:
    """A process's resident set (VmRSS) in MB, None once it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(p) for p in text.split()]


def find_descendant(pid: int, module: str) -> int | None:
    """The first process below `pid` whose command line runs `module` (`-m module`)."""
    todo = _children(pid)
    while todo:
        child = todo.pop()
        try:
            argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if module.encode() in argv:
            return child
        todo += _children(child)
    return None


def max_rss_mb(time_v_output: str) -> float:
    """The peak RSS (MB) that `/usr/bin/time -v` printed."""
    m = _MAX_RSS_RE.search(time_v_output)
    if m is None:
        raise ValueError("no 'Maximum resident set size' in the output of /usr/bin/time -v")
    return int(m.group(1)) / 1024.0


def soak_config(config: Path, work: Path) -> tuple[Path, Path]:
    """The daemon's config for the soak: a Zenoh port of its own (`mrrig bench fuzz`'s), and
    no SCHED_FIFO. Returns it and a client's Zenoh config reaching that daemon."""
    import json

    from mrrig.config import load_config
    from mrrig.offline.bench.fuzz import _daemon_config

    cfg = load_config(config)
    daemon_cfg, endpoints = _daemon_config(config, cfg, work)
    text = re.sub(r"(?m)^(\s*realtime\s*=\s*)true\b", r"\1false", daemon_cfg.read_text())
    daemon_cfg.write_text(text)
    client = work / "zenoh-client.json5"
    client.write_text(
        json.dumps(
            {
                "mode": "client",
                "connect": {"endpoints": endpoints},
                "scouting": {"multicast": {"enabled": False}},
            }
        )
    )
    return daemon_cfg, client


def sample_run(demo: subprocess.Popen, run_s: float, sample_s: float) -> RssTrace:
    """The sidecar's RSS every `sample_s` over the run's `run_s` (from when it is found)."""
    trace = RssTrace()
    sidecar = None
    found_deadline = time.monotonic() + 120.0
    while sidecar is None:
        if demo.poll() is not None or time.monotonic() > found_deadline:
            raise RuntimeError("no telemetry sidecar process came up under the demo")
        sidecar = find_descendant(demo.pid, SIDECAR_MODULE)
        time.sleep(0.2)
    t0 = time.monotonic()
    log.info("sidecar pid %d: sampling its RSS every %g s", sidecar, sample_s)
    next_t = t0
    # the last sample before the run's end: the daemon's shutdown is not the run
    while (now := time.monotonic()) - t0 < run_s - 1.0:
        mb = rss_mb(sidecar)
        if mb is None:
            break
        trace.t_s.append(now - t0)
        trace.rss_mb.append(mb)
        next_t += sample_s
        time.sleep(max(0.0, min(next_t, t0 + run_s - 1.0) - time.monotonic()))
    return trace


def review_peak(rec: Path, extra: list[str], work: Path) -> tuple[float, int]:
    """Peak RSS (MB) and exit code of `mrrig review REC [extra]` under /usr/bin/time -v."""
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "mrrig", "review", str(rec), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=work)
    (work / f"review{'-html' if extra else ''}.log").write_text(proc.stdout + proc.stderr)
    return max_rss_mb(proc.stderr), proc.returncode


def run(args: argparse.Namespace) -> int:
    from mrrig.cli.demo import SIM_MODEL, ensure_sim_model
    from mrrig.rigio.run_identity import CATALOG_ENV

    ensure_sim_model(SIM_MODEL)  # the configs' model: trained on first use, as the demo does
    work = args.work or Path(tempfile.mkdtemp(prefix="mrrig-bench-soak-"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ[CATALOG_ENV] = str(work / "catalog.sqlite")  # not the lab's catalog
    daemon_cfg, client_cfg = soak_config(args.config, work)
    rec = work / "soak.rrd"
    run_s = args.minutes * 60.0
    warmup_s = min(WARMUP_MAX_MIN * 60.0, run_s / 3.0)
    cmd = [sys.executable, "-m", "mrrig", "demo", "--config", str(daemon_cfg),
           "--sim-config", str(args.sim_config), "--duration", f"{run_s:g}",
           "--record", str(rec), "--zenoh-config", str(client_cfg),
           # the operator re-arms after every transport fault: the run is not what is measured
           "--max-rearms", "1000000", "--rearm-window", "1"]  # fmt: skip
    print(f"bench soak: {args.minutes:g} min recorded run; work in {work}", flush=True)
    with (work / "demo.log").open("w") as demo_log:
        demo = subprocess.Popen(cmd, stdout=demo_log, stderr=subprocess.STDOUT)
        try:
            trace = sample_run(demo, run_s, args.sample_s)
            demo.wait(timeout=run_s + 300.0)
        finally:
            if demo.poll() is None:
                demo.terminate()
                demo.wait(timeout=60.0)
    rows = zip(trace.t_s, trace.rss_mb, strict=True)
    csv = "t_s,rss_mb\n" + "".join(f"{t:.1f},{m:.2f}\n" for t, m in rows)
    (work / "sidecar-rss.csv").write_text(csv)
    demo_text = (work / "demo.log").read_text(errors="replace")
    rearms = _REARMS_RE.search(demo_text)
    start, end, growth = trace.growth(warmup_s)
    print(
        f"  sidecar RSS {start:.2f} MB after the {warmup_s / 60:.3g} min warm-up,"
        f" {end:.2f} MB at {trace.t_s[-1] / 60:.1f} min: growth {growth:+.2f} %"
        f" (limit {GROWTH_LIMIT_PCT:g} %); max {max(trace.rss_mb):.1f} MB,"
        f" slope {trace.slope_mb_per_min(warmup_s):+.3f} MB/min, {len(trace.t_s)} samples",
        flush=True,
    )
    print(
        f"  demo exit code {demo.returncode},"
        f" re-armed {rearms.group(1) if rearms else '?'} times after transport faults",
        flush=True,
    )
    if not rec.is_file():
        print(f"  no recording at {rec}: FAIL")
        return 1
    print(f"  recording {rec}: {rec.stat().st_size / 1e6:.1f} MB", flush=True)
    ok = growth < GROWTH_LIMIT_PCT
    for extra in ([], ["--html", str(work / "review.html")]):
        peak, rc = review_peak(rec, extra, work)
        what = "mrrig review REC" + (" --html" if extra else "")
        print(
            f"  review peak RSS {peak:.1f} MB ({what}; exit code {rc};"
            f" limit {REVIEW_LIMIT_MB:g} MB)",
            flush=True,
        )
        ok = ok and peak < REVIEW_LIMIT_MB and rc == 0
    print(f"  verdict {'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig bench soak", description=__doc__
    )
    ap.add_argument("--minutes", type=positive, default=60.0, help="length of the run")
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--sim-config", type=Path, default=Path("configs/sim.toml"))
    ap.add_argument("--sample-s", type=positive, default=5.0, help="RSS sampling period, s")
    ap.add_argument(
        "--work", type=Path, help="folder for the recording, logs and RSS trace (default: a new"
        " temporary folder)"
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        return run(args)
    except (RuntimeError, ValueError) as exc:
        log.error("error: %s", exc)
        return 1
