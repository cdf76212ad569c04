"""Network inversion of forward models that carry a state frame to frame: the Bouc-Wen twin
(a plant file of `mrrig identify`, mrrig/loop/twin_model.py; the grey-box too) and the GRU
(mrrig/loop/gru.py). `NetworkInversion.build` builds them for such a model."""

from __future__ import annotations

import numpy as np

from mrrig.loop.controller_base import ControlInput, Controller, ControllerSettings
from mrrig.loop.gru import GRUModel, GruTracker
from mrrig.loop.twin_model import TwinModel


class TwinInversion(Controller):
    """Network inversion with a Bouc-Wen twin (a plant file of `mrrig identify`) as the
    forward model: the twin's state carried frame to frame on the estimated motion and the
    commands sent, eq. 30 solved for the command through eq. 36's lag
    (mrrig/loop/twin_model.py). The load-cell feedback and the one-step-ahead solve as
    `NetworkInversion`'s; the solve is exact, without adaptation. Built by network_inversion
    for a twin model."""

    name = "network_inversion"
    controller_id = 1
    needs_model = True
    # network inversion's settings, as this solve has them: exact (the continuity: the pull
    # toward the present lagged current, `TwinTracker.solve`)
    method = "exact"

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        if s.method != "exact":
            raise ValueError(f"method {s.method!r}: a twin forward model is solved exactly")
        if s.adaptation is not None:
            raise ValueError("adaptation: not with a twin forward model (its force is eq. 30)")
        assert isinstance(s.model, TwinModel)
        return cls(s.i_max, s.model, s.dt_s, s.feedback_tau_s, s.ahead, s.continuity)

    def __init__(
        self,
        i_max: float,
        model: TwinModel,
        dt_s: float = 0.002,
        feedback_tau_s: float | None = None,
        ahead: bool = False,
        continuity: float = 0.0,
    ) -> None:
        super().__init__(i_max)
        if feedback_tau_s is not None and not feedback_tau_s >= 0:
            raise ValueError(f"feedback_tau_s must be >= 0, got {feedback_tau_s}")
        self.continuity = continuity
        self.model = model
        self.dt_s = dt_s
        self.feedback_tau_s = feedback_tau_s
        self.ahead = ahead
        self.wants_next_target = ahead
        self.reset(1)

    def reset(self, batch: int = 1) -> None:
        """A new run: the load-cell residual starts again; the twins keep the state the motion
        gave them (`follow_motion` while disarmed: the damper is the one that moved), where
        the lanes are as many; a twin not yet moved starts at rest at its first frame."""
        super().reset(batch)
        lanes = getattr(self, "lanes", [])
        if len(lanes) != batch:
            self.lanes = [
                self.model.tracker(self.dt_s, self.i_max, self.continuity) for _ in range(batch)
            ]
        self._residual = [0.0] * batch

    def follow_motion(self, x: float, xd: float) -> None:
        for twin in self.lanes:
            twin.command = 0.0  # the rig's SAFE answers: the coil off
            twin.advance(float(x), float(xd))

    def command_sent(self, current_a: float) -> None:
        self.lanes[0].command = current_a  # the command held until the next frame

    def command_one(
        self,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None = None,
    ) -> float:
        # plain floats: the integrator's arithmetic on numpy scalars takes 3-4 times as long
        nxt = None if f_des_next is None else float(f_des_next)
        return self._lane(0, float(x), float(xd), float(xdd), float(f_meas), float(f_des), nxt)

    def _lane(
        self,
        j: int,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None,
    ) -> float:
        twin = self.lanes[j]
        first = not twin.started
        f_twin = twin.advance(x, xd)
        ahead = self.ahead and f_des_next is not None
        r = self._residual_at(j, f_meas - f_twin, ahead and not first)
        if not ahead or f_des_next is None:
            return twin.solve(f_des - r)
        T = self.dt_s
        # the instant the command first acts on: one period on at constant acceleration (eq. 21)
        return twin.solve(f_des_next - r, x + xd * T + 0.5 * xdd * T * T, xd + xdd * T)

    def _residual_at(self, j: int, error_n: float, extrapolate: bool) -> float:
        """Lane j's load-cell residual: the measured force less the model's (`error_n`)
        low-passed over `feedback_tau_s`; where `extrapolate` (a solve one period ahead, after
        the first frame), at the solved instant, at its last rate of change. 0 without the
        feedback."""
        if self.feedback_tau_s is None:
            return 0.0
        a = self.dt_s / (self.feedback_tau_s + self.dt_s)
        last = r = self._residual[j]
        r += a * (error_n - r)
        self._residual[j] = r
        return 2.0 * r - last if extrapolate else r

    def command(self, s: ControlInput) -> np.ndarray:
        nxt = s.f_des_next
        return np.array(
            [
                self._lane(
                    j,
                    float(s.x[j]),
                    float(s.xd[j]),
                    float(s.xdd[j]),
                    float(s.f_meas[j]),
                    float(s.f_des[j]),
                    None if nxt is None else float(nxt[j]),
                )
                for j in range(self.batch)
            ]
        )

    def model_force_one(
        self, x: float, xd: float, xdd: float, f_meas: float, f_des: float, current_a: float
    ) -> float:
        return self._model_force_arrays(x, xd, xdd, f_meas, f_des, current_a)

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        """Eq. 30 at the twin's present state and the motion of `s`, with u = `current`."""
        cur = np.asarray(current, dtype=float)
        return np.array(
            [
                self.lanes[j].force(float(s.x[j]), float(s.xd[j]), float(cur[j]))
                for j in range(cur.size)
            ]
        )


