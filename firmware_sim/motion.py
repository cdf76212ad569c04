"""The actuator's motion generator: the waveforms an ActuatorCommand asks for (SINE, RANDOM,
HOLD, STOP) and STREAM's position setpoints (contract 1.1), every change ramped so that
position and velocity stay continuous. Pure numerics, no CAN: `Actuator.advance(dt_s)` gives
the position and velocity at the end of a step. `MotionStretch` is the test instrument's
record of one armed stretch's motion (`Firmware.armed_motion`).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from damper.signals import bandlimited_noise
from firmware_sim.config import ActuatorConfig

logger = logging.getLogger(__name__)


class MotionStretch(NamedTuple):
    """One stretch of ACTIVE commands (`Firmware.armed_motion`); times in s since boot."""

    start_s: float
    end_s: float  # inf while it goes on
    amplitude_at_start_m: float
    frequency_at_start_hz: float
    amplitude_max_m: float
    frequency_max_hz: float


class _Ramp:
    """A value that moves linearly to its target in a given time."""

    __slots__ = ("value", "target", "rate")

    def __init__(self, value: float = 0.0) -> None:
        self.value = value
        self.target = value
        self.rate = 0.0

    def set(self, target: float, ramp_s: float) -> None:
        """Head for target, arriving in ramp_s; a repeated target keeps the running ramp."""
        if target == self.target:
            return
        self.target = target
        self.rate = abs(target - self.value) / ramp_s

    def advance(self, dt_s: float) -> float:
        """Move by dt_s; returns the slope at the end of the step (0 once the target is hit)."""
        delta = self.target - self.value
        step = self.rate * dt_s
        if abs(delta) <= step:
            self.value = self.target
            return 0.0
        self.value += math.copysign(step, delta)
        return math.copysign(self.rate, delta)


class Actuator:
    """Displacement x = A_s sin(phase) + A_r n(tau): a sine plus a band-limited noise record.

    Every command moves amplitudes, the sine frequency and the noise's time rate linearly
    over `ramp_s`, so position and velocity stay continuous: STOP ramps both amplitudes to 0
    (rest at stroke centre), HOLD ramps the frequency and the noise rate to 0 (the motion
    slows to a standstill where it is), SINE and RANDOM cross-fade. A new RANDOM band fades
    the old record out before the new one fades in.

    STREAM (contract 1.1) follows the position setpoints instead (`stream_to`, `follow`);
    the position it leaves the stream at is an offset that STOP, SINE and RANDOM ramp to 0
    over `ramp_s` (HOLD keeps it).
    """

    def __init__(self, cfg: ActuatorConfig, period_s: float, rng: np.random.Generator) -> None:
        self._cfg = cfg
        self._period_s = period_s
        self._rng = rng
        self._amp_sine = _Ramp()
        self._freq = _Ramp()
        self._amp_rand = _Ramp()
        self._rate_rand = _Ramp(1.0)
        self._phase = 0.0
        self._tau_s = 0.0
        self._noise: tuple[list[float], list[float]] | None = None
        self._band_hz = -1.0
        self._pending: tuple[float, float] | None = None  # (peak, band) after the fade-out
        self._offset = _Ramp()  # the streamed position; where STREAM left the piston
        self._stream_target_m = 0.0  # the latest setpoint, clamped (`stream_to`)
        self.envelope_m = 0.0  # the STREAM command's envelope, within the stroke
        self.waveform = "STOP"
        self.x_m = 0.0
        self.xd_m_s = 0.0

    @property
    def at_rest(self) -> bool:
        ramps = (self._amp_sine, self._amp_rand, self._offset)
        return self.waveform != "STREAM" and all(r.value == 0.0 and r.target == 0.0 for r in ramps)

    @property
    def moving(self) -> bool:
        return self.waveform in ("SINE", "RANDOM", "STREAM") and not self.at_rest

    def motion(self) -> tuple[float, float]:
        """The motion's amplitude and highest frequency now (|x| stays within the amplitude:
        a RANDOM record peaks at 1, a cross-fade sums to at most the larger)."""
        sine, rand = self._amp_sine, self._amp_rand
        return sine.value + rand.value + abs(self._offset.value), max(
            self._freq.value if sine.value else 0.0, self._band_hz if rand.value else 0.0
        )

    def motion_in_force(self) -> tuple[float, float]:
        """`motion()` or where the ramps head, the larger of each (a sine stopping, its
        amplitude ramping to 0, still moves at the frequency its ramp heads for)."""
        sine, rand = self._amp_sine, self._amp_rand
        peak, band = self._pending or (rand.target, self._band_hz)
        amplitude_m, frequency_hz = self.motion()
        streamed = self.envelope_m if self.waveform == "STREAM" else abs(self._offset.target)
        return max(amplitude_m, sine.target + peak + streamed), max(
            frequency_hz,
            self._freq.target if sine.target or sine.value else 0.0,
            band if peak else 0.0,
        )

    def command(self, waveform: str, amplitude_m: float, frequency_hz: float) -> None:
        """Apply an ActuatorCommand (amplitude clamped to the stroke)."""
        ramp_s = self._cfg.ramp_s
        amplitude_m = min(max(amplitude_m, 0.0), self._cfg.stroke_m)
        if waveform == "STREAM":
            self.envelope_m = amplitude_m
            if self.waveform != "STREAM":  # the stream starts where the piston is
                self._amp_sine, self._amp_rand, self._pending = _Ramp(), _Ramp(), None
                self._offset.value = self._offset.target = self.x_m
                self._stream_target_m = self.x_m
            self.waveform = waveform
            return
        self.waveform = waveform
        if waveform == "HOLD":
            self._freq.set(0.0, ramp_s)
            self._rate_rand.set(0.0, ramp_s)
            return
        self._pending = None
        self._offset.set(0.0, ramp_s)
        if waveform == "SINE":
            self._amp_sine.set(amplitude_m, ramp_s)
            self._freq.set(frequency_hz, ramp_s)
            self._amp_rand.set(0.0, ramp_s)
        elif waveform == "RANDOM":
            self._amp_sine.set(0.0, ramp_s)
            self._rate_rand.set(1.0, ramp_s)
            if frequency_hz == self._band_hz:
                self._amp_rand.set(amplitude_m, ramp_s)
            else:
                self._pending = (amplitude_m, frequency_hz)
                self._amp_rand.set(0.0, ramp_s)
        else:  # STOP
            self._amp_sine.set(0.0, ramp_s)
            self._amp_rand.set(0.0, ramp_s)

    def _load_noise(self, peak_m: float, band_hz: float) -> None:
        n = round(self._cfg.random_record_s / self._period_s)
        try:
            x, xd, _ = bandlimited_noise(n, self._period_s, band_hz, 1.0, self._rng)
        except ValueError as exc:
            logger.warning("RANDOM band %.3f Hz unusable, staying at rest: %s", band_hz, exc)
            self._noise, self._band_hz = None, -1.0
            return
        self._noise = (x.tolist(), xd.tolist())
        self._band_hz = band_hz
        self._tau_s = 0.0
        self._amp_rand.set(peak_m, self._cfg.ramp_s)

    @property
    def stream_setpoint_m(self) -> float:
        """The position STREAM heads for: the latest setpoint applied (clamped), or the
        position it holds."""
        return self._stream_target_m

    def stream_to(self, setpoint_m: float) -> None:
        """The position STREAM heads for from the next step on (clamped by the firmware)."""
        self._stream_target_m = setpoint_m

    def follow(self, dt_s: float) -> tuple[float, float]:
        """STREAM: (x_m, xd_m_s) after dt_s of following the setpoint. An instant follower
        for now: the piston is at the setpoint by the end of the period, at the mean
        velocity that took."""
        x = self._stream_target_m
        return x, (x - self.x_m) / dt_s

    def advance(self, dt_s: float) -> tuple[float, float]:
        """Move on by dt_s; returns (x_m, xd_m_s) at the end of the step."""
        if self.waveform == "STREAM":
            x, xd = self.follow(dt_s)
            self._offset.value = self._offset.target = x
            self.x_m, self.xd_m_s = x, xd
            return x, xd
        o_dot = self._offset.advance(dt_s)
        f0 = self._freq.value
        a_s_dot = self._amp_sine.advance(dt_s)
        self._freq.advance(dt_s)
        self._phase = (self._phase + math.pi * (f0 + self._freq.value) * dt_s) % (2.0 * math.pi)
        r0 = self._rate_rand.value
        self._rate_rand.advance(dt_s)
        a_r_dot = self._amp_rand.advance(dt_s)
        if self._pending is not None and self._amp_rand.value == 0.0:
            pending, self._pending = self._pending, None
            self._load_noise(*pending)
        a_s = self._amp_sine.value
        s, c = math.sin(self._phase), math.cos(self._phase)
        x = a_s * s + self._offset.value
        xd = a_s_dot * s + a_s * 2.0 * math.pi * self._freq.value * c + o_dot
        if self._noise is not None:
            record_s = len(self._noise[0]) * self._period_s
            self._tau_s = (self._tau_s + 0.5 * (r0 + self._rate_rand.value) * dt_s) % record_s
            pos = self._tau_s / self._period_s
            i = int(pos)
            frac = pos - i
            nx, nv = self._noise
            j = (i + 1) % len(nx)
            n = nx[i] + frac * (nx[j] - nx[i])
            nd = nv[i] + frac * (nv[j] - nv[i])
            a_r = self._amp_rand.value
            x += a_r * n
            xd += a_r_dot * n + a_r * self._rate_rand.value * nd
        self.x_m, self.xd_m_s = x, xd
        return x, xd
