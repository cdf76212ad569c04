"""Desired-force sources: what the daemon asks the damper for at each instant.

Pure numerics: a source maps (time, motion estimate) to a force in N. The Zenoh source (an
upper-level controller sending `force_ref`) is fed from outside and goes stale after a timeout.
"""

from __future__ import annotations

import abc
import math
from dataclasses import astuple
from pathlib import Path

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams, bouc_wen_force
from damper.plant_file import load_plant
from damper.signals import bandlimited_noise
from mrrig.errors import MrrigError
from mrrig.loop import profile_csv


class ForceReferenceError(MrrigError, ValueError):
    """A force reference that cannot be built (bad parameters, unreadable file)."""


class StaleReference(MrrigError):
    """The external force reference is older than its timeout."""


class ForceReference(abc.ABC):
    kind: str = ""
    # whether the force of a later instant can be computed now (from a predicted state); an
    # external source's is only known when it arrives
    known_ahead = True

    def reset(self, t_s: float, x_m: float) -> None:  # noqa: B027 - most sources are stateless
        """Called when a run (or this source) starts at time t_s."""

    @abc.abstractmethod
    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        """Desired force at t_s, N."""

    def forecast(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        """The desired force at a coming instant t_s, from the motion predicted there, without
        moving the source on: what a controller solves for before the instant comes. A source
        whose force depends on the motion's path (`follows_motion`) forecasts from the state
        it reached at its last `force` instant; any other's forecast is its force."""
        return self.force(t_s, x_m, xd_m_s)

    def motion_state(self) -> tuple | None:
        """What the measured motion has put the source in (a reference damper's hysteresis
        state), for `resume`; None: a source of time alone, or a state that is not finite."""
        return None

    def resume(self, state: tuple | None) -> None:  # noqa: B027 - most sources keep none
        """After `reset`: take the state `motion_state` gave (of this source before, or of
        the one it replaces), where it is one of the same damper's."""

    def current_at(self, t_s: float) -> float:
        """The current a reference damper is driven with over the period that ends at t_s
        (what the `reference_current` controller commands); NaN: a source without one."""
        return math.nan

    # whether the force depends on the path of the motion (a reference damper): the daemon
    # then moves the source on by `force` on the motion as estimated at each instant, once its
    # frame has come, and that force is the instant's desired force (what it records and
    # judges Et by); the controller's targets are `forecast`s
    follows_motion = False


class Constant(ForceReference):
    kind = "constant"

    def __init__(self, offset_n: float) -> None:
        self.offset_n = offset_n

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        return self.offset_n


class Sine(ForceReference):
    kind = "sine"

    def __init__(self, offset_n: float, amplitude_n: float, freq_hz: float) -> None:
        if freq_hz <= 0:
            raise ForceReferenceError(f"sine: freq_hz must be positive, got {freq_hz}")
        self.offset_n, self.amplitude_n, self.w = offset_n, amplitude_n, 2 * math.pi * freq_hz

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        return self.offset_n + self.amplitude_n * math.sin(self.w * t_s)


class Noise(ForceReference):
    """Band-limited Gaussian noise (0..freq_hz), periodic over `period_s`, seeded."""

    kind = "noise"

    def __init__(
        self,
        offset_n: float,
        amplitude_n: float,
        freq_hz: float,
        seed: int,
        dt_s: float,
        period_s: float = 60.0,
    ) -> None:
        if freq_hz <= 0:
            raise ForceReferenceError(f"noise: freq_hz must be positive, got {freq_hz}")
        n = int(round(period_s / dt_s))
        self._f, _, _ = bandlimited_noise(
            n, dt_s, freq_hz, amplitude_n, np.random.default_rng(seed)
        )
        self._f = (self._f + offset_n).tolist()
        self.dt_s = dt_s

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        return self._f[int(t_s / self.dt_s) % len(self._f)]


class CsvSeries(ForceReference):
    """A time series from a CSV file (columns `t_s`, `force_n`), linearly interpolated.

    Before the first time it gives the first force; after the last it holds the last one.
    """

    kind = "csv"

    def __init__(
        self,
        path: Path,
        time_column: str = "t_s",
        force_column: str = "force_n",
        text: str | None = None,
    ):
        """`text`: the file's content, already read (the control plane reads under limits).
        The file is read by `profile_csv` (the reader of `mrrig send-force` too)."""
        try:
            if text is None:
                t, f = profile_csv.read(str(path), time_column, force_column)
            else:
                t, f = profile_csv.parse(text, str(path), time_column, force_column)
        except profile_csv.ProfileError as exc:
            raise ForceReferenceError(str(exc)) from None
        self.path = Path(path)
        self.t, self.f = t, f
        self._t0 = 0.0

    def reset(self, t_s: float, x_m: float) -> None:
        self._t0 = t_s

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        return float(np.interp(t_s - self._t0, self.t, self.f))


class BoucWenReference(ForceReference):
    """The force a reference Bouc-Wen damper would give for the measured motion and a current.

    This is the paper's validation protocol brought to the rig: the desired force is what a
    damper with the given current profile (constant + sine) produces, so it is reachable.

    `force(t, x, xd)` moves the damper on to t along the motion (x, xd at t), one period a
    call (the periods since the last call where frames were lost); `forecast` steps a copy
    from there to a coming instant and leaves the damper where it was. The daemon moves it
    on the Kalman filter's estimate of each instant once that instant's frame has come, and
    forecasts the controller's targets from the predicted motion: a damper moved on the
    predictions themselves integrates their errors into its hysteresis state (eq. 31), and
    its pre-yield stiffness (alpha A, eqs 31-33: about 2.4 N per um at 0.75 A) makes 1-2 um
    of displacement error newtons of force.
    """

    kind = "bouc_wen"
    follows_motion = True

    def __init__(
        self,
        preset: str,
        current_a: float,
        current_amp_a: float,
        current_freq_hz: float,
        dt_s: float,
    ) -> None:
        # a preset, or a plant file (`mrrig identify`'s twin; a twin in V takes 1 V per A, as
        # firmware_sim's [plant] command_per_a default): its force offset added
        self._offset_n = 0.0
        try:
            if preset.endswith(".json"):
                twin = load_plant(preset)
                params, self._offset_n = twin.params, twin.offset_n
            else:
                params = BoucWenParams.preset(preset)
        except ValueError as exc:
            raise ForceReferenceError(str(exc)) from None
        self._damper = BoucWenDamper(params, substep_s=2.5e-4)
        self._params = astuple(params)
        self.current_a, self.current_amp_a = current_a, current_amp_a
        self.w = 2 * math.pi * current_freq_hz
        self.dt_s = dt_s
        self.reset(0.0, 0.0)

    def reset(self, t_s: float, x_m: float) -> None:
        self._t = t_s  # the instant the damper is at, and the motion there
        self._motion = (x_m, 0.0)
        self._f = self._offset_n + self._damper.reset(x_m, 0.0, self.current_a)
        # the forecasts since: (t, state, x, xd, force) of the latest
        self._ahead: tuple | None = None

    def _current(self, t_s: float) -> float:
        return max(0.0, self.current_a + self.current_amp_a * math.sin(self.w * t_s))

    def current_at(self, t_s: float) -> float:
        return self._current(t_s)

    def motion_state(self) -> tuple | None:
        z, y, _u = self._damper.state
        if not (math.isfinite(z) and math.isfinite(y)):
            return None
        return (self._params, self._offset_n, z, y, self._t, self._motion)

    def resume(self, state: tuple | None) -> None:
        # the damper's z and y as the motion left them (its coil as `reset` put it): the
        # damper under test moved all along too, and its internal displacement y relaxes
        # toward the stroke's centre over (c0 + c1) / k0 (about 14 s at 0.75 A); one started
        # at rest where it is armed (y = x) asks for k0 (x - y) more, a force no current gives
        if state is None or state[:2] != (self._params, self._offset_n):
            return
        _params, _offset, z, y, t, motion = state
        d = self._damper
        u = d.state[2]
        d.set_state((z, y, u), *motion)
        self._t, self._motion, self._ahead = t, motion, None
        self._f = bouc_wen_force(z, y, u, *motion, self._params) + self._offset_n

    def _periods(self, t_s: float, since_s: float) -> int:
        return round((t_s - since_s) / self.dt_s)

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        d = self._damper
        n = self._periods(t_s, self._t)
        if n <= 0:  # the instant it is at (a reset there): the motion there as now given
            d.set_state(d.state, x_m, xd_m_s)
            self._f = bouc_wen_force(*d.state, x_m, xd_m_s, self._params) + self._offset_n
        else:
            self._f = d.step(x_m, xd_m_s, self._current(t_s), n * self.dt_s) + self._offset_n
            self._t = t_s
        self._motion, self._ahead = (x_m, xd_m_s), None
        return self._f

    def forecast(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        ahead = self._ahead
        if ahead is not None and self._periods(t_s, ahead[0]) == 0:
            return ahead[4]  # forecast already (the daemon's targets, a frame before)
        n = self._periods(t_s, self._t)
        if n <= 0:
            return self._f
        d = self._damper
        here = (d.state, *self._motion)
        t0 = self._t
        if ahead is not None and 0 < self._periods(ahead[0], self._t) < n:
            d.set_state(ahead[1], ahead[2], ahead[3])  # on from the latest forecast
            t0 = ahead[0]
        f = d.step(x_m, xd_m_s, self._current(t_s), self._periods(t_s, t0) * self.dt_s)
        f += self._offset_n
        self._ahead = (t_s, d.state, x_m, xd_m_s, f)
        d.set_state(*here)
        return f


# Table 6's validation cases (spec/modeling.md section 4 A): 6 s at 1 ms, drawn with data set
# A's validation seed (mrrig.offline.datasets draws them the same way; tests/test_tune.py
# checks the two agree)
PAPER_CASE_NAMES = ("1,k=1", "1,k=2", "1,k=3", "2", "3,k=1", "3,k=2", "3,k=3")
PAPER_CASE_SEED = 4202
PAPER_CASE_DT_S = 1e-3
PAPER_CASE_S = 6.0


def paper_case_command(case: int, seed: int = PAPER_CASE_SEED) -> np.ndarray:
    """The coil input of validation case `case` (1-7, Table 6's column order) over its 6 s at
    1 ms, in the paper's volts: (1) 1.5 V; (2) 2 V + noise 0-2 Hz peak 2 V, clipped at 0;
    (3) 1.5 + 0.75 sin(2 k pi t) V."""
    if not 1 <= case <= len(PAPER_CASE_NAMES):
        raise ForceReferenceError(f"paper_case: case must be 1-{len(PAPER_CASE_NAMES)}, got {case}")
    n = round(PAPER_CASE_S / PAPER_CASE_DT_S)
    t = np.arange(n) * PAPER_CASE_DT_S
    if case <= 3:
        return np.full(n, 1.5)
    if case >= 5:
        return 1.5 + 0.75 * np.sin(2.0 * (case - 4) * np.pi * t)
    rng = np.random.default_rng(seed)
    bandlimited_noise(n, PAPER_CASE_DT_S, 2.0, 0.02, rng)  # the cases' displacement comes first
    return np.maximum(bandlimited_noise(n, PAPER_CASE_DT_S, 2.0, 2.0, rng)[0] + 2.0, 0.0)


class PaperCase(BoucWenReference):
    """The force the reference damper gives for the measured motion and the coil input of one
    of Table 6's validation cases (`paper_case_command`), repeated every 6 s from the source's
    start: the paper's desired force, "the plant's force for the validation displacement and
    voltage", brought to the rig. The paper's volts become `current_scale` A per V (the
    rig-current preset is Table 3 per ampere: 1 A per V asks the paper's forces themselves)."""

    kind = "paper_case"

    def __init__(self, case: int, current_scale: float, preset: str, dt_s: float) -> None:
        self._i = (current_scale * paper_case_command(case)).tolist()
        # the damper starts as the one that made the desired force: its coil at the first input
        super().__init__(preset, self._i[0], 0.0, 1.0, dt_s)

    def reset(self, t_s: float, x_m: float) -> None:
        self._t0 = t_s
        super().reset(t_s, x_m)

    def _current(self, t_s: float) -> float:
        # the input held over the step that ends at t_s (zero-order hold, as the paper's plant
        # is simulated: `damper.plant.simulate`)
        k = round((t_s - self._t0) / PAPER_CASE_DT_S) - 1
        return self._i[k % len(self._i)]


class External(ForceReference):
    """The latest value sent on `mrrig/<rig>/force_ref`; stale after `timeout_s`."""

    kind = "zenoh"
    known_ahead = False

    def __init__(self, timeout_s: float) -> None:
        if timeout_s <= 0:
            raise ForceReferenceError(f"zenoh: timeout_s must be positive, got {timeout_s}")
        self.timeout_s = timeout_s
        self._value: float | None = None
        self._t_rx = -math.inf
        self.now = 0.0  # the daemon's clock, set before force()

    def receive(self, force_n: float, t_rx_s: float) -> None:
        self._value, self._t_rx = force_n, t_rx_s

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        if self._value is None:
            raise StaleReference("no force_ref received yet")
        age = t_s - self._t_rx
        if age > self.timeout_s:
            raise StaleReference(
                f"force_ref is {age * 1e3:.0f} ms old (timeout {self.timeout_s * 1e3:.0f} ms)"
            )
        return self._value


def check_in_range(reference: ForceReference, f_range_n: tuple[float, float]) -> None:
    """Refuse a force reference whose forces leave `loop.f_range_n` (ForceReferenceError naming
    the first sample outside, or the setting); the daemon clamps every desired force too, for
    the sources known only as they come (force_ref, the reference damper)."""
    lo, hi = f_range_n
    where = f"outside loop.f_range_n [{lo:g}, {hi:g}] N"
    if isinstance(reference, CsvSeries):
        outside = np.flatnonzero((reference.f < lo) | (reference.f > hi))
        if outside.size:
            k = int(outside[0])
            raise ForceReferenceError(
                f"{reference.path}: force_n {reference.f[k]:g} N at t_s {reference.t[k]:g} s "
                f"(sample {k + 1}; {outside.size} samples in all) is {where}"
            )
    elif isinstance(reference, Constant | Sine):
        amp = reference.amplitude_n if isinstance(reference, Sine) else 0.0
        low, high = reference.offset_n - amp, reference.offset_n + amp
        if low < lo or high > hi:
            raise ForceReferenceError(
                f"reference: {reference.kind} from {low:g} to {high:g} N is {where}"
            )
    elif isinstance(reference, Noise):
        low, high = min(reference._f), max(reference._f)
        if low < lo or high > hi:
            raise ForceReferenceError(f"reference: noise from {low:.6g} to {high:.6g} N is {where}")
