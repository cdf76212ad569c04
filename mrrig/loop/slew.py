"""The loop's current slew limit (`loop.max_current_slew_a_per_s`): each command of a model
the daemon sends while armed is at most one period's slew from the last one it sent,
whatever its controller asks. A model that jumps the coil between the rails from frame to
frame (issue 40: an untrained GRU stepped 0 to 2 A) moves it at most this fast; a sane
model's commands (hundredths of an ampere a frame on the demo's sine) pass unchanged. The
first command after arming is the controller's own: ramping it up from 0 A delayed the
demo's tracking at arming (Et 0.0121 -> 0.0142). The controller is told the command sent
(`Controller.command_sent`), so that a model which carries the command held (the coil's lag,
a twin's or a GRU's state) carries the one the coil got. Pure numerics."""

from __future__ import annotations

from mrrig.loop.controllers import CONTROLLERS, Controller


class SlewLimit:
    """Commands within `max_a_per_s * period_s` of the last active one sent (`sent`)."""

    def __init__(self, max_a_per_s: float, period_s: float) -> None:
        self.max_step_a = max_a_per_s * period_s
        self.last_a: float | None = None  # None: no active command since the last SAFE one

    def limit(self, current_a: float) -> float:
        """`current_a` moved no further than one step from the last command sent."""
        if self.last_a is None:
            return current_a
        lo, hi = self.last_a - self.max_step_a, self.last_a + self.max_step_a
        return min(max(current_a, lo), hi)

    def sent(self, current_a: float | None) -> None:
        """The active command that went out; None for a SAFE one (the next starts afresh)."""
        self.last_a = current_a


def loop_command(
    slew: SlewLimit, controller: Controller, i_a: float, i_max_a: float
) -> tuple[float, bool]:
    """A controller's command `i_a` as the loop sends it, and whether the slew limit moved
    it: within [0, `i_max_a`], then a model's within the slew limit, the controller told the
    command sent where the limit moved it (`Controller.command_sent`); an operator's own
    current (constant) is not limited. The daemon's frame and the all-numerical HIL reference
    (mrrig/hil/reference.py) both call it."""
    i_a = min(max(i_a, 0.0), i_max_a)
    if not CONTROLLERS[controller.name].needs_model:
        return i_a, False
    sent = slew.limit(i_a)
    if sent != i_a:
        controller.command_sent(sent)
    return sent, sent != i_a
