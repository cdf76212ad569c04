"""The loop's samples: a row per answered frame (`SAMPLE_DTYPE`), handed on a batch at a time
(to the telemetry process, the run's summary, and an in-process consumer that keeps them), and
the parts of each frame's latency."""

from __future__ import annotations

import numpy as np

from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.loop.summary import (
    LATENCY_BIN_US,
    LATENCY_PARTS,
    LATENCY_TOP_US,
    Histogram,
    SummaryAccumulator,
)


class SampleBatches:
    """`buf[n]` is the next frame's row and `split[n]` its latency parts; `take()` when `n`
    reaches the batch size. `keep`: keep every batch for `handed_over` (an in-process consumer
    such as characterize); otherwise none is kept and the memory stays fixed."""

    def __init__(self, size: int, keep: bool) -> None:
        self.keep = keep
        self.chunks: list[np.ndarray] = []  # only with keep
        self.summary = SummaryAccumulator()  # the exit summary, built batch by batch
        # per answered frame, the parts of latency_us: the wait between the bus's receive
        # timestamp and the loop's read, the loop's work from its read to the end of send()
        # (the spec's budget), and the send() call within that work
        self.split = np.full((size, 3), np.nan)
        self.split_us = {k: Histogram(LATENCY_BIN_US, LATENCY_TOP_US) for k in LATENCY_PARTS}
        self.buf = np.zeros(size, dtype=SAMPLE_DTYPE)
        self.n = 0

    def take(self) -> np.ndarray:
        """The rows so far, as a batch (added to the summary, kept where asked); `n` is 0."""
        batch = self.buf[: self.n].copy()
        if self.keep:
            self.chunks.append(batch)
        self.summary.add(batch)
        for k, part in enumerate(LATENCY_PARTS):
            self.split_us[part].add(self.split[: self.n, k])
        self.split[:] = np.nan
        self.n = 0
        return batch

    def handed_over(self, start: int = 0) -> list[np.ndarray]:
        """The sample batches completed so far, from batch `start` on (needs keep).

        Safe from another thread while the loop runs: the loop only appends whole batches,
        and a list slice is atomic.
        """
        if not self.keep:
            raise RuntimeError("the daemon keeps no batches: construct it with keep_batches=True")
        return self.chunks[start:]