class GruInversion(TwinInversion):
    """Network inversion with a GRU forward model (mrrig/loop/gru.py): its hidden state
    carried frame to frame, advanced with the commands actually sent, and its force one sample
    on solved for the command (a grid bracket and Newton steps through the gates; eq. 36's lag
    inverted for a model of the lagged current). The command of a frame acts on the next
    sample, so the solve is always for it, at the motion predicted there (eq. 21); `ahead`
    with `f_des_next` takes the desired force then as the target, else the present one. The
    load-cell feedback as `NetworkInversion`'s, the residual against the model's force now.
    Exact solve only, without adaptation; `continuity` as network inversion's (the model's
    own, `online_continuity`, chosen on its training rows), in closed form where u is the
    read-out's alone; with u in the cell the root nearest the present u. Built by
    network_inversion for a GRU model."""

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        if s.method != "exact":
            raise ValueError(f"method {s.method!r}: a GRU forward model is solved exactly")
        if s.adaptation is not None:
            raise ValueError("adaptation: not with a GRU forward model")
        assert isinstance(s.model, GRUModel)
        GruTracker(s.model, s.dt_s, s.i_max, s.continuity)  # a setting it refuses, here
        return cls(s.i_max, s.model, s.dt_s, s.feedback_tau_s, s.ahead, s.continuity)

    def __init__(
        self,
        i_max: float,
        model: GRUModel,
        dt_s: float = 0.002,
        feedback_tau_s: float | None = None,
        ahead: bool = False,
        continuity: float = 0.0,
    ) -> None:
        super().__init__(i_max, model, dt_s, feedback_tau_s, ahead, continuity)

    def follow_motion(self, x: float, xd: float) -> None:
        """Nothing: the GRU's hidden state starts at its run's first frame, as it was trained."""

    def reset(self, batch: int = 1) -> None:
        Controller.reset(self, batch)
        self.lanes = [
            GruTracker(self.model, self.dt_s, self.i_max, self.continuity) for _ in range(batch)
        ]
        self._residual = [0.0] * batch

    def _lane(
        self,
        j: int,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None,
    ) -> float:
        gru = self.lanes[j]
        first = not gru.started
        f_now = gru.advance(x, xd, xdd)
        ahead = self.ahead and f_des_next is not None
        target = f_des_next if ahead and f_des_next is not None else f_des
        target -= self._residual_at(j, f_meas - f_now, ahead and not first)
        T = self.dt_s
        return gru.solve(target, x + xd * T + 0.5 * xdd * T * T, xd + xdd * T, xdd)
