"""Reading a run's .rrd back: samples, events and summary; checking it; a PNG for people
without a viewer.

The layout read here is the one `mrrig.rigio.recording` writes (see its module docstring).
"""

from __future__ import annotations

import dataclasses
import logging
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.errors import MrrigError
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.loop.summary import SummaryAccumulator
from mrrig.offline.rrd_scan import Scan, scan_recording
from mrrig.rigio.recording import FIELD_ENTITIES, SUMMARY_ENTITY

log = logging.getLogger(__name__)

RRD_MAGIC = b"RRF2"  # the FourCC an .rrd file starts with (rerun-sdk 0.41, as pinned)


class ReviewError(MrrigError, ValueError):
    """A recording that cannot be read or checked; the message is one line naming the file."""


@dataclasses.dataclass
class Recording:
    """A run read back from its .rrd file."""

    path: Path
    samples: np.ndarray  # SAMPLE_DTYPE, sorted by t
    events: list[dict[str, Any]]  # t, level, text, plus the extra fields (kind, reason, ...)
    summary: dict[str, Any] | None  # what `Recorder.add_summary` stored, or None
    # the run's identity (run id, rig, specimen, model and config sha256, ...), where recorded
    identity: dict[str, Any] | None = None


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by `Recorder`: its samples (sorted by t), events, summary and
    identity, in one streaming pass (`mrrig.offline.rrd_scan`; memory: the samples).

    A truncated file (writer killed before `close()`) still gives what reached the disk.
    """
    path = Path(path)
    batches: list[np.ndarray] = []
    scan = scan_checked(path, batches.append)
    samples = np.concatenate(batches) if batches else np.empty(0, dtype=SAMPLE_DTYPE)
    return Recording(
        path=path,
        samples=samples[np.argsort(samples["t"], kind="stable")],
        events=scan.events,
        summary=scan.summary,
        identity=scan.identity,
    )


SUMMARY_BLOCK = 1 << 16  # samples per addition to the summary's accumulator


class BlockSummary:
    """`SummaryAccumulator` fed in blocks of exactly `SUMMARY_BLOCK` samples, however the
    samples come: a run read in streamed batches and the same run read whole (an export) sum
    in the same order, so their metrics are equal to the last bit; a run shorter than a
    block gives `summarize`'s numbers exactly."""

    def __init__(self) -> None:
        self.acc = SummaryAccumulator()
        self._held: list[np.ndarray] = []
        self._n = 0
        self.frames = 0

    def add(self, samples: np.ndarray) -> None:
        self.frames += samples.size
        while samples.size:
            take = samples[: SUMMARY_BLOCK - self._n]
            samples = samples[take.size :]
            self._held.append(take)
            self._n += take.size
            if self._n == SUMMARY_BLOCK:
                self._add_held()

    def result(
        self, events: list[dict[str, Any]], counters: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        self._add_held()
        return self.acc.result(events, counters)

    def _add_held(self) -> None:
        if self._held:
            self.acc.add(np.concatenate(self._held))
        self._held, self._n = [], 0


FIGURE_MAX_SAMPLES = 1 << 21  # 256 MB of samples: a figure of a longer window thins them


class FigureSamples:
    """The samples a figure draws, in bounded memory: all of them up to `max_samples`; past
    that, every `stride`-th (the stride doubling each time the held samples reach the cap)."""

    def __init__(self, max_samples: int = FIGURE_MAX_SAMPLES) -> None:
        self.max_samples = max_samples
        self.stride = 1
        self.seen = 0
        self._held: list[np.ndarray] = []
        self._n = 0

    def add(self, samples: np.ndarray) -> None:
        index = self.seen + np.arange(samples.size)
        kept = samples[index % self.stride == 0]
        self.seen += samples.size
        if kept.size:
            self._held.append(kept)
            self._n += kept.size
        if self._n > self.max_samples:  # those held are every stride-th: keep every other
            thinned = np.concatenate(self._held)[::2]
            self._held, self._n = [thinned], thinned.size
            self.stride *= 2

    def samples(self) -> np.ndarray:
        return np.concatenate(self._held) if self._held else np.empty(0, dtype=SAMPLE_DTYPE)


def review_recording(
    path: str | Path,
    t_from: float | None = None,
    t_to: float | None = None,
    keep_samples: bool = False,
) -> tuple[Recording, BlockSummary]:
    """The metrics of a recording's window [t_from, t_to] of sensor time (None: no bound),
    accumulated in one streaming pass: memory bounded whatever the run's length. The
    Recording returned has the window's events, the run's summary and identity, and its
    samples only with `keep_samples` (a figure of them); else none."""
    lo = -np.inf if t_from is None else t_from
    hi = np.inf if t_to is None else t_to
    if lo >= hi:
        raise ValueError(f"--from {t_from:g} must be before --to {t_to:g}")
    acc = BlockSummary()
    figure = FigureSamples()
    span = [np.inf, -np.inf]  # the recording's first and last sensor time

    def take(batch: np.ndarray) -> None:
        t = batch["t"]
        span[0], span[1] = min(span[0], float(t.min())), max(span[1], float(t.max()))
        inside = batch[(t >= lo) & (t <= hi)]
        acc.add(inside)
        if keep_samples:
            figure.add(inside)

    scan = scan_checked(path, take)
    if scan.frames and not acc.frames:
        raise ValueError(
            f"{path}: no frame between {lo:g} and {hi:g} s (the recording has"
            f" {span[0]:.3f} to {span[1]:.3f} s)"
        )
    events = [e for e in scan.events if e.get("t") is not None and lo <= e["t"] <= hi]
    if t_from is None and t_to is None:
        events = scan.events
    if figure.stride > 1:
        log.warning(
            "%s: the figure draws every %d-th of the window's %d frames (its memory); the"
            " metrics count them all",
            path,
            figure.stride,
            figure.seen,
        )
    rec = Recording(Path(path), figure.samples(), events, scan.summary, scan.identity)
    return rec, acc


def scan_checked(path: str | Path, on_samples: Callable[[np.ndarray], None]) -> Scan:
    """`scan_recording` of a file checked to be an mrrig recording, with its errors as one-line
    ReviewErrors naming the file. `on_samples` gets the samples in frame order, in batches."""
    path = Path(path)
    if not path.is_file():
        raise ReviewError(f"{path}: no such file")
    with path.open("rb") as f:
        head = f.read(len(RRD_MAGIC))
    if head != RRD_MAGIC:
        # before the reader, which would log its own warning besides this error
        raise ReviewError(f"{path}: not an .rrd file (it starts {head!r}, not {RRD_MAGIC!r})")
    try:
        scan = scan_recording(path, on_samples)
    except Exception as e:  # noqa: BLE001 - the reader's own errors, whatever they are
        raise ReviewError(
            f"{path}: cannot read the recording (truncated? `mrrig review --verify` checks it): {e}"
        ) from e
    entities = scan.entities - {"/__properties"}
    if not entities:
        raise ReviewError(f"{path}: not a readable RRD (not an .rrd file, or truncated)")
    ours = {f"/{e}" for e in FIELD_ENTITIES.values()} | {f"/{SUMMARY_ENTITY}", "/rig"}
    if not entities & ours:
        shown = ", ".join(sorted(entities)[:5]) + (", ..." if len(entities) > 5 else "")
        raise ReviewError(
            f"{path}: not an mrrig recording: a Rerun file of another application (its"
            f" entities {shown}; an mrrig recording has /rig and the rig's series)"
        )
    return scan


_VERIFIED_RE = re.compile(r"(\d+) files? verified without error")
_FAILED_RE = re.compile(r"failed with (\d+) errors?")
_NO_FOOTER = "Missing RRD footer"


def verify_rrd(path: str | Path) -> None:
    """Check a file with `rerun rrd verify`, and that it is whole: raise ReviewError unless
    rerun reports it fine and it holds every frame its end marker counts.

    The CLI exits 0 on a non-RRD file ("0 files verified"), so its output is what counts. A
    recording has no footer (`mrrig.rigio.recording`), which is the one error of rerun's that
    is not one here; that rerun reads a file cut short without another, so the end marker
    written at `close()` and the frames read back are what say that it is whole. A recording
    from before the marker passes on rerun's verdict with its footer.
    """
    path = Path(path)
    if not path.is_file():
        raise ReviewError(f"{path}: no such file")
    rerun_cli = Path(sys.executable).parent / "rerun"
    try:
        proc = subprocess.run(
            [str(rerun_cli), "rrd", "verify", str(path)],
            capture_output=True,
            text=True,
            timeout=3600,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        raise ReviewError(f"{path}: cannot run {rerun_cli}: {e}") from e
    output = proc.stdout + proc.stderr
    m = _VERIFIED_RE.search(output)
    if proc.returncode == 0 and m is not None and int(m.group(1)) == 1:
        return  # footer and all
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    failed = _FAILED_RE.search(output)
    if failed is None or int(failed.group(1)) != 1 or _NO_FOOTER not in output:
        # the line naming the file says what is wrong; the last one only counts errors
        reason = next((ln for ln in lines if path.name in ln), lines[-1] if lines else "")
        raise ReviewError(f"{path}: rerun rrd verify failed: {reason}")
    scan = scan_checked(path, lambda batch: None)
    if scan.end is None:
        raise ReviewError(
            f"{path}: truncated: no end marker (the writer was killed or its disk failed);"
            f" {scan.frames} frames readable"
        )
    if scan.frames != scan.end.get("frames"):
        raise ReviewError(
            f"{path}: truncated: {scan.frames} frames readable of the {scan.end.get('frames')}"
            " its end marker counts"
        )


def plot_recording(rec: Recording, out_png: str | Path) -> Path:
    """The review figure (`mrrig.offline.review_report.plot`) of the whole run as a PNG."""
    from mrrig.loop.summary import summarize
    from mrrig.offline.review_report import plot

    counters = {k: v for k, v in (rec.summary or {}).items() if not isinstance(v, dict | list)}
    plot(rec, summarize(rec.samples, rec.events, counters), out_png)
    return Path(out_png)
