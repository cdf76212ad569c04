"""The daemon's own safety logic (spec/system.md, Safety): states, faults and their reasons.

Pure: it is told what happened (a bad frame, a sensor frame's values, a firmware status, a
non-finite number, a stale reference) and answers with the events it causes. Any fault puts it
in FAULT at once; the loop then sends SAFE 0 A for this and every following frame until the
fault is acknowledged (`reset`, to IDLE) and the rig armed again: two explicit acts, as a rig
controller separates the interlock reset from the run. One exception: a transport fault
(TRANSPORT_FAULTS: a stall of the bus or the machine) of a rig that was not armed ends by
itself with the next valid sensor frame, back to IDLE with an event saying so; nothing was
running that it interrupted. An armed rig's never does. Errors are returned as events, never
raised: the loop keeps running.
"""

from __future__ import annotations

import collections
import enum
import math
from dataclasses import dataclass

from mrrig.loop.samples import RigState

# after another sender's command was last seen, arming stays refused this long: a second
# controller on the rig's bus may send only now and then (its own IDLE SAFE commands)
FOREIGN_HOLD_S = 1.0


class Fault(enum.Enum):
    BAD_FRAMES = "bad_frames"  # CRC mismatch / repeated counter beyond the budget
    LOST_FRAMES = "lost_frames"  # counter jumps beyond the budget
    SENSOR_TIMEOUT = "sensor_timeout"  # no RigSensors frame for timeout_periods
    DISPLACEMENT_RANGE = "displacement_range"
    FORCE_RANGE = "force_range"
    NON_FINITE = "non_finite"  # NaN/inf in the estimate or the model
    STALE_REFERENCE = "stale_reference"
    FIRMWARE_FAULT = "firmware_fault"  # RigStatus State FAULT
    FIRMWARE_WATCHDOG = "firmware_watchdog"  # RigStatus CommandTimeouts moved while armed
    ESTOP = "estop"
    LIMIT_TRIPPED = "limit_tripped"
    SENSOR_FAULT = "sensor_fault"
    BUS_ERROR = "bus_error"
    FOREIGN_COMMAND = "foreign_command"  # a command the DBC has only the daemon send, not ours
    INTERNAL_ERROR = "internal_error"  # an unexpected exception in the cycle
    STALE_FRAME = "stale_frame"  # a sensor frame older than loop.max_frame_age_s when answered
    TELEMETRY_LOST = "telemetry_lost"  # the telemetry process died or stopped its heartbeat
    RECORDING_FAILED = "recording_failed"  # the recording could not be written
    DUPLICATE_RIG = "duplicate_rig"  # a second daemon of this rig's name on the Zenoh network
    NO_SENSOR_FRAMES = "no_sensor_frames"  # none valid within the sensor timeout of start/arm
    LEASE_LAPSED = "lease_lapsed"  # the client that armed stopped renewing its lease
    # the error detectors' disarm and stop actions (mrrig/loop/detectors.py)
    TRACKING_ERROR = "tracking_error"
    OVER_VELOCITY = "over_velocity"
    OVER_TEMPERATURE = "over_temperature"
    # the hybrid loop's checks (mrrig/hil/watch.py): unstable, out of envelope, not tracking
    HIL_SAFETY = "hil_safety"


# The faults a transport stall causes (a bus or a process held up past the sensor timeout or
# the firmware's 20 ms watchdog): `mrrig validate` tries such a window again, `mrrig demo`
# re-arms after them, each with an explicit `reset` first. The daemon itself never re-arms.
TRANSPORT_FAULTS = frozenset(
    {
        Fault.SENSOR_TIMEOUT.value,
        Fault.LOST_FRAMES.value,
        Fault.FIRMWARE_WATCHDOG.value,
        Fault.STALE_FRAME.value,
    }
)


@dataclass(frozen=True)
class Limits:
    x_range_m: tuple[float, float]
    f_range_n: tuple[float, float]
    bad_frame_budget: int
    lost_frame_budget: int
    budget_window_s: float


