"""What the daemon watches in the sensor frames' arrival, apart from their content: the first
valid sensor frame due (a `no_sensor_frames` fault names the CAN IDs the bus carried instead),
the gap since the previous one by the bus's receive timestamps, and a counter that moved on
faster than time passed (a replayed or forged frame, or a second sender)."""

from __future__ import annotations

import math

from mrrig.loop.safety import Fault, Supervisor
from mrrig.rigio.canbus.profile import RigProfile

MAX_IDS_NAMED = 8  # CAN IDs a no_sensor_frames fault names (the most frequent)
MAX_IDS_COUNTED = 64  # distinct IDs counted before the first valid sensor frame


class SensorWatch:
    """The arrival of sensor frames; each check returns the supervisor's events (the daemon
    emits them). `counters`: the daemon's, for `sensor_frames_early`."""

    def __init__(
        self,
        profile: RigProfile,
        supervisor: Supervisor,
        counters: dict[str, int],
        period_s: float,
        budget_window_s: float,
    ) -> None:
        self.profile = profile
        self.supervisor = supervisor
        self.counters = counters
        self.period_s = period_s
        self.budget_window_s = budget_window_s
        self._last_bus_ts = None  # the bus's receive timestamp of the last sensor frame
        self._early_event_t = -math.inf
        # until the first valid sensor frame: since when one is due (the first frame of any
        # kind, an arm), and the frames the bus carried instead, per CAN ID
        self._listen_since: float | None = None
        self._bus_heard = False
        self._ids_seen: dict[str, int] = {}

    def armed(self, now_abs: float) -> None:
        """Armed before the first valid sensor frame: one is due from now."""
        self._listen_since = now_abs

    def note_id(self, msg, t_rx: float) -> None:
        """Count a frame by its CAN ID until the first valid sensor frame: a no_sensor_frames
        fault names what the bus carried (a rig on another DBC, a wrong channel). The first
        frame of the run opens the window a sensor frame is due in: a silent bus is a rig not
        yet streaming (a daemon started first), a bus of other frames one that is not ours."""
        if not self._bus_heard:
            self._bus_heard = True
            self._listen_since = t_rx
        if msg.is_error_frame:
            key = "error frames"
        else:
            key = (
                f"0x{msg.arbitration_id:08X}"
                if msg.is_extended_id
                else f"0x{msg.arbitration_id:03X}"
            )
            key += " (remote)" if msg.is_remote_frame else ""
        if key in self._ids_seen or len(self._ids_seen) < MAX_IDS_COUNTED:
            self._ids_seen[key] = self._ids_seen.get(key, 0) + 1
        else:
            self._ids_seen["other"] = self._ids_seen.get("other", 0) + 1

    def first_frame(self, now_abs: float, limit_s: float, t: float) -> list[dict]:
        """No valid sensor frame yet: one within the sensor timeout of the bus's first frame
        or of an arm, or fault no_sensor_frames (once for each), naming the IDs seen."""
        if self._listen_since is None or now_abs - self._listen_since <= limit_s:
            return []
        self._listen_since = None
        since = "arming" if self.supervisor.active else "the bus's first frame"
        return self.no_sensor_frames(t, f"within {limit_s * 1e3:g} ms of {since}")

    def no_sensor_frames(self, t: float, when: str) -> list[dict]:
        seen = sorted(self._ids_seen.items(), key=lambda kv: -kv[1])
        n = sum(self._ids_seen.values())
        if n:
            ids = ", ".join(f"{k} x{c}" for k, c in seen[:MAX_IDS_NAMED])
            more = f" and {len(seen) - MAX_IDS_NAMED} more" if len(seen) > MAX_IDS_NAMED else ""
            heard = f"the bus carried {n} other frames: {ids}{more}"
        else:
            heard = "the bus carried no frames at all"
        sensors = self.profile.sensor_layout
        return self.supervisor.trip(
            t,
            Fault.NO_SENSOR_FRAMES,
            f"no valid {sensors.name} frame (0x{sensors.frame_id:03X}) {when}; {heard} "
            "(another DBC, channel or rig?)",
        )

    def gap_s(self, bus_ts: float) -> float:
        """Time since the previous sensor frame by the bus's receive timestamps (0 for the
        first one)."""
        last = self._last_bus_ts
        return 0.0 if last is None else bus_ts - last

    def counter_timing(self, bus_ts: float, lost: int, t: float) -> list[dict]:
        """A sensor frame whose counter moved on more periods than time has passed since the
        last one (a counter jump inside one period): a replayed or forged frame with a valid
        CRC, or a second sender. E2E profile 2's 4-bit counter cannot stop such frames (README,
        security); this only makes them seen: counted, and an event per budget window."""
        last, self._last_bus_ts = self._last_bus_ts, bus_ts
        if last is None or lost == 0 or bus_ts - last >= lost * self.period_s:
            return []
        self.counters["sensor_frames_early"] += 1
        if t - self._early_event_t < self.budget_window_s:
            return []
        self._early_event_t = t
        return self.supervisor.notice(
            t,
            "suspect_frame",
            f"sensor counter advanced {lost + 1} in {(bus_ts - last) * 1e3:.2f} ms: "
            "a replayed or forged frame, or a second sender?",
        )
