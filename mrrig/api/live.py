"""The live half of `mrrig.api` (imported on first use: numpy and the exports are not what
`mrrig runs` needs): `Recording`, `Rig`, `RigError`, `Telemetry`."""

from __future__ import annotations

import json
import logging
import math
import time
import weakref
from collections.abc import Callable, Iterable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from mrrig.errors import MrrigError
from mrrig.export import COLUMNS, UTC_COLUMN, read_any, utc_ns, utc_start

if TYPE_CHECKING:
    import pandas as pd
    import zenoh

    from mrrig.rigio.force_stream import SendResult
    from mrrig.rigio.lease import Lease
    from mrrig.rigio.rearm import RearmLimit

log = logging.getLogger(__name__)

_NAMES = {c.field: c.name for c in COLUMNS}
# stream_force's profile length: the forces' own end stops it (`_Feed` gives None there)
_UNTIL_THE_END_S = 1e9
# a disarm that the daemon did not answer in time is asked this many times in all
DISARM_TRIES = 3
# an arm that the daemon did not answer in time: the rig disarmed, then asked again (in all)
ARM_TRIES = 3


def _unanswered(error: str) -> bool:
    """The rig's sidecar's answer for a request the daemon did not answer in time."""
    return error == "daemon did not answer" or error.startswith("busy")


class RigError(MrrigError, RuntimeError):
    """The daemon refused a request (its reply's `error`), or the Rig is closed."""


class RigUnanswered(RigError):
    """The rig's control plane did not answer the request in time ("daemon did not answer",
    "busy: the control plane is overloaded"): not a refusal, a request to ask again."""


def _frame(samples: np.ndarray, utc0: datetime | None = None) -> pd.DataFrame:
    """Samples as a DataFrame with unit-named columns (`t_s`, `x_m`, `force_n`, ...) and, with
    a UTC start, `utc` (`utc0` + `t_s`)."""
    import pandas as pd

    frame = pd.DataFrame({_NAMES.get(n, n): samples[n] for n in samples.dtype.names})
    if utc0 is not None:
        frame.insert(0, UTC_COLUMN, pd.to_datetime(utc_ns(samples["t"], utc0), utc=True))
    return frame


class Recording:
    """A recorded run, read once: the daemon's `.rrd`, or a Parquet or MDF4 export of it."""

    def __init__(self, path: str | Path) -> None:
        rec = read_any(path)
        self._rec = rec
        self.path: Path = rec.path
        #: every sample, sorted by `t`: SAMPLE_DTYPE fields `t` (s since the daemon started),
        #: `x`, `x_est` (m), `xd` (m/s), `xdd` (m/s^2), `f_meas`, `f_des`, `f_model` (N),
        #: `i_cmd`, `i_meas` (A), `latency_us` (us), `temp_degc` (degC), `state` (RigState)
        self.samples: np.ndarray = rec.samples
        #: the run's events: `t` (s), `level`, `text`, plus their fields (`kind`, `reason`, ...)
        self.events: list[dict[str, Any]] = rec.events
        #: the daemon's end-of-run summary (Et, faults, latency percentiles, ...); None when
        #: the run was cut short
        self.summary: dict[str, Any] | None = rec.summary
        #: who ran what, where, when (run id, rig, specimen, model sha256, ...); None in a
        #: recording made before runs had one
        self.identity: dict[str, Any] | None = rec.identity

    @property
    def utc_start(self) -> datetime | None:
        """The UTC time of `t = 0` (the run identity's start, else as `mrrig.export` says)."""
        return utc_start(self._rec)[0]

    def to_pandas(self) -> pd.DataFrame:
        """The samples as a DataFrame: `utc` (UTC timestamps), then unit-named columns
        (`t_s`, `x_m`, `xd_m_s`, `force_n`, `i_cmd_a`, `latency_us`, `state`, ...)."""
        return _frame(self.samples, self.utc_start)

    def __len__(self) -> int:
        return int(self.samples.size)

    def __repr__(self) -> str:
        et = (self.summary or {}).get("et")
        return f"Recording({str(self.path)!r}: {len(self)} samples, Et {et})"


