"""Issue 42, item 2: `mrrig review --html` as a test record: the identity header, the verdict,
the key numbers, time traces of every channel, the per-cycle table and the marks."""

from __future__ import annotations

import re

from mrrig.loop.summary import summarize
from mrrig.offline import review_report
from mrrig.offline.review import read_recording
from mrrig.rigio.recording import Recorder
from tests.test_recording import run_events, synthetic_run

IDENTITY = {
    "run_id": "0b5e9a1c-2d4f-4e6a-9c1b-3f2a91c07d11",
    "rig": "rig1",
    "specimen": "SN-MR-042",
    "operator": "walk",
    "started_utc": "2026-12-06T03:00:00+00:00",
    "controller": "network_inversion",
    "model_path": "models/dyke.json",
    "model_sha256": "ab" * 32,
}


def test_the_review_html_is_a_test_record(tmp_path):
    s = synthetic_run(3000)  # 6 s of a 10 mm, 2 Hz stroke
    events = run_events(s)
    events.append({"t": 1.0, "level": "info", "text": "plan p step 1/1 sine: start",
                   "kind": "mark", "data": {"step": "sine"}})  # fmt: skip
    path = tmp_path / "rig1-20261206T030000Z.rrd"
    with Recorder(path, "rig1", flush_interval_s=0.5, identity=IDENTITY) as rec:
        rec.add_samples(s)
        for ev in events:
            extra = {k: v for k, v in ev.items() if k not in ("t", "level", "text")}
            rec.add_event(ev["t"], ev["level"], ev["text"], **extra)
        rec.add_summary({"controller": "network_inversion", "exit_code": 1})
    rec = read_recording(path)
    metrics = summarize(rec.samples, rec.events, {})
    text = review_report.write_html(rec, metrics, tmp_path / "r.html").read_text()
    for label, key in review_report.IDENTITY_ROWS[:8]:
        if key in IDENTITY:
            assert f"<td>{label}</td><td>{IDENTITY[key]}</td>" in text, label
    assert "verdict: <b>fault, 1 fault</b>" in text
    assert re.search(r"<td>Et \(eqs 41-43\)</td><td>0\.\d{4}</td>", text)
    assert "alt='time traces'" in text and "alt='per cycle'" in text
    # the per-condition table: one row, 10 mm at 2 Hz, about 2 cycles a second
    (row,) = re.findall(r"<tr><td>(10)</td><td>(2)</td><td>[\d.]+</td><td>(\d+)</td>", text)
    assert 9 <= int(row[2]) <= 12, row
    assert "plan p step 1/1 sine: start" in text  # the marks
    assert "<details><summary>Every summary number</summary>" in text
