"""The RTHS benchmark's tracking metrics and the response errors (spec/hil.md, Metrics), from
recorded arrays: x_c the commanded stroke (what the numerical model asked for that frame's
time), x_m the measured Displacement, one sample per frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_LAG_SAMPLES = 49


@dataclass(frozen=True)
class Tracking:
    j1_ms: float  # J1, the lag at the cross-correlation's peak, refined between samples
    j1_lag_samples: int  # the peak's whole lag in 0..49 (the spec's J1 / period)
    j2_pct: float  # J2, normalised RMS tracking error
    j3_pct: float  # J3, normalised peak tracking error


def tracking(x_c: np.ndarray, x_m: np.ndarray, period_s: float) -> Tracking:
    """J1: the lag of x_m behind x_c at the maximum of their cross-correlation over lags
    0..49 samples (one-sided), in ms; refined by the parabola through the peak and its
    neighbours (lag -1 included, so a measured stroke that leads reads a J1 below 0), since
    one sample at 500 Hz is 2 ms and the spec's bound is 0.5 ms.
    J2 = 100 std(x_m - x_c) / std(x_c);  J3 = 100 max|x_m - x_c| / max|x_c|."""
    x_c = np.asarray(x_c, dtype=float)
    x_m = np.asarray(x_m, dtype=float)
    if x_c.shape != x_m.shape or x_c.ndim != 1 or x_c.size <= MAX_LAG_SAMPLES + 1:
        raise ValueError(
            f"x_c and x_m: two series of one length over {MAX_LAG_SAMPLES + 1} samples, "
            f"got {x_c.shape} and {x_m.shape}"
        )
    c, m = x_c - x_c.mean(), x_m - x_m.mean()
    n = c.size
    lags = np.arange(-1, MAX_LAG_SAMPLES + 1)
    # r(j) = sum_k x_m[k] x_c[k - j]: x_m lagging x_c by j samples
    r = np.array(
        [np.dot(m[max(j, 0) : n + min(j, 0)], c[max(-j, 0) : n - max(j, 0)]) for j in lags]
    )
    peak = int(np.argmax(r[1:])) + 1
    lag = float(lags[peak])
    if peak + 1 < r.size:
        lo, mid, hi = r[peak - 1], r[peak], r[peak + 1]
        curvature = lo - 2.0 * mid + hi
        if curvature < 0.0:
            lag += 0.5 * (lo - hi) / curvature
    error = x_m - x_c
    return Tracking(
        j1_ms=1e3 * lag * period_s,
        j1_lag_samples=int(lags[peak]),
        j2_pct=100.0 * float(np.std(error) / np.std(x_c)),
        j3_pct=100.0 * float(np.max(np.abs(error)) / np.max(np.abs(x_c))),
    )


@dataclass(frozen=True)
class ResponseError:
    rms_pct: float  # 100 rms(y - y_ref) / rms(y_ref)
    peak_pct: float  # 100 max|y - y_ref| / max|y_ref|
    rms_of_rms_pct: float  # 100 (rms(y) - rms(y_ref)) / rms(y_ref): the figure's error


def response_error(y: np.ndarray, y_ref: np.ndarray) -> ResponseError:
    """A HIL response against the reference's, sample by sample (the same frames)."""
    y, y_ref = np.asarray(y, dtype=float), np.asarray(y_ref, dtype=float)
    if y.shape != y_ref.shape:
        raise ValueError(f"y and y_ref: one shape, got {y.shape} and {y_ref.shape}")
    rms_ref = float(np.sqrt(np.mean(y_ref**2)))
    d = y - y_ref
    return ResponseError(
        rms_pct=100.0 * float(np.sqrt(np.mean(d**2))) / rms_ref,
        peak_pct=100.0 * float(np.max(np.abs(d))) / float(np.max(np.abs(y_ref))),
        rms_of_rms_pct=100.0 * (float(np.sqrt(np.mean(y**2))) - rms_ref) / rms_ref,
    )


# a frame of a stall: its answer took longer than this many periods (it reached the firmware
# after the next frame was due: the setpoint is dropped as late, can-protocol.md), or it
# arrived this many periods after the frame before it (the bus or the simulator held up)
STALL_PERIODS = 1.0
GAP_PERIODS = 1.5
# the frames after a stall whose tracking error is the stall's: the servo's settling (50 Hz,
# damped 0.67) behind two frames of transport
AFTER_STALL_S = 0.02


@dataclass(frozen=True)
class StallApart:
    stalls: int  # frames of a measured stall
    excluded: int  # frames within AFTER_STALL_S of one
    j2_pct: float  # J2 and J3 over the frames left
    j3_pct: float
    peak_t_s: float  # where the whole run's largest |x_m - x_c| is
    peak_after_stall: bool  # and whether a stall explains it


def stall_frames(t_s: np.ndarray, latency_us: np.ndarray, period_s: float) -> np.ndarray:
    """The frames of a measured stall of the loop (`STALL_PERIODS`, `GAP_PERIODS`): the
    setpoint the firmware got late, or a frame the bus delivered late."""
    t_s, latency_us = np.asarray(t_s, float), np.asarray(latency_us, float)
    gap = np.diff(t_s, prepend=t_s[:1])
    return (latency_us > STALL_PERIODS * period_s * 1e6) | (gap > GAP_PERIODS * period_s)


