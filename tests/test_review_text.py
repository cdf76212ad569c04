"""Issue 40, findings 12 and 13 for `mrrig review`: a `$` in a recording's file name or a fault's
reason is text in the figure and the report (matplotlib read it as mathtext and failed); a
recording without a single sensor frame is one line and exit 1, not a page of NaN."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from mrrig.loop.summary import summarize
from mrrig.offline import review_report
from mrrig.offline.review import read_recording
from mrrig.rigio.recording import Recorder
from tests.conftest import REPO
from tests.test_recording import run_events, synthetic_run, write_recording


def _mrrig(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_dollar_in_the_file_name_and_a_faults_reason_is_text_in_the_review(tmp_path: Path):
    s = synthetic_run(2000)
    events = run_events(s)
    events[1] = {**events[1], "reason": "$x^$ over $\\frac$"}
    path = tmp_path / "run $x^$ a$b.rrd"
    write_recording(path, s, events, {"controller": "constant $i_{max}$"})
    rec = read_recording(path)
    metrics = summarize(rec.samples, rec.events, {})
    out = review_report.write_html(rec, metrics, tmp_path / "report $x$.html")
    text = out.read_text()
    assert "run $x^$ a$b.rrd" in text and "$x^$ over $\\frac$" in text
    review_report.plot_compare([("run $x^$", s, events), ("a$b", s, [])], tmp_path / "c.png")


def test_review_of_a_recording_without_frames_is_one_line_and_exit_1(tmp_path: Path):
    path = tmp_path / "empty.rrd"
    with Recorder(path, "rig1") as rec:
        rec.add_summary({"controller": "constant"})
    assert read_recording(path).samples.size == 0
    for extra in ((), ("--partial", "--html", str(tmp_path / "r.html"))):
        done = _mrrig("review", str(path), *extra)
        assert done.returncode == 1, done.stdout + done.stderr
        errors = [line for line in done.stderr.splitlines() if "ERROR" in line]
        assert len(errors) == 1 and "no frames" in errors[0], done.stderr
        assert "Traceback" not in done.stderr and "nan" not in done.stdout
    assert not (tmp_path / "r.html").exists()
