"""What clients ask of the loop: control requests that the control thread prepared
(`mrrig.rigio.control.ControlWorker`), swapped in between frames, at most one a pass; the arm
lease that a remote arm holds while its client renews it; and force references for an
external reference. The loop thread alone runs this."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from mrrig.loop import reference as ref
from mrrig.loop.coverage import controller_envelope
from mrrig.loop.exit_codes import Exit
from mrrig.loop.lease import PATH_QUIET_S, ArmLease
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.rigio.control import Change, RequestError, check_actuator_step, settings_in_force

if TYPE_CHECKING:
    from mrrig.loop.daemon import Daemon

log = logging.getLogger(__name__)


class ControlRequests:
    """The daemon's side of its control requests: `apply_next` once a pass of the loop, and
    the lease of a remote arm (`lease`, checked each pass by `lease_lapsed`). The changes are
    to the daemon's state (its controller, reference, actuator, config, supervisor)."""

    def __init__(self, owner: Daemon) -> None:
        self._d = owner
        self.lease = ArmLease(owner.cfg.control.lease_timeout_s)  # a remote arm's, while held

    def apply_next(self) -> None:
        """At most one prepared change per pass of the loop, between frames."""
        control = self._d.control
        taken = control.take()
        if taken is None:
            return
        change, item = taken
        try:
            reply = {"ok": True, **self.apply(change)}
        except RequestError as exc:
            reply = {"ok": False, "error": str(exc)}
        except Exception as exc:  # noqa: BLE001 - a failed change must not stop the loop
            log.exception("applying %s failed", change.cmd)
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        control.done(item, reply)

    def apply(self, c: Change) -> dict[str, Any]:
        """Swap in a prepared change (loop thread). The state is checked again here: an arm
        that came after the change was prepared wins."""
        d = self._d
        sup = d.supervisor
        if c.cmd == "arm":
            if d.controller.follows_reference and math.isnan(d.reference.current_at(d.now())):
                raise RequestError(
                    f"arm: controller {d.controller.name} commands the force reference's own"
                    f" current: a bouc_wen or paper_case reference has one, {d.reference.kind}"
                    " has none (set_profile first)"
                )
            ok, msg, events = sup.arm(d.now())
            if not ok:
                raise RequestError(msg)
            if c.hil_run is not None:  # the run this arm starts, built off the loop
                d.hil.ready(c.hil_run)
            if events:
                self.lease.end()  # armed anew: a lease of its own
                d.actuator_at_arm = d.actuator
                d.controller.reset(1)
                d.detectors.reset()
                d.restart_reference(d.now(), d.last_x)
                d.sensors.armed(time.perf_counter())  # frames must come while armed
            d._emit(events)
            if not c.remote:  # in process: the daemon ends with its client
                return {"state": sup.state.name, "message": msg}
            self.lease.grant(time.perf_counter())
            return {"state": sup.state.name, "message": msg, **self.lease.reply()}
        if c.cmd == "renew":
            return self._renew(c.lease)
        if c.cmd == "reset":
            msg, events = sup.reset(d.now())
            d._emit(events)
            return {"state": sup.state.name, "message": msg}
        if c.cmd == "disarm":
            d._emit(sup.disarm(d.now(), "disarmed by request"))
            self.lease.end()
            return {"state": sup.state.name}
        if c.cmd == "status":
            return {"status": d.status()}
        if c.cmd in ("reset_adaptation", "freeze_adaptation"):  # allowed while armed
            return self._adaptation_change(c)
        if c.cmd == "sidecar":
            if c.sidecar is None:
                d.exit_code = Exit.TELEMETRY_LOST
                d.request_stop("telemetry lost: its restart failed")
            else:
                d.sidecar.back(*c.sidecar)
            return {}
        if c.cmd in ("set_controller", "set_profile", "set_hil") and sup.state is RigState.ARMED:
            raise RequestError(f"{c.cmd} only when not armed (disarm first)")
        if c.cmd == "set_controller":
            d.envelope = controller_envelope(c.controller)
            d.controller = c.controller
            d.controller.reset(1)
            d.restart_reference(d.now(), d.last_x)  # its desired forces ahead, if any
            d.cfg = replace(d.cfg, controller=c.controller_section)
            d.in_force = c.in_force or d.in_force
            d._send_status(force=True)
            settings = settings_in_force(c.controller_section, c.controller)
            return {"controller": d.controller.name, "settings": settings}
        if c.cmd == "set_hil":
            if d.hil.streaming:  # a disarm ends the run at the next frame
                raise RequestError("set_hil: the last run is still ending (ask again)")
            d.hil.set_scenario(c.hil_scenario)
            d.hil.ready(c.hil_run)
            d._send_status(force=True)
            return {"hil": d.hil.status()}
        if c.cmd == "set_profile":
            d.restart_reference(d.now(), d.last_x, c.reference)
            d.cfg = replace(d.cfg, reference=c.reference_section)
            d._send_status(force=True)
            return {"reference": d.reference.kind}
        a = c.actuator
        check_actuator_step(sup.state, d.actuator, a, d.cfg, d.actuator_at_arm)
        d.actuator = a
        d._send_actuator()
        return {
            "waveform": a.waveform,
            "amplitude_m": a.amplitude_m,
            "frequency_hz": a.frequency_hz,
        }

    def _renew(self, lease_id: str) -> dict[str, Any]:
        """Keep an arm's lease; refused when it is not the one held or the rig left ARMED."""
        state = self._d.supervisor.state
        if state is not RigState.ARMED:
            self.lease.end()
            raise RequestError(f"lease {lease_id}: ended, the rig is {state.name}")
        if not self.lease.renew(lease_id, time.perf_counter()):
            raise RequestError(f"lease {lease_id}: not held (lapsed, or another arm's)")
        return self.lease.reply()

    def lease_lapsed(self, t_rx: float) -> None:
        """No renewal of the arm's lease within its timeout (its client killed or cut off):
        FAULT (this frame on answered SAFE) and the actuator stopped, as a detector's stop. The
        lease's clock stops while the telemetry process, which carries the renewals, is
        silent (a stall of it is no client's end; `telemetry_lost` guards that)."""
        d = self._d
        if d.sidecar.link is not None and t_rx - d.sidecar.heard() > PATH_QUIET_S:
            self.lease.deadline = t_rx + self.lease.timeout_s
            return
        timeout_s, unrenewed_s = self.lease.timeout_s, t_rx - self.lease.deadline
        self.lease.end()
        if not d.supervisor.active:
            return
        d.counters["leases_lapsed"] += 1
        reason = (
            f"lease lapsed: no renewal for {unrenewed_s + timeout_s:.2f} s"
            f" (limit control.lease_timeout_s = {timeout_s:g} s): the client that armed is gone"
        )
        d.actuator = replace(d.actuator, waveform="stop")
        d._last_actuator_sent = -math.inf
        d._emit(d.supervisor.trip(t_rx - d.t0, Fault.LEASE_LAPSED, reason))

    def _adaptation_change(self, c: Change) -> dict[str, Any]:
        d = self._d
        adapt = getattr(d.controller, "adapt", None)
        if adapt is None:
            raise RequestError(
                f"controller {d.controller.name} has no on-line adaptation ([adaptation] enabled)"
            )
        if c.cmd == "reset_adaptation":  # back to the model as trained (gain 1, offset 0)
            adapt.reset(adapt.theta.shape[0])
            what = "reset"
        else:  # frozen: the adapted state stays in use, without updates
            adapt.frozen = c.frozen
            what = "frozen" if c.frozen else "resumed"
        d._emit([d.supervisor.event(d.now(), "adaptation", f"adaptation {what} by request")])
        return {"adaptation": adapt.state()}

    def on_force_ref(self, force_n: float, t_rx_mono: float) -> None:
        """A force reference from a client (force_ref, through the telemetry process): to an
        external reference (`reference.External`), clamped into loop.f_range_n."""
        d = self._d
        if isinstance(d.reference, ref.External):
            d.counters["force_refs_received"] += 1
            lo, hi = d.cfg.loop.f_range_n
            if not lo <= force_n <= hi:
                d.counters["force_refs_clamped"] += 1
                if d.counters["force_refs_clamped"] == 1:
                    d._emit(
                        [
                            d.supervisor.event(
                                d.now(),
                                "force_ref_clamped",
                                f"force_ref {force_n:g} N outside loop.f_range_n [{lo:g}, "
                                f"{hi:g}] N: clamped (counted in force_refs_clamped)",
                            )
                        ]
                    )
                force_n = min(max(force_n, lo), hi)
            # the sidecar stamps with time.monotonic(); both clocks tick at the same rate
            delay = time.monotonic() - t_rx_mono
            d.reference.receive(force_n, d.now() - delay)