def tracking_apart_from_stalls(
    x_c: np.ndarray, x_m: np.ndarray, t_s: np.ndarray, latency_us: np.ndarray, period_s: float
) -> StallApart:
    """J2 and J3 over the frames that no measured stall explains: each stall frame and the
    `AFTER_STALL_S` after it set aside (a late setpoint is dropped by the firmware, whatever
    the compensation: the piston heads for the last one it took)."""
    x_c, x_m = np.asarray(x_c, float), np.asarray(x_m, float)
    stalls = stall_frames(t_s, latency_us, period_s)
    after = int(round(AFTER_STALL_S / period_s))
    # frame j is set aside when a stall is among frames j - after .. j
    count = np.convolve(stalls.astype(int), np.ones(after + 1, int))[: stalls.size]
    excluded = count > 0
    error = x_m - x_c
    kept = error[~excluded]
    peak = int(np.argmax(np.abs(error)))
    return StallApart(
        stalls=int(stalls.sum()),
        excluded=int(excluded.sum()),
        j2_pct=100.0 * float(np.std(kept) / np.std(x_c)),
        j3_pct=100.0 * float(np.max(np.abs(kept)) / np.max(np.abs(x_c))),
        peak_t_s=float(np.asarray(t_s, float)[peak]),
        peak_after_stall=bool(excluded[peak]),
    )


@dataclass(frozen=True)
class StallWindow:
    """A stall that something measured (`kind`: the actuator's "setpoint dropped", the
    simulator's "simulator" or "transport" window, the daemon's "kernel" stall), on the run's
    clock (the times of the frames it is set beside)."""

    kind: str
    start_s: float
    end_s: float

    def __str__(self) -> str:
        return f"{self.kind} [{self.start_s:.3f}, {self.end_s:.3f}] s"


@dataclass(frozen=True)
class WindowsApart:
    windows: tuple[StallWindow, ...]  # the measured ones, merged where they touch
    excluded: int  # frames inside one or within AFTER_STALL_S after its end
    j2_pct: float  # J2 and J3 over the frames left
    j3_pct: float
    peak_t_s: float  # where the whole run's largest |x_m - x_c| is
    peak_window: StallWindow | None  # the window that explains it; None: none does
    kept_peak_t_s: float  # where the largest error of the frames left is


def merged_windows(windows: list[StallWindow], join_s: float) -> tuple[StallWindow, ...]:
    """Windows that overlap or lie within `join_s` of each other as one (their kinds joined
    with "+", each once): one stall may delay a frame, then drop its setpoint."""
    out: list[StallWindow] = []
    for w in sorted(windows, key=lambda w: w.start_s):
        if out and w.start_s <= out[-1].end_s + join_s:
            last = out[-1]
            kinds = last.kind.split("+")
            kind = last.kind if w.kind in kinds else f"{last.kind}+{w.kind}"
            out[-1] = StallWindow(kind, last.start_s, max(last.end_s, w.end_s))
        else:
            out.append(w)
    return tuple(out)


def tracking_apart_from_windows(
    x_c: np.ndarray,
    x_m: np.ndarray,
    t_s: np.ndarray,
    windows: list[StallWindow],
    period_s: float,
) -> WindowsApart:
    """J2 and J3 over the frames (times `t_s`, the windows' clock) that no measured stall
    window explains: a frame inside a window or within `AFTER_STALL_S` after its end (the
    servo's settling) is set aside, nothing else. A dropped setpoint's window is the instant
    the firmware dropped it: the piston went on to the last one it took."""
    x_c, x_m, t_s = np.asarray(x_c, float), np.asarray(x_m, float), np.asarray(t_s, float)
    if not x_c.shape == x_m.shape == t_s.shape:
        raise ValueError(f"x_c, x_m, t_s: one shape, got {x_c.shape}, {x_m.shape}, {t_s.shape}")
    merged = merged_windows(windows, period_s)
    excluded = np.zeros(t_s.size, dtype=bool)
    inside: list[np.ndarray] = []
    for w in merged:
        here = (t_s >= w.start_s) & (t_s <= w.end_s + AFTER_STALL_S)
        inside.append(here)
        excluded |= here
    error = np.abs(x_m - x_c)
    peak = int(np.argmax(error))
    if excluded.all():
        raise ValueError("every frame lies in a measured stall window: nothing left to judge")
    kept = np.where(excluded, -np.inf, error)
    kept_peak = int(np.argmax(kept))
    left = (x_m - x_c)[~excluded]
    return WindowsApart(
        windows=merged,
        excluded=int(excluded.sum()),
        j2_pct=100.0 * float(np.std(left) / np.std(x_c)),
        j3_pct=100.0 * float(error[kept_peak] / np.max(np.abs(x_c))),
        peak_t_s=float(t_s[peak]),
        peak_window=next((w for w, h in zip(merged, inside, strict=True) if h[peak]), None),
        kept_peak_t_s=float(t_s[kept_peak]),
    )


@dataclass(frozen=True)
class TooFast:
    frames: int  # frames whose stroke velocity is beyond the limit
    peak_m_s: float  # the largest |velocity| asked
    peak_t_s: float  # and when (from the first frame)


def too_fast(x_c: np.ndarray, period_s: float, limit_m_s: float) -> TooFast | None:
    """Where a commanded stroke (one sample per frame) asks a velocity (central differences)
    beyond an actuator's `limit_m_s`, which no compensation can give: the piston falls behind
    there. None where it never does."""
    v = np.abs(np.gradient(np.asarray(x_c, float), period_s))
    over = int(np.count_nonzero(v > limit_m_s))
    if not over:
        return None
    k = int(np.argmax(v))
    return TooFast(over, float(v[k]), k * period_s)
