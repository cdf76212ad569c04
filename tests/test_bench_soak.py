"""`mrrig bench soak`: a short run of it prints real numbers (the memory of a 60-minute run is
the benchmark's to print, not a test's to assert: RSS on a shared VM is not a unit test)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from mrrig.offline.bench.soak import RssTrace, max_rss_mb

REPO = Path(__file__).resolve().parents[1]


def test_max_rss_is_read_from_time_v_output() -> None:
    out = "\tUser time (seconds): 1.0\n\tMaximum resident set size (kbytes): 204800\n"
    assert max_rss_mb(out) == 200.0
    with pytest.raises(ValueError, match="Maximum resident set size"):
        max_rss_mb("Command terminated by signal 9\n")


def test_growth_is_the_last_sample_against_the_first_after_the_warm_up() -> None:
    trace = RssTrace([0.0, 5.0, 10.0, 15.0], [50.0, 100.0, 101.0, 102.0])
    assert trace.growth(5.0) == (100.0, 102.0, pytest.approx(2.0))
    assert trace.slope_mb_per_min(5.0) == pytest.approx(12.0)
    with pytest.raises(ValueError, match="none after the 20 s warm-up"):
        trace.growth(20.0)


@pytest.mark.process
def test_a_short_soak_prints_the_sidecar_growth_and_the_review_peaks(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "bench", "soak", "--minutes", "0.5",
         "--sample-s", "1", "--work", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    out = proc.stdout
    print(out, proc.stderr[-3000:])
    m = re.search(
        r"sidecar RSS ([\d.]+) MB after the [\d.]+ min warm-up, ([\d.]+) MB at [\d.]+ min:"
        r" growth ([-+][\d.]+) %",
        out,
    )
    assert m is not None, out
    start, end, growth = (float(g) for g in m.groups())
    assert start > 20.0 and end > 20.0  # a Python process with rerun and Zenoh loaded
    assert growth == pytest.approx((end - start) / start * 100.0, abs=0.01)
    # the trace behind it: a sample a second over the run
    rows = (tmp_path / "sidecar-rss.csv").read_text().splitlines()[1:]
    assert len(rows) >= 20
    assert float(rows[-1].split(",")[1]) == pytest.approx(end, abs=0.01)
    peaks = re.findall(
        r"review peak RSS ([\d.]+) MB \((mrrig review REC[^;]*); exit code (\d+)", out
    )
    assert [what for _, what, _ in peaks] == ["mrrig review REC", "mrrig review REC --html"]
    assert all(float(mb) > 50.0 and rc == "0" for mb, _, rc in peaks)
    assert (tmp_path / "review.html").stat().st_size > 10_000
    passed = growth < 5.0 and all(float(mb) < 1024.0 for mb, _, _ in peaks)
    assert ("verdict PASS" in out) == passed
    assert proc.returncode == (0 if passed else 1)
