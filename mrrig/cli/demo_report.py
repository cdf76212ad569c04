"""The demo's progress (one line a second while it runs) and its verdict at the end.

Progress comes from the daemon's telemetry over Zenoh: time, Et over the armed samples so far
(the paper's eq. 41, from running sums), the armed share and the faults seen. The verdict
checks the daemon's own summary against the demo's bounds (`DemoBounds`) and prints PASS or
FAIL with each bound's number, then the commands that open the recording.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.loop.samples import RigState


@dataclasses.dataclass(frozen=True)
class DemoBounds:
    """What a demo run must show: tracking with network inversion on the simulated rig."""

    et_max: float = 0.10  # Et over the armed frames (the model's own is about 0.02)
    armed_share_min: float = 0.5  # of the daemon's frames: re-arming keeps it high
    # faults other than the transport's (a stall of this machine) end the run's tracking


class RunningEt:
    """Et (eq. 41) over the armed samples received so far, from running sums; fed by the
    telemetry subscriber's thread, read by the demo's."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.n = self.armed = 0
        self._sum_err2 = self._sum_fd = self._sum_fd2 = 0.0

    def __call__(self, sample: Any) -> None:
        fields = json.loads(sample.payload.to_bytes())["fields"]
        self.add(fields)

    def add(self, fields: Mapping[str, list]) -> None:
        state = np.asarray(fields["state"])
        f_des = np.asarray(fields["f_des"], dtype=float)
        f_meas = np.asarray(fields["f_meas"], dtype=float)
        keep = (state == RigState.ARMED) & np.isfinite(f_des) & np.isfinite(f_meas)
        fd, fm = f_des[keep], f_meas[keep]
        with self._lock:
            self.n += state.size
            self.armed += int(keep.sum())
            self._sum_err2 += float(np.sum((fd - fm) ** 2))  # eq. 42
            self._sum_fd += float(fd.sum())
            self._sum_fd2 += float(np.sum(fd * fd))

    def et(self) -> float:
        with self._lock:
            if self.armed < 2:
                return math.nan
            spread2 = self._sum_fd2 - self._sum_fd**2 / self.armed  # eq. 43
            return math.sqrt(self._sum_err2 / spread2) if spread2 > 0 else math.nan  # eq. 41


class DemoProgress:
    """One progress line a second on stdout, from the daemon's telemetry and status."""

    def __init__(self, duration_s: float, period_s: float = 1.0) -> None:
        self.et = RunningEt()
        self.duration_s, self.period_s = duration_s, period_s
        self._next = time.monotonic() + period_s
        self._waited = 0.0

    def tick(self, status: Mapping[str, Any] | None, faults: int, rearmed: int) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.period_s
        if status is None:
            self._waited += self.period_s
            if self._waited % 5 < self.period_s:  # a line every 5 s while it starts
                print(f"demo: starting the daemon ({self._waited:.0f} s)", flush=True)
            return
        print(progress_line(status["t"], self.duration_s, self.et, faults, rearmed), flush=True)


def progress_line(t_s: float, duration_s: float, et: RunningEt, faults: int, rearmed: int) -> str:
    e = et.et()
    et_text = "   n/a" if math.isnan(e) else f"{e:6.4f}"
    share = et.armed / et.n if et.n else 0.0
    return (
        f"demo: {t_s:5.1f}/{duration_s:g} s  Et so far {et_text}  armed {share:4.0%}"
        f"  faults {faults} (re-armed {rearmed})"
    )


def verdict(
    summary: Mapping[str, Any], bounds: DemoBounds = DemoBounds(), gaps: Sequence[str] = ()
) -> tuple[bool, str]:
    """PASS/FAIL of the daemon's summary against `bounds`, with every number; an Et that is
    n/a with its reason: the config's `gaps` (`mrrig.config_gaps`), else what the summary
    shows."""
    et = summary.get("et")
    frames, armed = summary.get("frames") or 0, summary.get("armed_frames") or 0
    share = armed / frames if frames else 0.0
    other = [
        f"{f.get('fault', '?')}: {f.get('reason')}"
        for f in summary.get("faults", [])
        if f.get("fault") not in TRANSPORT_FAULTS
    ]
    checks = [
        (
            et is not None and math.isfinite(et) and et <= bounds.et_max,
            f"Et {'n/a' if et is None else f'{et:.4f}'} <= {bounds.et_max:g}",
        ),
        (
            share >= bounds.armed_share_min,
            f"armed {armed} of {frames} frames ({share:.0%} >= {bounds.armed_share_min:.0%})",
        ),
        (
            not other,
            f"faults other than transport: {len(other)}" + "".join(f"; {r}" for r in other),
        ),
    ]
    ok = all(c for c, _ in checks)
    lines = [f"demo: {'PASS' if ok else 'FAIL'}"] + [
        f"  {'ok  ' if c else 'FAIL'} {text}" for c, text in checks
    ]
    if et is None or not math.isfinite(et):
        lines.append(f"  why Et is n/a: {_et_missing(summary, armed, gaps)}")
    transport = [f for f in summary.get("faults", []) if f.get("fault") in TRANSPORT_FAULTS]
    if transport and not checks[0][0]:
        times = ", ".join(f"{f['t']:.1f}" for f in transport)
        lines.append(
            f"  note: {len(transport)} transport faults (t = {times} s; a stall of this machine"
            " or of the bus) put their own error into the armed frames: the Tracking tab of"
            " the recording shows it there"
        )
    return ok, "\n".join(lines)


def _et_missing(summary: Mapping[str, Any], armed: int, gaps: Sequence[str]) -> str:
    """Why the summary has no Et, in one line."""
    if armed < 2:
        return "the daemon was armed for fewer than 2 frames (see its faults above)"
    reference = next((g for g in gaps if "[reference]" in g), None)
    if reference is not None:
        return reference
    return (
        f"the desired force (reference {summary.get('reference', '?')}) did not vary over the"
        " armed frames: eqs 41-43 divide by its spread"
    )


def open_hint(recording: Path) -> str:
    return (
        f"open the recording: rerun {recording}\n"
        f"  or a report: mrrig review {recording} --html {recording.with_suffix('.html')}"
    )