class Telemetry:
    """The rig's live telemetry, batch by batch (numpy structured arrays of the sample fields,
    SI units as `Recording.samples`; a missing value is NaN), for `duration_s` or until no
    batch came for `quiet_s`. Every batch iterated is kept for `samples` and `to_pandas()`;
    `utc_start` is the UTC time of `t = 0` the daemon sends with each batch (its run's start)."""

    def __init__(self, session: zenoh.Session, rig: str, duration_s: float | None, quiet_s: float):
        from mrrig.rigio.rig_topics import keys

        self._sub = session.declare_subscriber(keys(rig)["telemetry"])
        self._duration_s = duration_s
        self._quiet_s = quiet_s
        self.batches: list[np.ndarray] = []
        #: the UTC time of `t = 0` (the run identity's `started_utc`, sent with every batch);
        #: None until a batch carrying it came (a daemon older than this sends none)
        self.utc_start: datetime | None = None

    def __iter__(self) -> Iterator[np.ndarray]:
        import time

        t0 = last = time.monotonic()
        try:
            while self._duration_s is None or time.monotonic() - t0 < self._duration_s:
                sample = self._sub.try_recv()
                if sample is None:
                    if time.monotonic() - last > self._quiet_s:
                        break
                    time.sleep(0.01)
                    continue
                last = time.monotonic()
                message = json.loads(sample.payload.to_bytes())
                if self.utc_start is None and message.get("utc_start"):
                    self.utc_start = datetime.fromisoformat(message["utc_start"]).astimezone(UTC)
                batch = _batch(message["fields"])
                self.batches.append(batch)
                yield batch
        finally:
            self._sub.undeclare()

    @property
    def samples(self) -> np.ndarray:
        """Every batch iterated so far, in one array."""
        from mrrig.loop.samples import SAMPLE_DTYPE

        return np.concatenate(self.batches) if self.batches else np.empty(0, SAMPLE_DTYPE)

    def to_pandas(self) -> pd.DataFrame:
        """The batches iterated so far as a DataFrame: `utc` (UTC timestamps: `utc_start` +
        `t_s`; left out when the daemon sent no start), then unit-named columns (`t_s`, ...),
        as `Recording.to_pandas()`."""
        return _frame(self.samples, self.utc_start)


def _batch(fields: dict[str, list[Any]]) -> np.ndarray:
    """A telemetry message's columns (null: not finite) as SAMPLE_DTYPE samples."""
    from mrrig.loop.samples import SAMPLE_DTYPE

    n = len(fields.get("t", []))
    batch = np.zeros(n, dtype=SAMPLE_DTYPE)
    for name in SAMPLE_DTYPE.names:
        values = fields.get(name)
        if values is None:
            if SAMPLE_DTYPE[name].kind == "f":
                batch[name] = np.nan
            continue
        batch[name] = [math.nan if v is None else v for v in values]
    return batch


class _Feed:
    """An iterable of forces as `send_force`'s fn(t) at `rate_hz`: the k-th value for the k-th
    time, the same value when a time repeats, None once the values end or one is not a finite
    number (the stream stops there, ramps to 0 N and disarms; `bad` says which)."""

    def __init__(self, forces: Iterable[float], rate_hz: float) -> None:
        self._it = iter(forces)
        self._rate_hz = rate_hz
        self._k = -1
        self._value: float | None = None
        self.bad: str | None = None

    def __call__(self, t: float) -> float | None:
        k = round(t * self._rate_hz)
        while self._k < k and self.bad is None:
            self._k += 1
            v = next(self._it, None)
            self._value = None if v is None else float(v)
            if self._value is not None and not math.isfinite(self._value):
                self.bad = f"force {self._k} is {self._value} N (every force must be finite)"
                self._value = None
        return self._value


