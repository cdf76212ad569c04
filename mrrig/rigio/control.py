"""Control requests to the daemon (`mrrig/<rig>/control`): checked and prepared off the loop.

A request is a JSON object with a `cmd`; the reply is `{"ok": true, ...}` or
`{"ok": false, "error": "..."}`. An invalid request (too large or too deep, not JSON, unknown
command, a value of the wrong type, out of range or not finite, a file outside the configured
directories or over its limits, the wrong state) changes nothing.

The loop owns the daemon (spec/system.md): nothing here runs in the loop thread. The sidecar
checks size, depth and JSON (`parse_request`); the daemon's `ControlWorker` thread checks the
values against the config and the state, reads files under limits, builds models and profiles
(`prepare`), and puts the ready `Change` into one bounded mailbox. The loop takes at most one
change between frames (`ControlWorker.take`), applies it (`Daemon.apply`) and hands the reply
back to the worker, which writes it.

What needs DISARMED (not ARMED: IDLE or FAULT): `set_controller`, `set_model`, `set_profile`
(a new force target or controller under an armed damper would step its current), `set_hil`
(the law, compensation and duration of a `[hil]` daemon's next runs), and an
`actuator` change of waveform or frequency, or to an amplitude more than
`control.armed_amplitude_step_m` from the amplitude at arming, while ARMED; `actuator` STOP
is always taken (the firmware ramps to rest). The loop checks the state again when it
applies a change: an `arm` that came first wins.

An `arm` over the control plane (from the telemetry process: a Zenoh client) holds a lease:
its reply names it (`lease`, `lease_timeout_s`), and the client renews it (`renew` with that
`lease`) within `control.lease_timeout_s`, or the loop disarms and stops the actuator
(`mrrig.loop.lease`). An in-process arm (characterize, validate) needs none: the daemon ends
with its client.
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import stat
import threading
import time
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from mrrig.config import (
    ActuatorSection,
    ControllerSection,
    DaemonConfig,
    ReferenceSection,
    reference_from_table,
)
from mrrig.errors import MrrigError
from mrrig.loop.controllers import CONTROLLER_NAMES, CONTROLLERS
from mrrig.loop.samples import RigState
from mrrig.rigio.run_identity import controller_in_force
from mrrig.typed_config import ConfigError, parse

log = logging.getLogger(__name__)

# a request is a flat object of a few fields: 2 kB and 4 levels leave room and stop abuse
MAX_REQUEST_BYTES = 2048
MAX_REQUEST_DEPTH = 4
# a model file is an object of lists of lists (W1): depth 3; 32 stops a stack-exhausting file
MAX_FILE_DEPTH = 32
MAILBOX_SIZE = 4  # ready changes waiting for the loop
MAX_REQUEST_INT = int(1.7e308)  # larger integers have no float (OverflowError)
# a model file read by a request (set_model, set_controller) has at most this many numbers
# (commas + 1): the paper's 4-30-1 network has 181, a history MLP or a small recurrent one a
# few thousand; 20,000 parse in a few ms, and far fewer already cost more than a period
MAX_MODEL_NUMBERS = 20_000
JOB_PUT_TIMEOUT_S = 5.0
# a `mark`'s text (one line) and the JSON of its data: a plan step's name and settings fit
MAX_MARK_CHARS = 200
MAX_MARK_DATA_CHARS = 1200
# a controller's settings in a request, besides its name and model
CONTROLLER_SETTINGS = (
    "method", "ahead", "feedback", "feedback_tau_s", "continuity", "current_a", "gain", "b",
    "on_current_a",
)  # fmt: skip


class RequestError(MrrigError, ValueError):
    """A control request that cannot be carried out; nothing was changed."""


# ---------------------------------------------------------------------------- parsing
def json_depth_exceeds(raw: bytes | str, limit: int) -> bool:
    """True when JSON text nests arrays/objects deeper than `limit` (strings skipped).

    Checked before `json.loads`, whose recursion a deeply nested text exhausts.
    """
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else raw
    depth = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def _bad_value(value: Any, path: str) -> str | None:
    """What is wrong with the first value of a decoded request that no field can take, named
    by its dotted key: NaN/Infinity, an integer beyond a float's range, a string with a NUL
    character or a lone surrogate (each failed later with a message that named no field)."""
    if isinstance(value, float) and not math.isfinite(value):
        return f"{path}: not a finite number (NaN and Infinity are refused)"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > MAX_REQUEST_INT:
        return f"{path}: an integer of {len(str(abs(value)))} digits is beyond a float's range"
    if isinstance(value, str):
        if "\0" in value:
            return f"{path}: contains a NUL character (\\u0000)"
        try:
            value.encode("utf-8")
        except UnicodeEncodeError as exc:
            return f"{path}: a lone surrogate \\u{ord(value[exc.start]):04x} is not text"
        return None
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, list):
        items = ((f"[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for k, v in items:
        sub = f"{path}{k}" if str(k).startswith("[") else f"{path}.{k}" if path else str(k)
        found = _bad_value(k, f"{sub} (the key)") if isinstance(k, str) else None
        found = found or _bad_value(v, sub)
        if found is not None:
            return found
    return None


def parse_request(raw: bytes) -> dict[str, Any]:
    """The request's JSON object; RequestError with one line saying what is wrong."""
    if len(raw) > MAX_REQUEST_BYTES:
        raise RequestError(f"request too large: {len(raw)} bytes (limit {MAX_REQUEST_BYTES})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(f"request is not UTF-8 text: {exc}") from None
    if json_depth_exceeds(text, MAX_REQUEST_DEPTH):
        raise RequestError(f"request nested deeper than {MAX_REQUEST_DEPTH} levels")
    try:
        req = json.loads(text)
    except ValueError as exc:
        raise RequestError(f"invalid request: not JSON: {exc}") from None
    return check_request(req)


def check_request(req: Any) -> dict[str, Any]:
    """A decoded request that is an object, of a known command, without NaN or Infinity."""
    if not isinstance(req, dict):
        raise RequestError("invalid request: a control request must be a JSON object")
    bad = _bad_value(req, "")
    if bad is not None:
        raise RequestError(bad)
    cmd = req.get("cmd")
    if not isinstance(cmd, str) or cmd not in COMMANDS:
        raise RequestError(f"unknown command {cmd!r} (known: {', '.join(COMMANDS)})")
    return req


def check_mark(req: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """A `mark` request's text (one line of at most MAX_MARK_CHARS) and data (a JSON object
    of at most MAX_MARK_DATA_CHARS): a marker in the recording, as a plan leaves at each
    step's start and end with its settings."""
    unknown = sorted(set(req) - {"cmd", "id", "text", "data"})
    if unknown:
        raise RequestError(f"{unknown[0]}: unknown field of mark (known: text, data)")
    text, data = req.get("text"), req.get("data", {})
    if not isinstance(text, str) or not text.strip():
        raise RequestError("text: a mark needs a text (a string, not blank)")
    if len(text) > MAX_MARK_CHARS:
        raise RequestError(f"text: {len(text)} characters, over the limit of {MAX_MARK_CHARS}")
    if any(unicodedata.category(c) == "Cc" for c in text):
        raise RequestError("text: a control character (a line break, ...): a mark is one line")
    if not isinstance(data, dict):
        raise RequestError(f"data: expected a JSON object, got {type(data).__name__}")
    size = len(json.dumps(data))
    if size > MAX_MARK_DATA_CHARS:
        raise RequestError(
            f"data: {size} characters of JSON, over the limit of {MAX_MARK_DATA_CHARS}"
        )
    return text, data


# ---------------------------------------------------------------------------- changes
@dataclass(frozen=True)
class Change:
    """A checked, ready request for the loop: `cmd` and what it swaps in."""

    cmd: str
    controller_section: ControllerSection | None = None
    controller: Any = None
    in_force: dict[str, Any] | None = None  # set_controller: `run_identity.controller_in_force`
    reference_section: ReferenceSection | None = None
    reference: Any = None
    actuator: ActuatorSection | None = None
    sidecar: Any = None  # "sidecar": a restarted telemetry process (process, link, replies)
    frozen: bool = True  # "freeze_adaptation"
    lease: str = ""  # "renew": the lease an arm answered
    remote: bool = False  # from a Zenoh client (an arm holds a lease), not in process
    hil_scenario: Any = None  # "set_hil": the scenario of the next hybrid simulation runs
    # "arm", "set_hil" of a [hil] daemon: its next run, built here (its excitation record
    # takes 10 ms to seconds to compute: never in the loop)
    hil_run: Any = None


def read_limited(path: Path, dirs: tuple[Path, ...], max_bytes: int, timeout_s: float) -> str:
    """A file's text, read under the control plane's limits: inside one of `dirs` (after
    symlinks, before it is opened and again on the file opened), a regular file (a FIFO or
    device is refused without blocking), at most `max_bytes`, read within `timeout_s`."""
    real = Path(os.path.realpath(path))
    roots = [Path(os.path.realpath(d)) for d in dirs]

    def confine(where: Path) -> None:
        if not any(where.is_relative_to(r) for r in roots):
            allowed = ", ".join(str(d) for d in dirs) or "none configured"
            raise RequestError(f"{path}: outside the allowed directories ({allowed})")

    confine(real)
    try:
        fd = os.open(real, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise RequestError(f"{path}: cannot open: {exc.strerror}") from None
    try:
        # again on the file opened: a directory swapped for a symlink since is not followed out
        opened = Path(f"/proc/self/fd/{fd}")
        confine(Path(os.readlink(opened)) if opened.is_symlink() else real)
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise RequestError(f"{path}: not a regular file")
        if st.st_size > max_bytes:
            raise RequestError(f"{path}: {st.st_size} bytes, over the limit of {max_bytes}")
        deadline = time.monotonic() + timeout_s
        chunks: list[bytes] = []
        total = 0
        while chunk := os.read(fd, 1 << 16):
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:
                raise RequestError(f"{path}: grew over the limit of {max_bytes} bytes")
            if time.monotonic() > deadline:
                raise RequestError(f"{path}: not read within {timeout_s:g} s")
    finally:
        os.close(fd)
    try:
        return b"".join(chunks).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(f"{path}: not UTF-8 text: {exc}") from None


def settings_in_force(section: ControllerSection, controller: Any) -> dict[str, Any]:
    """What a `set_controller` or `set_model` put in force, for its reply: the model and the
    settings its controller uses, as it resolved them (the model's own continuity, ahead off
    for a model with history inputs)."""
    out: dict[str, Any] = {}
    if CONTROLLERS[section.name].needs_model:
        out["model"] = str(section.model)
    if section.name == "network_inversion":
        out |= {
            "method": controller.method,
            "ahead": controller.ahead,
            "feedback": section.feedback,
            "feedback_tau_s": section.feedback_tau_s,
            "continuity": controller.continuity,
        }
    if section.name == "constant":
        out["current_a"] = controller.current
    if section.name == "continuous_state":
        out |= {"gain": controller.gain, "b": controller.b}
    if section.name == "heaviside":
        out["on_current_a"] = controller.on_current_a
    return out


def _section(cls, table: dict, prefix: str):
    try:
        return parse(cls, table, "request", prefix)
    except ConfigError as exc:
        raise RequestError(str(exc).removeprefix("request: ")) from None


def _require_not_armed(state: RigState, what: str) -> None:
    if state is RigState.ARMED:
        raise RequestError(f"{what} only when not armed (disarm first)")


Builders = tuple[Callable[..., Any], Callable[..., Any]]


class Preparer:
    """Turns a parsed request into a `Change` (worker thread): every check, every file read,
    every object built. Reads the daemon's config, state and actuator; changes nothing."""

    def __init__(self, daemon: Any, build_controller: Callable, build_reference: Callable):
        self._d = daemon
        self._build_controller = build_controller
        self._build_reference = build_reference
        # the allowed directories, fixed at start-up: the configured ones and those of the
        # config's own model and profile. A path a request gave never widens them.
        cfg = daemon.cfg
        model, profile = cfg.controller.model, cfg.reference.path
        self.model_dirs = (*cfg.control.model_dirs, *((model.parent,) if model else ()))
        csv = profile if cfg.reference.kind == "csv" else None
        self.profile_dirs = (*cfg.control.profile_dirs, *((csv.parent,) if csv else ()))

    @property
    def cfg(self) -> DaemonConfig:
        return self._d.cfg

    def _read(self, path: Path, dirs: tuple[Path, ...], what: str) -> str:
        c = self.cfg.control
        text = read_limited(path, dirs, c.max_file_bytes, c.read_timeout_s)
        if path.suffix == ".json" and json_depth_exceeds(text, MAX_FILE_DEPTH):
            raise RequestError(f"{path}: {what} nested deeper than {MAX_FILE_DEPTH} levels")
        return text

    def _read_model(self, path: Path) -> str:
        """A model file's text, refused unparsed (and unscanned) when it holds more numbers
        than a model the loop can evaluate: json.loads holds the GIL for the whole text (a
        2.2 MB model held the loop up 280-580 ms)."""
        c = self.cfg.control
        text = read_limited(path, self.model_dirs, c.max_file_bytes, c.read_timeout_s)
        numbers = text.count(",") + 1
        if numbers > MAX_MODEL_NUMBERS:
            raise RequestError(
                f"{path}: about {numbers} numbers, more than the {MAX_MODEL_NUMBERS} of a model"
                " the loop can evaluate within its budget (not parsed: that alone would hold"
                " the loop up)"
            )
        if json_depth_exceeds(text, MAX_FILE_DEPTH):
            raise RequestError(f"{path}: model file nested deeper than {MAX_FILE_DEPTH} levels")
        return text

    def prepare(self, req: dict[str, Any]) -> Change:
        cmd = req["cmd"]
        if cmd == "mark":
            raise RequestError(
                "mark: taken by the telemetry process, which writes the recording (this daemon"
                " runs without one)"
            )
        if cmd == "arm" and (hil := self._d.hil) is not None and not hil.run_ready():
            return Change(cmd, hil_run=hil.build_run())
        if cmd in ("arm", "disarm", "reset", "status", "reset_adaptation"):
            return Change(cmd)
        if cmd == "renew":
            lease = req.get("lease")
            if not isinstance(lease, str) or not lease or len(lease) > 64:
                raise RequestError(f"lease: the id an arm answered is required, got {lease!r}")
            return Change(cmd, lease=lease)
        return getattr(self, f"_{cmd}")(req)

    def _freeze_adaptation(self, req: dict) -> Change:
        frozen = req.get("frozen", True)
        if not isinstance(frozen, bool):
            raise RequestError(f"frozen: expected true or false, got {frozen!r}")
        return Change("freeze_adaptation", frozen=frozen)

    def _set_controller(self, req: dict) -> Change:
        from mrrig.loop.twin_model import forward_model_from_text

        _require_not_armed(self._d.supervisor.state, "set_controller")
        name = req.get("name")
        if name not in CONTROLLER_NAMES:
            raise RequestError(
                f"name: unknown controller {name!r} (known: {', '.join(CONTROLLER_NAMES)})"
            )
        table = {k: v for k, v in req.items() if k in ("model", *CONTROLLER_SETTINGS)}
        table["name"] = name
        kept = self.cfg.controller.model
        if not CONTROLLERS[name].needs_model and "model" in table:
            raise RequestError(
                f"model: controller {name} uses no model file (leave the field out; the "
                f"daemon keeps {kept})"
            )
        if "model" in table and table["model"] is None:
            raise RequestError(
                f"model: null: controller {name} needs a model file (leave the field out "
                f"to keep {kept})"
            )
        if "model" not in table and kept is not None:
            table["model"] = str(kept)  # kept for a controller that uses none
        section = _section(ControllerSection, table, "controller")
        model = None
        if CONTROLLERS[section.name].needs_model:
            text = self._read_model(section.model)
            try:
                model = forward_model_from_text(text, section.model)
            except ValueError as exc:
                raise RequestError(str(exc)) from None
        try:
            controller = self._build_controller(self.cfg, section, model)
        except (ValueError, OSError) as exc:
            raise RequestError(str(exc)) from None
        return Change(
            "set_controller",
            controller_section=section,
            controller=controller,
            in_force=controller_in_force(section),  # the model's sha256 read here, off the loop
        )

    def _set_model(self, req: dict) -> Change:
        path = req.get("path")
        if not isinstance(path, str) or not path:
            raise RequestError("path: a model file path is required")
        now = self.cfg.controller
        if not CONTROLLERS[now.name].needs_model:
            raise RequestError(f"controller {now.name} uses no model")
        # the controller's settings stay as they are unless the request changes them
        kept = {k: getattr(now, k) for k in CONTROLLER_SETTINGS if getattr(now, k) is not None}
        given = {k: v for k, v in req.items() if k in CONTROLLER_SETTINGS}
        return self._set_controller({**kept, **given, "name": now.name, "model": path})

    def _set_profile(self, req: dict) -> Change:
        from mrrig.loop.reference import CsvSeries, check_in_range

        _require_not_armed(self._d.supervisor.state, "set_profile")
        table = {k: v for k, v in req.items() if k not in ("cmd", "id")}
        try:
            section = reference_from_table(table, "request")
        except ConfigError as exc:
            raise RequestError(str(exc).removeprefix("request: ")) from None
        if section.kind != "csv" and section.path is not None:
            raise RequestError(f"path: a {section.kind} reference reads no file (leave it out)")
        lo, hi = self.cfg.loop.f_range_n
        peak = abs(section.offset_n) + section.amplitude_n
        if section.kind in ("constant", "sine", "noise") and peak > max(-lo, hi):
            raise RequestError(
                f"amplitude_n: offset_n +- amplitude_n reaches {peak:g} N, outside "
                f"loop.f_range_n [{lo:g}, {hi:g}] N"
            )
        try:
            if section.kind == "csv":
                text = self._read(section.path, self.profile_dirs, "force profile")
                new = CsvSeries(section.path, text=text)
                check_in_range(new, self.cfg.loop.f_range_n)
            else:
                new = self._build_reference(section, self.cfg.loop.period_s)
        except (ValueError, OSError) as exc:
            raise RequestError(str(exc)) from None
        return Change("set_profile", reference_section=section, reference=new)

    def _set_hil(self, req: dict) -> Change:
        from mrrig.loop.hil_loop import scenario_with

        _require_not_armed(self._d.supervisor.state, "set_hil")
        hil = self._d.hil
        if hil is None:
            raise RequestError("set_hil: this daemon runs no hybrid simulation (no [hil] scenario)")
        table = {k: v for k, v in req.items() if k not in ("cmd", "id")}
        try:
            scenario = scenario_with(hil.configured, table, "set_hil")
        except ConfigError as exc:
            raise RequestError(str(exc).removeprefix("set_hil: ")) from None
        return Change("set_hil", hil_scenario=scenario, hil_run=hil.build_run(scenario))

    def _actuator(self, req: dict) -> Change:
        table = {k: v for k, v in req.items() if k not in ("cmd", "id")}
        section = _section(ActuatorSection, table, "actuator")
        d = self._d
        if section.waveform == "stream" and (why := d.profile.stream_refusal()):
            raise RequestError(why)
        check_actuator_step(d.supervisor.state, d.actuator, section, self.cfg, d.actuator_at_arm)
        return Change("actuator", actuator=section)


def check_actuator_step(
    state: RigState,
    now: ActuatorSection,
    new: ActuatorSection,
    cfg: DaemonConfig,
    at_arming: ActuatorSection,
) -> None:
    """While ARMED the motion may stop, or change amplitude within
    `control.armed_amplitude_step_m` of the amplitude it had when the rig was armed
    (`at_arming`); nothing else. The bound holds over a sequence of requests: a chain of
    small steps cannot walk the amplitude away from what was armed."""
    if state is not RigState.ARMED or new.waveform == "stop" or new == now:
        return
    if new.waveform != now.waveform:
        raise RequestError(
            f"waveform: {now.waveform} -> {new.waveform} only when not armed (disarm first)"
        )
    if new.frequency_hz != now.frequency_hz:
        raise RequestError("frequency_hz: changes only when not armed (disarm first)")
    step = cfg.control.armed_amplitude_step_m
    moved = abs(new.amplitude_m - at_arming.amplitude_m)
    # to the DBC's resolution of the amplitude (10 um): 0.020 - 0.015 is 0.005000000000000001
    if round(moved - step, 9) > 0:
        raise RequestError(
            f"amplitude_m: {new.amplitude_m:g} m is {moved * 1e3:.3g} mm from the "
            f"{at_arming.amplitude_m:g} m armed (limit control.armed_amplitude_step_m = "
            f"{step * 1e3:g} mm from the amplitude at arming; disarm first)"
        )


# ---------------------------------------------------------------------------- the worker
Reply = Callable[[dict[str, Any]], None]


@dataclass
class _Item:
    req: Any  # raw bytes (from the sidecar) or a dict (in process)
    reply: Reply
    change: Change | None = None


class ControlWorker:
    """The daemon's control thread: requests in, ready changes to the loop, replies out.

    `submit` (any thread, never blocks) queues a request with the callable that delivers its
    reply; the worker prepares it; the loop `take`s the change between frames and gives the
    reply back with `done`. Replies are delivered from the worker thread only.
    """

    def __init__(self, preparer: Preparer) -> None:
        self._prep = preparer
        self._inbox: queue.SimpleQueue[tuple[str, _Item, dict | None]] = queue.SimpleQueue()
        self._mailbox: queue.Queue[_Item] = queue.Queue(maxsize=MAILBOX_SIZE)
        self._thread = threading.Thread(target=self._run, name="mrrig-control", daemon=True)
        self._started = False
        self.on_start: Callable[[], None] | None = None  # runs first in the worker thread

    def start(self) -> None:
        if not self._started:
            self._started = True
            self._thread.start()

    def stop(self) -> None:
        if self._started:
            self._inbox.put(("stop", _Item(None, lambda _r: None), None))
            self._thread.join(timeout=5)

    def submit(self, req: Any, reply: Reply) -> None:
        self._inbox.put(("request", _Item(req, reply), None))

    def submit_job(self, job: Callable[[], Change | None]) -> None:
        """Slow work the loop asks for (restarting the telemetry process): run in the worker
        thread; a Change it returns goes to the loop like a request's."""
        self._inbox.put(("job", _Item(job, _log_reply), None))

    def ready(self) -> int:
        """How many prepared changes wait for the loop."""
        return self._mailbox.qsize()

    def take(self) -> tuple[Change, _Item] | None:
        """The next ready change (loop thread), or None."""
        try:
            item = self._mailbox.get_nowait()
        except queue.Empty:
            return None
        return item.change, item

    def done(self, item: _Item, reply: dict[str, Any]) -> None:
        """The loop's reply to a change it took (loop thread; never blocks)."""
        self._inbox.put(("done", item, reply))

    def _run(self) -> None:
        if self.on_start is not None:
            self.on_start()
        while True:
            kind, item, reply = self._inbox.get()
            if kind == "stop":
                return
            if kind == "done":
                self._deliver(item, reply)
                continue
            if kind == "job":
                self._job(item)
                continue
            try:
                raw = item.req
                req = parse_request(raw) if isinstance(raw, bytes) else check_request(raw)
                item.change = self._prep.prepare(req)
                if isinstance(raw, bytes):  # through the telemetry process: a Zenoh client
                    item.change = replace(item.change, remote=True)
            except RequestError as exc:
                self._deliver(item, {"ok": False, "error": str(exc)})
                continue
            except Exception as exc:  # noqa: BLE001 - one request never ends the control plane
                log.exception("control request failed")
                self._deliver(item, {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
                continue
            try:
                self._mailbox.put_nowait(item)
            except queue.Full:
                self._deliver(item, {"ok": False, "error": "busy: too many changes waiting"})

    def _job(self, item: _Item) -> None:
        try:
            item.change = item.req()
        except Exception as exc:  # noqa: BLE001 - the worker outlives a failed job
            log.exception("control thread job failed")
            self._deliver(item, {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
            return
        if item.change is not None:
            try:
                self._mailbox.put(item, timeout=JOB_PUT_TIMEOUT_S)
            except queue.Full:
                log.error("the loop took no change for %g s: job result lost", JOB_PUT_TIMEOUT_S)

    @staticmethod
    def _deliver(item: _Item, reply: dict[str, Any] | None) -> None:
        try:
            item.reply(reply or {"ok": False, "error": "no reply"})
        except Exception:  # noqa: BLE001 - a reply that cannot go out must not stop the worker
            log.exception("could not deliver a control reply")


def _log_reply(reply: dict[str, Any]) -> None:
    if not reply.get("ok", True):
        log.error("control thread: %s", reply.get("error"))


class Pending:
    """An in-process request's reply (`Daemon.submit`): `wait()` for it."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.reply: dict[str, Any] | None = None

    def __call__(self, reply: dict[str, Any]) -> None:
        self.reply = reply
        self._event.set()

    def done(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout_s: float) -> dict[str, Any]:
        if not self._event.wait(timeout_s):
            return {"ok": False, "error": f"daemon did not answer within {timeout_s:g} s"}
        return self.reply


COMMANDS = (
    "arm",
    "renew",  # keep the lease an arm answered ({"cmd": "renew", "lease": ID})
    "disarm",
    "reset",  # acknowledge a FAULT (to IDLE): arm is refused until then
    "status",
    "set_controller",
    "set_model",
    "set_profile",
    "actuator",
    "reset_adaptation",
    "freeze_adaptation",
    "set_hil",  # the next hybrid simulation runs' law, compensation, duration_s (disarmed)
    "mark",  # a marker in the recording (answered by the telemetry process, which writes it)
)
