"""The daemon's telemetry process (the sidecar: Zenoh and the recording), started, heard and
supervised from the loop: its pipe (`link`), its heartbeat, one restart when it is lost, and
the recording files it wrote. The loop polls it once a pass (`poll`, `watch`); the slow parts
(killing, reaping, starting a new one) run as jobs of the control thread."""

from __future__ import annotations

import logging
import math
import resource
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mrrig.errors import MrrigError
from mrrig.loop.exit_codes import Exit
from mrrig.loop.realtime import keep_off_cpu
from mrrig.loop.safety import Fault
from mrrig.rigio.control import Change
from mrrig.rigio.ipc import LoopEnd, Msg, ReplyWriter, make_channel

if TYPE_CHECKING:
    from mrrig.loop.daemon import Daemon

log = logging.getLogger(__name__)

SIDECAR_START_S = 20.0  # a new telemetry process's first heartbeat may take this long
MAX_SIDECAR_RESTARTS = 1
MAX_REPLAYED_EVENTS = 20  # events a restarted telemetry process is told again
# importing rerun and zenoh and opening both, on a loaded 2-core machine; a live_url that
# nothing listens on alone blocks the recorder about 6 s
SIDECAR_START_TIMEOUT_S = 30.0


class SidecarStartError(MrrigError, OSError):
    """The telemetry process (Zenoh, recording) could not start: the daemon does not run."""