class Rig:
    """A running daemon (`mrrig run`) of rig `name`, over one Zenoh session.

    `zenoh_config`: a Zenoh config file or `zenoh.Config` (default: `configs/zenoh-client.json5`,
    127.0.0.1, as the CLI's `--zenoh-config`); `timeout_s`: how long a request waits for the
    daemon's reply (s).
    """

    def __init__(
        self,
        name: str,
        zenoh_config: str | Path | zenoh.Config | None = None,
        timeout_s: float = 2.0,
    ) -> None:
        import zenoh

        from mrrig.rigio import audit
        from mrrig.rigio.client import DEFAULT_CONFIG, open_session
        from mrrig.rigio.zenoh_config import load_zenoh_config

        self.name = name
        self.timeout_s = timeout_s
        conf = zenoh_config if zenoh_config is not None else DEFAULT_CONFIG
        self._conf = conf if isinstance(conf, zenoh.Config) else load_zenoh_config(conf)
        self._cm = open_session(self._conf)
        self._session: zenoh.Session | None = self._cm.__enter__()
        self._claims = audit.claims(self._session, self._conf)
        self._lease: Lease | None = None  # the lease of this client's arm, renewed while held
        self._armed_here = False  # this client armed the rig: its close stops the actuator
        self._rearms: RearmLimit | None = None  # `rearm`'s cap, made on its first use
        # the last resort at exit: an open session keeps the interpreter from ending
        self._finalizer = weakref.finalize(self, self._session.close)

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the Zenoh session (again: nothing). A client that armed the rig disarms it
        if it still holds its lease and stops the actuator first (the firmware ramps it to
        rest): its end, normal or by Ctrl-C, leaves the rig still and SAFE."""
        if self._session is not None:
            if self._armed_here:
                self._end_of_client()
            self._session = None
            self._finalizer.detach()
            self._cm.__exit__(None, None, None)

    @property
    def operator(self) -> str:
        """Who drives the rig (for the runs this client registers): the common name of the
        Zenoh config's certificate where it authenticates with mutual TLS, else its Zenoh
        user where it authenticates by user and password, else the local user."""
        from mrrig.rigio.run_identity import operator_of

        return operator_of(self._conf)

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RigError(f"rig {self.name!r}: closed")
        return self._session

    def ask(self, payload: dict[str, Any]) -> dict[str, Any]:
        """One control request (`{"cmd": ...}`, as `mrrig control`) and the daemon's reply as
        it is, `ok` or not (ClientError where no daemon answers). An arm's lease is held
        (renewed in the background) until a disarm or `close`."""
        reply = self._query(payload, self.timeout_s)
        cmd = payload.get("cmd")
        if cmd == "arm" and reply.get("ok"):
            from mrrig.rigio.lease import Lease

            self._armed_here = True
            self._release()
            self._lease = Lease.of(self._query, reply, self.name)
        elif cmd == "disarm" and reply.get("ok"):
            self._release()
        return reply

    def _query(self, payload: dict[str, Any], timeout_s: float) -> dict[str, Any]:
        from mrrig.rigio.client import query

        return query(self.session, self.name, payload, timeout_s, self._claims)

    def _release(self) -> None:
        if self._lease is not None:
            self._lease.release()
            self._lease = None

    def let_go(self) -> None:
        """Stop renewing this client's lease and leave the rig as it is: `close` then neither
        disarms nor stops the actuator; the daemon does both once the lease lapses (its
        `lease_timeout_s`) unless another client arms (takes the lease) before."""
        self._release()
        self._armed_here = False

    @property
    def lease(self) -> Lease | None:
        """The lease of this client's arm while it holds one (`lost` says why it ended)."""
        return self._lease

    def _end_of_client(self) -> None:
        """Disarm while this client holds the rig, and stop the actuator; a daemon that does
        not answer disarms and stops it on its own once the lease lapses."""
        from mrrig.rigio.client import ClientError

        held = self._lease is not None and self._lease.held
        self._release()
        try:
            if held:
                self._query({"cmd": "disarm"}, self.timeout_s)
            self._query({"cmd": "actuator", "waveform": "stop"}, self.timeout_s)
        except ClientError as exc:
            log.error("rig %s: no disarm and actuator stop at the client's end: %s", self.name, exc)

    def request(self, payload: dict[str, Any]) -> dict[str, Any]:
        """`ask`, and RigError when the reply is not ok."""
        reply = self.ask(payload)
        if not reply.get("ok"):
            error = str(reply.get("error"))
            kind = RigUnanswered if _unanswered(error) else RigError
            raise kind(f"rig {self.name!r}: {payload.get('cmd')}: {error}")
        return reply

    def status(self) -> dict[str, Any]:
        """The daemon's status: `state` (IDLE/ARMED/FAULT), `fault`, `controller`, `reference`,
        counters, the recording being written, ... (as `mrrig status --json`'s `status`)."""
        return self.request({"cmd": "status"})["status"]

    def arm(self) -> dict[str, Any]:
        """Arm: the daemon's commands become ACTIVE. Returns its reply. An arm the control
        plane did not answer in time ("daemon did not answer", "busy", or no reply) may have
        armed the rig under a lease this client never got: the rig is disarmed (`disarm`) and
        the arm asked again, up to ARM_TRIES times in all (on CI, three rigs on a 2-core
        machine, a plan step was aborted on "arm: daemon did not answer")."""
        return self._ask_until_answered("arm", ARM_TRIES, before_again=self.disarm)

    def disarm(self) -> dict[str, Any]:
        """Disarm: commands become SAFE 0 A. Returns the daemon's reply. A disarm the daemon
        did not answer in time (its control plane overloaded: "daemon did not answer", "busy",
        or no reply at all) is asked again, up to DISARM_TRIES times: it only makes the rig
        safer, and a plan that gave up after one such answer aborted a step whose rig then
        disarmed a second later (three rigs on a 2-core machine)."""
        return self._ask_until_answered("disarm", DISARM_TRIES)

    def _ask_until_answered(
        self, cmd: str, tries: int, before_again: Callable[[], object] | None = None
    ) -> dict[str, Any]:
        """`cmd`'s reply, asked up to `tries` times while the daemon did not answer it in time
        (a ClientError, or its "daemon did not answer" or "busy"), `before_again` called
        between; any other refusal is a RigError at once, the last ClientError raised."""
        from mrrig.rigio.client import ClientError

        for tries_left in range(tries - 1, -1, -1):
            try:
                reply = self.ask({"cmd": cmd})
            except ClientError as exc:
                if not tries_left:
                    raise
                error = str(exc)
            else:
                error = str(reply.get("error") or "")
                if reply.get("ok") or not tries_left or not _unanswered(error):
                    break
            again = "disarmed, and asked again" if before_again else "asking again"
            log.warning("rig %r: %s unanswered (%s): %s", self.name, cmd, error, again)
            if before_again is not None:
                before_again()
        if not reply.get("ok"):
            raise RigError(f"rig {self.name!r}: {cmd}: {reply.get('error')}")
        return reply

    def reset(self) -> dict[str, Any]:
        """Acknowledge a FAULT (back to IDLE), the one way out of FAULT before `arm`."""
        return self.request({"cmd": "reset"})

    def rearm(self, limit: RearmLimit | None = None) -> dict[str, Any]:
        """After a transport fault (a stall): acknowledge it (`reset`) and arm again, within
        `limit` (default this client's own: at most 3 re-arms in any 10 s,
        `mrrig.rigio.rearm`). Beyond it, RigError `faulty bus: N faults in S s` and the rig
        stays in FAULT. Returns the arm's reply."""
        if limit is None:
            from mrrig.rigio.rearm import RearmLimit

            self._rearms = self._rearms or RearmLimit()
            limit = self._rearms
        now = time.monotonic()
        if not limit.allows(now):
            raise RigError(f"rig {self.name!r}: {limit.refusal()}")
        self.reset()
        reply = self.arm()
        limit.rearmed(now)
        return reply

    def stream_force(
        self,
        forces: Iterable[float],
        rate_hz: float = 100.0,
        *,
        arm: bool = False,
        disarm: bool = True,
        ramp_s: float = 0.5,
        duration_s: float | None = None,
        out: TextIO | None = None,
    ) -> SendResult:
        """Stream desired forces (N), one per 1/`rate_hz` s, as `mrrig send-force`: the daemon
        must take a `zenoh` force reference; with `arm`, armed once it has the first force;
        then a ramp to 0 N over `ramp_s` (s) and a disarm (unless `disarm=False`). `forces`:
        a sequence, an array or any iterator (streamed as it yields, until it ends); a force
        that is not finite stops the stream there (ramp, disarm), then ValueError.
        `duration_s`: the profile's length where known (s; its progress lines say how far),
        `out`: where a line a second goes (as `mrrig send-force`'s), None for none."""
        from mrrig.rigio.force_stream import send_force

        feed = _Feed(forces, rate_hz)
        if feed(0.0) is None:
            raise ValueError(f"stream_force: {feed.bad or 'no forces to send'}")
        result = send_force(
            self.name,
            self._conf,
            feed,  # type: ignore[arg-type]  # None ends the stream (force_stream.stream)
            _UNTIL_THE_END_S if duration_s is None else duration_s,
            rate_hz,
            arm=arm,
            disarm=disarm,
            ramp_s=ramp_s,
            timeout_s=self.timeout_s,
            out=out,
        )
        if feed.bad:
            raise ValueError(f"stream_force: {feed.bad}: stopped there, ramped to 0 N")
        return result

    def telemetry(self, duration_s: float | None = None, quiet_s: float = 2.0) -> Telemetry:
        """The live telemetry (about 50 batches a second) for `duration_s` (s; None: until
        no batch for `quiet_s` s); iterate it, then `.samples` or `.to_pandas()`."""
        return Telemetry(self.session, self.name, duration_s, quiet_s)

    def __repr__(self) -> str:
        return f"Rig({self.name!r}{'' if self._session else ', closed'})"