class Supervisor:
    """IDLE -> (arm) -> ARMED -> (disarm) -> IDLE; any fault -> FAULT; FAULT -> (reset) -> IDLE.

    `arm` in FAULT is refused and `disarm` leaves FAULT as it is (commands are SAFE there
    already): only `reset` acknowledges a fault, but for a transport fault that came while
    IDLE, which the next valid sensor frame ends (`sensors`)."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.state = RigState.IDLE
        self.fault: Fault | None = None
        self.reason = ""
        self._bad: collections.deque[float] = collections.deque()
        self._lost: collections.deque[tuple[float, int]] = collections.deque()
        self._lost_sum = 0
        self.firmware_blocking: str = ""  # why the firmware status forbids arming, if it does
        self._timeouts: int | None = None  # the firmware's CommandTimeouts, last seen
        self._foreign_t = -math.inf  # when another sender's command was last seen
        self._foreign_name = ""
        # the fault is a transport fault that came while IDLE: valid frames end it
        self._clears_itself = False

    @property
    def active(self) -> bool:
        """True when commands may be ACTIVE."""
        return self.state is RigState.ARMED

    def _event(self, t_s: float, kind: str, reason: str, **extra) -> dict:
        level = "error" if kind == "fault" else "info"
        return {
            "t": t_s,
            "kind": kind,
            "level": level,
            "text": f"{kind}: {reason}",
            "state": self.state.name,
            "reason": reason,
            **extra,
        }

    def event(self, t_s: float, kind: str, reason: str) -> dict:
        """An event of this state that is no fault (e.g. a change of the adaptation)."""
        return self._event(t_s, kind, reason)

    def notice(self, t_s: float, kind: str, reason: str) -> list[dict]:
        """A warning event that changes no state (a suspect frame)."""
        return [{**self._event(t_s, kind, reason), "level": "warning"}]

    def trip(self, t_s: float, fault: Fault, reason: str) -> list[dict]:
        """Enter FAULT (or stay there, recording the new reason). Returns the events."""
        if fault.value not in TRANSPORT_FAULTS:
            self._clears_itself = False
        elif self.state is not RigState.FAULT:
            self._clears_itself = self.state is RigState.IDLE
        self.fault, self.reason = fault, reason
        self.state = RigState.FAULT
        return [self._event(t_s, "fault", reason, fault=fault.value)]

    def arm(self, t_s: float) -> tuple[bool, str, list[dict]]:
        if self.firmware_blocking:
            return False, f"cannot arm: {self.firmware_blocking}", []
        if t_s - self._foreign_t < FOREIGN_HOLD_S:
            return (
                False,
                f"cannot arm: another sender's {self._foreign_name} on the bus "
                f"{t_s - self._foreign_t:.3f} s ago (a second daemon on this rig?)",
                [],
            )
        if self.state is RigState.FAULT:
            return (
                False,
                f"cannot arm: in FAULT ({self.fault.value}: {self.reason}); acknowledge it "
                "with reset first (mrrig reset --rig NAME)",
                [],
            )
        if self.state is RigState.ARMED:
            return True, "already armed", []
        self.state = RigState.ARMED
        self._bad.clear()
        self._lost.clear()
        self._lost_sum = 0
        return True, "armed", [self._event(t_s, "state", "armed (was IDLE)")]

    def reset(self, t_s: float) -> tuple[str, list[dict]]:
        """The operator's acknowledgement of a fault: FAULT -> IDLE (commands stay SAFE; a
        firmware that still blocks arming still does). Elsewhere nothing to reset."""
        if self.state is not RigState.FAULT:
            return f"nothing to reset: {self.state.name}", []
        fault, reason = self.fault, self.reason
        self.state, self.fault, self.reason = RigState.IDLE, None, ""
        text = f"fault acknowledged by reset: {fault.value}: {reason}"
        return "reset", [self._event(t_s, "state", text)]

    def disarm(self, t_s: float, reason: str = "disarmed") -> list[dict]:
        if self.state is not RigState.ARMED:
            return []  # IDLE already, or FAULT: SAFE, and only reset acknowledges it
        self.state = RigState.IDLE
        return [self._event(t_s, "state", f"{reason} (was ARMED)")]

    def bad_frame(self, t_s: float, reason: str) -> list[dict]:
        """A RigSensors frame failed its E2E check; beyond the budget in the window -> FAULT."""
        self._bad.append(t_s)
        while self._bad and t_s - self._bad[0] > self.limits.budget_window_s:
            self._bad.popleft()
        if len(self._bad) > self.limits.bad_frame_budget and self.state is not RigState.FAULT:
            return self.trip(
                t_s,
                Fault.BAD_FRAMES,
                f"{len(self._bad)} bad sensor frames in {self.limits.budget_window_s:g} s "
                f"(budget {self.limits.bad_frame_budget}); last: {reason}",
            )
        return []

    def lost_frames(self, t_s: float, n: int) -> list[dict]:
        if n <= 0:
            return []
        self._lost.append((t_s, n))
        self._lost_sum += n
        while self._lost and t_s - self._lost[0][0] > self.limits.budget_window_s:
            self._lost_sum -= self._lost.popleft()[1]
        if self._lost_sum > self.limits.lost_frame_budget and self.state is not RigState.FAULT:
            return self.trip(
                t_s,
                Fault.LOST_FRAMES,
                f"{self._lost_sum} sensor frames lost in {self.limits.budget_window_s:g} s "
                f"(budget {self.limits.lost_frame_budget})",
            )
        return []

    def sensors(self, t_s: float, v: dict[str, float]) -> list[dict]:
        """Flags and ranges of a valid RigSensors frame; it ends a transport fault that came
        while IDLE (an event saying so), and is then checked as any other."""
        if self.state is RigState.FAULT and not self._clears_itself:
            return []
        events = self._frames_resumed(t_s) if self.state is RigState.FAULT else []
        return events + self._check_sensors(t_s, v)

    def _frames_resumed(self, t_s: float) -> list[dict]:
        fault, reason = self.fault, self.reason
        self.state, self.fault, self.reason = RigState.IDLE, None, ""
        self._clears_itself = False
        text = (
            f"transport fault cleared: valid sensor frames again after {fault.value}: {reason}"
            " (not armed when it came: no reset needed)"
        )
        return [self._event(t_s, "state", text, cleared=fault.value)]

    def _check_sensors(self, t_s: float, v: dict[str, float]) -> list[dict]:
        if v["EStop"]:
            return self.trip(t_s, Fault.ESTOP, "e-stop reported by the rig")
        if v["LimitTripped"]:
            return self.trip(t_s, Fault.LIMIT_TRIPPED, "stroke limit tripped on the rig")
        if v["SensorFault"]:
            return self.trip(t_s, Fault.SENSOR_FAULT, "sensor fault reported by the rig")
        lo, hi = self.limits.x_range_m
        if not lo <= v["Displacement"] <= hi:
            return self.trip(
                t_s,
                Fault.DISPLACEMENT_RANGE,
                f"displacement {v['Displacement'] * 1e3:.2f} mm outside "
                f"[{lo * 1e3:g}, {hi * 1e3:g}] mm",
            )
        lo, hi = self.limits.f_range_n
        if not lo <= v["Force"] <= hi:
            return self.trip(
                t_s, Fault.FORCE_RANGE, f"force {v['Force']:.1f} N outside [{lo:g}, {hi:g}] N"
            )
        return []

    def firmware_status(
        self, t_s: float, state_name: str, fault_code: int, fault_label: str, timeouts: int
    ) -> list[dict]:
        """RigStatus. A new watchdog trip (CommandTimeouts moved) faults the daemon; any other
        firmware FAULT (over-limit setpoint, stroke limit, sensor fault, e-stop, bad command
        frames) faults it and blocks arming while it lasts. A FAULT that is only the watchdog's
        (FaultCode 1) does not block arming: the firmware leaves it after 5 ACTIVE commands.
        """
        events: list[dict] = []
        new_timeouts = self._timeouts is not None and timeouts != self._timeouts
        self._timeouts = timeouts
        if state_name == "FAULT" and fault_code != 1:
            self.firmware_blocking = f"firmware in FAULT ({fault_label})"
            if self.state is not RigState.FAULT:
                events += self.trip(
                    t_s, Fault.FIRMWARE_FAULT, f"firmware reports FAULT: {fault_label}"
                )
        else:
            self.firmware_blocking = ""
            if new_timeouts and self.state is RigState.ARMED:
                events += self.trip(
                    t_s,
                    Fault.FIRMWARE_WATCHDOG,
                    "firmware watchdog tripped (no valid command for 20 ms)",
                )
        return events

    def foreign_command(self, t_s: float, name: str) -> list[dict]:
        """A frame of a message that the DBC has only the daemon send, and a bus does not hand
        a sender its own frames: another controller commands this rig. FAULT (SAFE 0 A from
        here), and arming is refused until it has been quiet for FOREIGN_HOLD_S. One event per
        episode: a fault already there (the firmware's watchdog, tripped by the doubled
        commands) gets this reason too, the sender's next frames add none."""
        new = t_s - self._foreign_t >= FOREIGN_HOLD_S
        self._foreign_t, self._foreign_name = t_s, name
        if self.state is RigState.FAULT and not new:
            return []
        return self.trip(
            t_s,
            Fault.FOREIGN_COMMAND,
            f"another sender's {name} on the bus (a second daemon on this rig?)",
        )

    def finite(self, t_s: float, what: str, *values: float) -> list[dict]:
        if all(math.isfinite(v) for v in values) or self.state is RigState.FAULT:
            return []
        return self.trip(t_s, Fault.NON_FINITE, f"non-finite number in {what}")
