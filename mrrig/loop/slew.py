"""The loop's current slew limit (`loop.max_current_slew_a_per_s`): each command the daemon
sends is at most one period's slew from the last one it sent (0 A while disarmed, so an armed
rig's command ramps up from 0 A), whatever its controller asks. A model that jumps the coil
between the rails from frame to frame (issue 40: an untrained GRU stepped 0 to 2 A) moves it
at most this fast; a sane model's commands (a few hundredths of an ampere a frame) pass
unchanged. The controller is told the command sent (`Controller.command_sent`), so that a
model which carries the command held (the coil's lag, a twin's or a GRU's state) carries the
one the coil got. Pure numerics."""

from __future__ import annotations

import math


class SlewLimit:
    """Commands within `max_a_per_s * period_s` of the last one sent (`sent`)."""

    def __init__(self, max_a_per_s: float, period_s: float) -> None:
        self.max_step_a = max_a_per_s * period_s
        self.last_a = 0.0

    def limit(self, current_a: float) -> float:
        """`current_a` moved no further than one step from the last command sent."""
        if math.isinf(self.max_step_a):
            return current_a
        lo, hi = self.last_a - self.max_step_a, self.last_a + self.max_step_a
        return min(max(current_a, lo), hi)

    def sent(self, current_a: float) -> None:
        """The command that went out (0 A for a SAFE one)."""
        self.last_a = current_a
