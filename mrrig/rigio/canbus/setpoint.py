"""The daemon's ActuatorSetpoint stream (contract 1.1): one setpoint per valid sensor frame.

While the actuator's waveform is STREAM the daemon answers every valid RigSensors frame with
one ActuatorSetpoint echoing that frame's counter, within the envelope its STREAM command
announced (spec/can-protocol.md, "Daemon behaviour"). `SetpointStream.message` builds that
frame through the rig profile's packer (the DBC's layout, E2E counter and CRC filled there);
it refuses, in one line, what the contract forbids the daemon to send: a position beyond the
envelope, a number that is not finite, a second setpoint for the same sensor frame. The
caller (the HIL loop) faults on a refusal and sends HOLD or STOP; it never sends a clamped
setpoint in its place.
"""

from __future__ import annotations

import math

from mrrig.errors import MrrigError
from mrrig.pycan import can
from mrrig.rigio.canbus.codec import EncodeError, Packer
from mrrig.rigio.canbus.profile import RigProfile


class SetpointError(MrrigError, ValueError):
    """A setpoint the contract does not let the daemon send; nothing was sent."""


class SetpointStream:
    """Encodes one ActuatorSetpoint per sensor frame for a STREAM of `envelope_m`."""

    def __init__(self, profile: RigProfile, packer: Packer, envelope_m: float) -> None:
        """`packer`: the daemon's (`RigProfile.packer()`), so that the setpoint's rolling
        counter is the one every frame of it carried; `envelope_m`: the STREAM command's
        amplitude."""
        if (why := profile.stream_refusal()) is not None:
            raise SetpointError(why)
        assert profile.setpoint_message is not None  # mapped with actuator_setpoint
        if not (math.isfinite(envelope_m) and envelope_m > 0.0):
            raise SetpointError(f"envelope {envelope_m!r} m: must be a positive number")
        self.message_name = profile.setpoint_message
        self.envelope_m = envelope_m
        self._packer = packer
        self._last_echo: int | None = None

    def restart(self) -> None:
        """A new run: its first sensor frame may carry the counter the last run's last
        setpoint echoed (the counter comes round), and is a frame of its own."""
        self._last_echo = None

    def message(self, echo: int, position_m: float, velocity_m_s: float = 0.0) -> can.Message:
        """The ActuatorSetpoint answering the sensor frame whose counter is `echo`: the piston
        to `position_m`, moving at `velocity_m_s` (its feedforward; 0 when unknown)."""
        name = self.message_name
        if echo == self._last_echo:
            raise SetpointError(f"{name}: sensor frame {echo} has its setpoint already")
        if not (math.isfinite(position_m) and math.isfinite(velocity_m_s)):
            raise SetpointError(
                f"{name}: position {position_m!r} m, velocity {velocity_m_s!r} m/s: not finite"
            )
        if abs(position_m) > self.envelope_m:
            raise SetpointError(
                f"{name}: position {position_m * 1e3:.3f} mm beyond the STREAM envelope"
                f" +-{self.envelope_m * 1e3:g} mm"
            )
        values = {
            "SensorCounterEcho": echo,
            "PositionSetpoint": position_m,
            "VelocityFeedforward": velocity_m_s,
        }
        try:
            msg = self._packer.message(name, values)
        except EncodeError as exc:
            raise SetpointError(str(exc)) from None
        self._last_echo = echo
        return msg