class SidecarWatch:
    """The telemetry process of one daemon: `proc`, its pipe `link` (None while there is none,
    or while a lost one restarts) and the control thread's end of it; the recording files.

    The daemon is its owner: a lost process faults it (`_emit`, `supervisor`), ends its run
    when the restart is spent (`exit_code`, `request_stop`), and what the process sends in
    (requests, force_ref, notices) goes to the daemon's control thread and reference."""

    def __init__(self, owner: Daemon, record_path: Path | None) -> None:
        self._d = owner
        self.proc = None
        self.link: LoopEnd | None = None  # to the sidecar, when telemetry or recording is on
        self._replies: ReplyWriter | None = None  # the control thread's end of the same pipe
        self.deadline = math.inf  # of its next heartbeat
        self.restarts = 0
        self._restarting = False
        self.record_path = record_path
        self.record_paths = [record_path] if record_path is not None else []
        self.recording_failed = ""  # why the recording stopped, if it did

    @property
    def cfg(self):
        return self._d.cfg

    def wanted(self) -> bool:
        """Telemetry, a recording or a bus log: a run with a telemetry process."""
        cfg = self.cfg
        return cfg.telemetry.enabled or self.record_path is not None or self._d.tap is not None

    def start(self) -> None:
        self.proc, self.link, self._replies = self._spawn()
        self.deadline = time.perf_counter() + SIDECAR_START_S

    def heard(self) -> float:
        """When its last heartbeat came (perf_counter)."""
        return self.deadline - self.cfg.telemetry.heartbeat_timeout_s

    def poll(self, now: float) -> None:
        d = self._d
        for mtype, payload in self.link.poll():
            if mtype == Msg.REQUEST:
                request_id, raw = payload
                d.control.submit(raw, self._replies.reply_to(request_id))
            elif mtype == Msg.FORCE_REF:
                d.requests.on_force_ref(*payload)
            elif mtype == Msg.HEARTBEAT:
                self.deadline = now + self.cfg.telemetry.heartbeat_timeout_s
            elif mtype == Msg.NOTICE and payload.get("kind") == "recording_failed":
                self._recording_failed(str(payload.get("reason", "")))
            elif mtype == Msg.NOTICE and payload.get("kind") == "duplicate_rig":
                reason = str(payload.get("reason", ""))
                d._emit(d.supervisor.trip(d.now(), Fault.DUPLICATE_RIG, reason))

    def _recording_failed(self, reason: str) -> None:
        d = self._d
        self.recording_failed = reason or "unknown"
        d._emit(d.supervisor.trip(d.now(), Fault.RECORDING_FAILED, f"recording failed: {reason}"))

    def watch(self, now: float) -> None:
        """A dead sidecar (its pipe closed) or one without a heartbeat for
        `telemetry.heartbeat_timeout_s`: fault `telemetry_lost`, then one restart."""
        if self._restarting:
            return
        d = self._d
        if self.link.closed:
            code = self.proc.poll() if self.proc is not None else None
            why = f"the telemetry process exited (code {code})"
        elif now > self.deadline:
            why = (
                "no heartbeat from the telemetry process for "
                f"{self.cfg.telemetry.heartbeat_timeout_s:g} s (stopped or stuck)"
            )
        else:
            return
        d._emit(d.supervisor.trip(d.now(), Fault.TELEMETRY_LOST, why))
        old = (self.proc, self.link, self._replies)
        self.link = None
        if self.restarts >= MAX_SIDECAR_RESTARTS:
            log.error("telemetry lost again after its restart: stopping the daemon")
            d.exit_code = Exit.TELEMETRY_LOST
            d.request_stop(f"telemetry lost: {why}")
            d.control.submit_job(lambda: self._end(*old))
            return
        self.restarts += 1
        self._restarting = True
        log.warning("%s: restarting it", why)
        d.control.submit_job(lambda: self._restart(*old))

    def _end(self, proc, link, replies) -> None:
        """Kill and reap a lost sidecar and close its pipes (control thread)."""
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            try:
                proc.wait(timeout=5)
            except Exception:  # noqa: BLE001
                log.warning("telemetry process %d not reaped", proc.pid)
        replies.close()
        link.close()

    def _restart(self, proc, link, replies) -> Change:
        """Control thread: the lost process ended, a new one started (its own recording);
        a Change for the loop either way (`sidecar` None: it could not start)."""
        self._end(proc, link, replies)
        if self.record_path is not None:
            n = self.restarts
            self.record_path = self.record_path.with_name(
                f"{self.record_path.stem.split('.restart')[0]}.restart{n}.rrd"
            )
            self.record_paths.append(self.record_path)
        if self._d.tap is not None:
            log.warning("the bus log ends here: a restarted telemetry process does not continue it")
        try:
            return Change("sidecar", sidecar=self._spawn(can_log=False))
        except Exception as exc:  # noqa: BLE001 - the loop is told and stops
            log.error("restarting the telemetry process failed: %s", exc)
            return Change("sidecar")

    def back(self, proc, link, replies) -> None:
        """The restarted process, in place (loop thread, from the control thread's Change)."""
        self.proc, self.link, self._replies = proc, link, replies
        self.deadline = time.perf_counter() + SIDECAR_START_S
        self._restarting = False
        log.info("telemetry process restarted (pid %d)", proc.pid)
        for e in self._d.events[-MAX_REPLAYED_EVENTS:]:
            link.send_event(e)
        self._d._send_status(force=True)

    def _spawn(self, can_log: bool = True) -> tuple[Any, LoopEnd, ReplyWriter]:
        """Start the telemetry process and wait for it to be ready; `can_log` False: without
        the bus log (a restarted process would start the run's bus log over)."""
        from mrrig.rigio.rig_topics import is_duplicate_text
        from mrrig.rigio.sidecar_process import start_sidecar

        cfg = self.cfg
        fds = make_channel()
        proc = start_sidecar(
            rig=cfg.rig.name,
            zenoh_config=cfg.telemetry.zenoh_config if cfg.telemetry.enabled else None,
            record=self.record_path,
            fds=fds,
            telemetry_hz=cfg.telemetry.rate_hz,
            live_url=cfg.recording.live_url,
            insecure=cfg.telemetry.insecure,
            can_log=self._can_log() if can_log else None,
            identity=self._d.identity,
        )
        keep_off_cpu(proc.pid, cfg.loop.cpu, "telemetry process")
        link = LoopEnd(*fds.loop_fds())
        # a rig must not run unobserved: no telemetry or recording, no loop
        error = link.wait_ready(SIDECAR_START_TIMEOUT_S)
        if error is not None:
            link.close()
            off = ""
            # not for a name already served: without Zenoh it would open that rig's bus
            if cfg.telemetry.enabled and not is_duplicate_text(error):
                off = " (to run without Zenoh: telemetry.enabled = false, or --no-telemetry)"
            raise SidecarStartError(f"the telemetry process could not start: {error}{off}")
        return proc, link, link.reply_writer()

    def _can_log(self) -> tuple[Path, str] | None:
        """The bus log and the channel name it shows (the interface's, a rig name otherwise)."""
        path = self.cfg.recording.can_log
        if path is None:
            return None
        bus = self.cfg.bus
        return path, bus.channel if bus.interface == "socketcan" else self.cfg.rig.name

    def close(self, summary: dict[str, Any]) -> None:
        """The run's end: the summary to the process, its pipes closed, the process waited
        for (its CPU time into the summary)."""
        if self.link is not None:
            self.link.send_summary(summary)
            self.link.send_stop()
            self.link.close()
            self._replies.close()
        if self.proc is not None:
            try:
                self.proc.wait(timeout=15)
            except Exception:  # noqa: BLE001
                log.warning("telemetry process did not stop in 15 s; terminating it")
                self.proc.terminate()
            summary["cpu_sidecar_s"] = (
                resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
                + resource.getrusage(resource.RUSAGE_CHILDREN).ru_stime
            )
