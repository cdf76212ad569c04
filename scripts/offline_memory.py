"""Peak memory of `mrrig train` and `mrrig evaluate` on a large CSV (issue 32, finding 12).

Writes a CSV of `--samples` samples (default 20 M, about 1 GB: t_s, x_m, force_n, current_a
and a column nobody reads, runs of 4 s at 0.5 kHz from `mrrig bench train`'s simulated pool
with fresh sensor noise) into a temporary folder, runs both commands under
`/usr/bin/time -v`, prints each one's wall time, exit code and maximum resident set size, and
deletes the folder. Training keeps at most `TRAIN_MAX_SAMPLES` of the samples (whole
segments at random); evaluation scores every one, a segment at a time.

    .venv/bin/python scripts/offline_memory.py            # 20 M samples, ~1 GB (df -h /tmp first)
    .venv/bin/python scripts/offline_memory.py --samples 2000000
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mrrig.offline.bench.train import make_pool, series_of_size
from mrrig.offline.training.stream import SEGMENT_ROWS, TRAIN_MAX_SAMPLES

WRITE_ROWS = 1_000_000
MRRIG = Path(sys.executable).with_name("mrrig")
TRAIN_FLAGS = ["--features", "manual", "--current-input", "lagged", "--epochs", "30"]
TRAIN_FLAGS += ["--restarts", "1", "--no-supervised"]


def write_csv(path: Path, samples: int, pool_runs: int) -> None:
    pool = make_pool(pool_runs)
    with path.open("w", encoding="utf-8") as fh:
        fh.write("t_s,x_m,force_n,current_a,temperature_c\n")
        for k, a in enumerate(range(0, samples, WRITE_ROWS)):
            s = series_of_size(pool, min(WRITE_ROWS, samples - a), seed=k)
            temp = np.full(len(s), 25.0) + 0.001 * k
            cols = np.column_stack([s.t, s.x, s.force, s.current, temp])
            np.savetxt(fh, cols, fmt=["%.6f", "%.9f", "%.4f", "%.7f", "%.4f"], delimiter=",")


def timed(args: list[str]) -> tuple[int, float, float, str]:
    """(exit code, wall s, peak RSS MB, the command's last output line) under time -v."""
    t0 = time.monotonic()
    out = subprocess.run(
        ["/usr/bin/time", "-v", *args], capture_output=True, text=True, check=False
    )
    wall = time.monotonic() - t0
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr)
    lines = [ln for ln in (out.stdout + out.stderr).splitlines() if "Command" not in ln]
    tail = next((ln for ln in reversed(out.stdout.splitlines()) if ln.strip()), "")
    if out.returncode != 0:
        tail = "\n".join(lines[-5:])
    return out.returncode, wall, int(rss.group(1)) / 1024.0 if rss else float("nan"), tail


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20_000_000)
    ap.add_argument("--pool-runs", type=int, default=20, help="distinct simulated runs")
    ap.add_argument(
        "--train-defaults",
        action="store_true",
        help="train with mrrig train's defaults (the feature search, restarts, the supervised"
        " inverse) instead of one manual network: longer",
    )
    args = ap.parse_args()
    flags = [] if args.train_defaults else TRAIN_FLAGS
    tmp = Path(tempfile.mkdtemp(prefix="mrrig-offline-memory-"))
    try:
        data = tmp / "big.csv"
        t0 = time.monotonic()
        write_csv(data, args.samples, args.pool_runs)
        size_mb = data.stat().st_size / 1e6
        print(
            f"{data}: {args.samples} samples, {size_mb:.0f} MB,"
            f" written in {time.monotonic() - t0:.0f} s"
        )
        print(f"segments of {SEGMENT_ROWS} samples; train keeps at most {TRAIN_MAX_SAMPLES}")
        model = tmp / "m.json"
        runs = {
            "train": [str(MRRIG), "-q", "train", str(data), "--out", str(model), *flags],
            "evaluate": [str(MRRIG), "-q", "evaluate", str(model), str(data)],
        }
        worst = 0
        for name, cmd in runs.items():
            rc, wall, rss, tail = timed(cmd)
            print(f"mrrig {name}: exit {rc}, {wall:.0f} s, Maximum resident set size {rss:.0f} MB")
            print(f"  {tail}")
            worst = max(worst, rc)
        return worst
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
