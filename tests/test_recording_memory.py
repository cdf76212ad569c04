"""Bounded memory of a long recording and of its review (issue 40, finding 9).

The sidecar grew 2.5-6 MB a minute while recording: rerun keeps the RRD footer's manifest
(about 1 kB a chunk) in the writer's memory until the file is closed. The recording has no
footer now and an end marker instead; `mrrig review` streams the file chunk by chunk. The
numbers of a long run are `mrrig bench soak`'s (tests/test_bench_soak.py runs it short).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rerun_bindings import check_for_rrd_footer

from mrrig.cli.review import main as review_main
from mrrig.export import export
from mrrig.loop.summary import format_summary, summarize
from mrrig.offline.review import (
    SUMMARY_BLOCK,
    BlockSummary,
    FigureSamples,
    ReviewError,
    read_recording,
    review_recording,
    verify_rrd,
)
from mrrig.offline.review_report import window
from mrrig.offline.rrd_scan import scan_recording
from tests.test_recording import run_events, synthetic_run, write_recording

N = 4000


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, list[dict]]:
    path = tmp_path_factory.mktemp("mem") / "rig1-run.rrd"
    s = synthetic_run(N)
    events = run_events(s)
    write_recording(path, s, events, summarize(s, events, {"frames_received": N}))
    return path, s, events


def test_the_recording_has_no_footer_whose_manifest_the_writer_would_hold(run) -> None:
    """What kept the sidecar growing: with a footer, rerun holds every chunk's manifest entry
    in memory until close. Without one, the end marker says that the file is whole."""
    path, s, events = run
    assert not check_for_rrd_footer(path)
    scan = scan_recording(path, lambda batch: None)
    assert scan.end == {"frames": s.size, "events": len(events)}
    verify_rrd(path)  # whole: rerun's one complaint (no footer) answered by the marker


def test_a_recording_cut_short_fails_verify_though_rerun_reads_it_without_error(
    run, tmp_path: Path
) -> None:
    path = run[0]
    data = path.read_bytes()
    for fraction in (0.3, 0.9):
        cut = tmp_path / f"cut-{fraction}.rrd"
        cut.write_bytes(data[: int(len(data) * fraction)])
        with pytest.raises(ReviewError, match=rf"cut-{fraction}.rrd: truncated"):
            verify_rrd(cut)


def test_the_scan_hands_out_the_samples_in_batches_of_its_window(run) -> None:
    """Held back: a window of frames (here 512) and the flush that comes in (0.5 s, 260
    frames at most), not the run; the batches put together are the recording, bit for bit."""
    path, s, _ = run
    batches: list[np.ndarray] = []
    scan = scan_recording(path, batches.append, window=512)
    assert len(batches) >= N // (512 + 260)
    assert max(b.size for b in batches) <= 512 + 260
    assert scan.frames == N and scan.dropped == 0
    assert np.concatenate(batches).tobytes() == s.tobytes()
    assert read_recording(path).samples.tobytes() == s.tobytes()


def test_block_summary_of_a_run_shorter_than_a_block_is_summarize_exactly(run) -> None:
    _, s, events = run
    acc = BlockSummary()
    for k in range(0, s.size, 37):
        acc.add(s[k : k + 37])
    assert format_summary(acc.result(events)) == format_summary(summarize(s, events))
    assert json.dumps(acc.result(events)) == json.dumps(summarize(s, events))


def test_block_summary_adds_the_same_blocks_however_the_samples_come() -> None:
    s = synthetic_run(2 * SUMMARY_BLOCK + 123)
    whole, pieces = BlockSummary(), BlockSummary()
    whole.add(s)
    for k in range(0, s.size, 1000):
        pieces.add(s[k : k + 1000])
    assert json.dumps(whole.result([])) == json.dumps(pieces.result([]))


def test_figure_samples_thin_to_every_stride_th_past_the_cap() -> None:
    s = synthetic_run(1000)
    fig = FigureSamples(max_samples=100)
    for k in range(0, s.size, 30):
        fig.add(s[k : k + 30])
    kept = fig.samples()
    assert fig.stride == 16 and fig.seen == 1000
    assert kept.tobytes() == s[::16].tobytes()


def test_streamed_review_of_a_window_is_the_window_of_the_whole(run) -> None:
    path, s, _ = run
    rec, acc = review_recording(path, 2.0, 6.0, keep_samples=True)
    whole = window(read_recording(path), 2.0, 6.0)
    assert rec.samples.tobytes() == whole.samples.tobytes()
    assert rec.events == whole.events
    assert json.dumps(acc.result(rec.events)) == json.dumps(summarize(whole.samples, whole.events))
    with pytest.raises(ValueError, match="no frame between 100 and 200 s"):
        review_recording(path, 100.0, 200.0)


def test_review_of_the_rrd_and_of_its_parquet_print_the_same_metrics(run, tmp_path, capsys):
    path = run[0]
    parquet = export(read_recording(path), "parquet", tmp_path / "run.parquet")
    out = {}
    for p in (path, parquet):
        assert review_main([str(p), "--json", str(tmp_path / f"{p.suffix}.json")]) == 0
        out[p.suffix] = (tmp_path / f"{p.suffix}.json").read_text()
    assert out[".rrd"] == out[".parquet"]
    assert json.loads(out[".rrd"])["frames"] == N
