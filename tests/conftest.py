"""Shared fixtures: a forward model trained from the simulator, processes on a bridge."""

from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from mrrig.offline.datasets import Series, dataset_b
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from tests import rig_chain

REPO = Path(__file__).resolve().parents[1]
# a valid RigSensors message's signals (a machine at rest, actuator on, no fault)
SENSORS = {
    "ActuatorEnabled": 1,
    "LimitTripped": 0,
    "EStop": 0,
    "SensorFault": 0,
    "Displacement": 0.001,
    "Force": 10.0,
}


SMALL = dict(amplitudes_m=(0.010, 0.020), freqs_hz=(2.0, 5.0), currents_a=(0.0, 0.6, 1.2))


@pytest.fixture(scope="session")
def small_b(tmp_path_factory):
    """A small characterization matrix (data set B: 2 x 2 x 3 runs of 0.4 s), simulated once."""
    with _Machine.hold(_shared_base(tmp_path_factory), alone=False):
        return dataset_b(duration_s=0.4, **SMALL)


@pytest.fixture(scope="session")
def small_truth(small_b):
    """The small matrix with its exact kinematics (no estimation in the way)."""
    b = small_b
    return Series(
        t=b.t,
        x=b.x,
        xd=b.xd,
        xdd=b.xdd,
        current=b.current,
        force=b.force_meas,
        name="small",
        run_id=b.run_id,
    )


@pytest.fixture(scope="session")
def sim_model(tmp_path_factory) -> Path:
    """A forward network trained on the simulated characterization matrix, once per run: the
    pytest-xdist workers share the base directory and the first one trains it."""
    from filelock import FileLock

    from mrrig.offline.training import simulated_matrix_model

    root = _shared_base(tmp_path_factory)
    path = root / "sim-forward.json"
    with _Machine.hold(root, alone=False), FileLock(f"{path}.lock"):
        if not path.is_file():
            simulated_matrix_model(path, seed=0)
    return path


@pytest.fixture(scope="session")
def sim_gru(tmp_path_factory) -> Path:
    """A GRU forward model trained on the simulated characterization matrix, once per run,
    under the machine's shared hold (about 100 s of training: a process module that trained
    it itself held the machine alone meanwhile)."""
    from filelock import FileLock

    from mrrig.offline.training.gru import simulated_matrix_gru

    root = _shared_base(tmp_path_factory)
    path = root / "sim-gru.json"
    with _Machine.hold(root, alone=False), FileLock(f"{path}.lock"):
        if not path.is_file():
            simulated_matrix_gru(path)
    return path


DYKE = REPO.parent / "shared" / "data" / "dyke-mr-damper-ransim-u.csv"


def _mrrig_ok(*args: str, timeout_s: float = 900) -> str:
    """`mrrig ARGS` in a process of its own: its output, which must end with exit code 0."""
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout + proc.stderr


@pytest.fixture(scope="session")
def dyke_twin_path(tmp_path_factory) -> tuple[Path, Path]:
    """(twin, forward model in A) of the Dyke file, as the README's commands make them, once per
    run under the machine's shared hold (about 40 s of fits and training: the twin path's
    process test, tests/test_twin_path.py, held the machine alone meanwhile; tests/
    test_session_models.py asks for them first, while the shared modules run). `mrrig identify`
    gives the twin; `mrrig train` on the same measured data (not on the twin) the forward model,
    whose command in V `mrrig identify --map-model` maps to the rig's A."""
    from filelock import FileLock

    root = _shared_base(tmp_path_factory)
    twin, fwd_v, fwd = (root / f"dyke-{name}.json" for name in ("twin", "fwd-v", "fwd"))
    with _Machine.hold(root, alone=False), FileLock(f"{fwd}.lock"):
        if not fwd.is_file():
            # one start: the path needs a twin, not the starts' better estimate (its time kept)
            _mrrig_ok("-q", "identify", str(DYKE), "--out", str(twin), "--starts", "1")
            # no history inputs: they would count samples of 3004.8 Hz (the daemon refuses such
            # a model)
            train = ("--features", "manual", "--history", "0", "--no-supervised")
            _mrrig_ok("-q", "train", str(DYKE), "--out", str(fwd_v), *train)
            _mrrig_ok("-q", "identify", "--map-model", str(fwd_v), "--out", str(fwd))
    return twin, fwd


# the two file locks every test run on this machine shares ($MRRIG_TEST_MACHINE to move them)
MACHINE_LOCKS = Path(os.environ.get("MRRIG_TEST_MACHINE", "/tmp/mrrig-test-machine"))


class _Machine:
    """The machine, shared by pytest-xdist's workers and by any other test run on it through
    two file locks in MACHINE_LOCKS: a process module (its tests start rigs: a simulator, a
    bridge, a daemon that runs SCHED_FIFO on the loop's CPU) holds it alone; any other module,
    and the session's training, hold it shared. A rig on this 2-core machine uses both CPUs; a torch
    training or a second rig beside it stalls its processes for tens of ms, and a process test
    cannot tell that from a fault of the daemon. The turnstile keeps a waiting process module
    from being starved by the other worker's stream of shared holders."""

    held: str | None = None  # "shared" or "alone" while this worker holds the machine
    # seconds this worker waited for the machine and held it, by how: the run's summary
    seconds: collections.Counter[str] = collections.Counter()
    # seconds each process module held the machine alone (the rig chain's links): the summary
    alone_by_module: collections.Counter[str] = collections.Counter()

    @classmethod
    @contextlib.contextmanager
    def hold(cls, base: Path, alone: bool) -> Iterator[None]:
        del base  # the locks are the machine's, not one run's: two runs at once disturb
        # each other's rigs as two workers do (a developer's runs beside CI's or another's)
        if cls.held is not None:
            yield  # this worker holds it already
            return
        MACHINE_LOCKS.mkdir(mode=0o1777, parents=True, exist_ok=True)
        with (
            open(MACHINE_LOCKS / "machine.turnstile", "a") as turnstile,
            open(MACHINE_LOCKS / "machine.lock", "a") as machine,
        ):
            how = "alone" if alone else "shared"
            t0 = time.monotonic()
            fcntl.flock(turnstile, fcntl.LOCK_EX)
            try:
                fcntl.flock(machine, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
            finally:
                fcntl.flock(turnstile, fcntl.LOCK_UN)
            t1 = time.monotonic()
            cls.seconds[f"waited to hold it {how}"] += t1 - t0
            cls.held = how
            try:
                yield
            finally:
                cls.held = None
                fcntl.flock(machine, fcntl.LOCK_UN)
                cls.seconds[f"held it {how}"] += time.monotonic() - t1


def _shared_base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The base directory all of the run's workers share."""
    root = tmp_path_factory.getbasetemp()
    return root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root


@pytest.fixture(scope="session", autouse=True)
def _runs_catalog_of_the_tests(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The daemons the tests start register their runs in a catalog of the test run's own
    ($MRRIG_CATALOG, inherited by every process), not in the checkout's recordings/."""
    path = tmp_path_factory.mktemp("catalog") / "catalog.sqlite"
    old = os.environ.get("MRRIG_CATALOG")
    os.environ["MRRIG_CATALOG"] = str(path)
    yield
    if old is None:
        os.environ.pop("MRRIG_CATALOG", None)
    else:
        os.environ["MRRIG_CATALOG"] = old


# Modules of pure numerics (trainings, fits, the models' and the HIL's numerics: no thread,
# process, socket or timeout of their own) that run beside a rig at SCHED_IDLE rather than wait
# for the machine: a task of that class gets only a CPU no other task wants, and any other
# task that wakes takes its CPU at once, so the rig's bridges, sidecars and tools lose nothing
# to them (its loops and simulators are SCHED_FIFO anyway). They took about 220 s of CI's
# test time while the other worker's rigs left a CPU idle.
BESIDE_RIGS = frozenset(
    {
        "test_features_auto_kinds",
        "test_measured_data",
        "test_identify_generalizes",
        "test_plant",
        "test_training",
        "test_export_window",
        "test_crossval",
        "test_datasets",
        "test_hil_loop",
        "test_inversion",
        "test_hil_numerics",
        "test_closed_loop",
        "test_reference_motion",
        "test_actuator",
        "test_evaluate_kinds",
        "test_model_continuity",
        "test_greybox",
        "test_choice_by_other_tests",
        "test_beside_rigs",
        "test_rnn_training",
    }
)


@contextlib.contextmanager
def _at_sched_idle() -> Iterator[bool]:
    """Every thread of this process (a pool that torch or OpenBLAS started earlier too, and
    what they start) at SCHED_IDLE while the block runs, then as it was; False (nothing
    changed) where this process could not set it back (not root)."""
    if os.geteuid() != 0 or not hasattr(os, "SCHED_IDLE"):
        yield False
        return
    tids = [int(t) for t in os.listdir("/proc/self/task")]
    old = {}
    for tid in tids:
        with contextlib.suppress(OSError):
            old[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid))
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
    try:
        yield True
    finally:
        for tid, (policy, param) in old.items():
            with contextlib.suppress(OSError):  # a thread that ended
                os.sched_setscheduler(tid, policy, param)


@pytest.fixture(scope="module", autouse=True)
def _process_modules_run_alone(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[None]:
    """A module with process tests holds the machine alone, its module fixtures included
    (send-force's and the bus logs' runs start rigs too); a module of BESIDE_RIGS runs beside
    them at SCHED_IDLE; any other module holds it shared."""
    module = request.module
    process = any(
        item.get_closest_marker("process") is not None
        for item in request.session.items
        if getattr(item, "module", None) is module
    )
    if not process and module.__name__.rsplit(".", 1)[-1] in BESIDE_RIGS:
        with _at_sched_idle() as idle:
            if idle:
                _Machine.held = "beside"  # its fixtures' trainings too: no lock, idle
                try:
                    yield
                finally:
                    _Machine.held = None
                return
    held_before = _Machine.seconds["held it alone"]
    with _Machine.hold(_shared_base(tmp_path_factory), alone=process):
        yield
    if process:
        held = _Machine.seconds["held it alone"] - held_before
        _Machine.alone_by_module[request.module.__name__.rsplit(".", 1)[-1]] += held


def pytest_configure(config: pytest.Config) -> None:
    """The controller of a parallel run names the file its workers write their module kinds to
    (tests/rig_chain.py), before it starts them."""
    if config.getvalue("dist") == "loadfile" and not hasattr(config, "workerinput"):
        fd, path = tempfile.mkstemp(prefix="mrrig-rig-chain-", suffix=".json")
        os.close(fd)
        os.environ[rig_chain.KINDS_ENV] = path
        config.add_cleanup(lambda: Path(path).unlink(missing_ok=True))


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """Under `--dist loadfile` (the default addopts): tests/rig_chain.py's order."""
    if config.getvalue("dist") != "loadfile":
        return None
    return rig_chain.RigChainScheduling(config, log)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A worker hands its seconds with the machine to the controller (xdist's workeroutput)."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["machine_seconds"] = dict(_Machine.seconds)
        workeroutput["alone_by_module"] = dict(_Machine.alone_by_module)
    elif _Machine.seconds:  # a run without workers (-n 0): its own seconds
        _WORKER_SECONDS["main"] = dict(_Machine.seconds)
        _ALONE_BY_MODULE.update(_Machine.alone_by_module)


def pytest_testnodedown(node: Any, error: Any) -> None:
    """The controller keeps each worker's seconds with the machine."""
    output = getattr(node, "workeroutput", {})
    seconds = output.get("machine_seconds")
    if seconds is not None:
        _WORKER_SECONDS[node.gateway.id] = seconds
    _ALONE_BY_MODULE.update(output.get("alone_by_module", {}))


_WORKER_SECONDS: dict[str, dict[str, float]] = {}
_ALONE_BY_MODULE: collections.Counter[str] = collections.Counter()


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """Where the run's time went on the machine: per worker, how long it held the machine alone
    (the process modules: they run one at a time) or shared, and how long it waited for it."""
    for worker, seconds in sorted(_WORKER_SECONDS.items()):
        parts = ", ".join(f"{how} {s:.0f} s" for how, s in sorted(seconds.items()))
        terminalreporter.write_line(f"machine, {worker}: {parts or 'not held'}")
    if _ALONE_BY_MODULE:
        chain = sum(_ALONE_BY_MODULE.values())
        longest = ", ".join(f"{m} {s:.0f} s" for m, s in _ALONE_BY_MODULE.most_common(10))
        terminalreporter.write_line(
            f"rig chain: {len(_ALONE_BY_MODULE)} process modules held the machine alone "
            f"{chain:.0f} s; the longest: {longest}"
        )


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--all",
        action="store_true",
        help="also the process and long tests (CI runs every test)",
    )


def _kind_of_module(module: Any, rigs: set[Any]) -> str:
    """What a module needs of the machine: the rigs alone, a CPU beside them, or a shared hold."""
    if module in rigs:
        return rig_chain.RIGS
    if module.__name__.rsplit(".", 1)[-1] in BESIDE_RIGS and os.geteuid() == 0:
        return rig_chain.BESIDE  # (not root: it cannot set SCHED_IDLE back, and holds shared)
    return rig_chain.SHARED


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test on the bridge or with processes of its own is a process test; what each module
    needs of the machine is written down for the scheduler (tests/rig_chain.py); the default run
    leaves the process and long tests out (`--all`, or a -m expression, chooses otherwise)."""
    for item in items:
        if {"bridge", "procs"} & set(item.fixturenames):
            item.add_marker(pytest.mark.process)
    rigs = {item.module for item in items if item.get_closest_marker("process") is not None}
    rig_chain.write_kinds(
        {item.nodeid.split("::", 1)[0]: _kind_of_module(item.module, rigs) for item in items}
    )
    if config.getoption("--all") or config.getoption("markexpr"):
        return
    kept, left_out = [], []
    for item in items:
        slow = any(item.get_closest_marker(m) for m in ("process", "long", "slow"))
        (left_out if slow else kept).append(item)
    if left_out:
        config.hook.pytest_deselected(items=left_out)
        items[:] = kept


def write_json(path: Path, conf: dict) -> Path:
    path.write_text(json.dumps(conf))
    return path


def wait_until(pred: Callable[[], Any], timeout_s: float = 10.0, step_s: float = 0.05) -> Any:
    """pred()'s first true value, asked every `step_s` until `timeout_s`; else its last one."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(step_s)
    return pred()


def zenoh_configs(tmp_path: Path) -> tuple[Path, Path, int]:
    """A daemon's (peer, listening) and a client's (connecting) Zenoh config files on a free
    port of 127.0.0.1, multicast scouting off: (daemon file, client file, port)."""
    port = find_free_port()
    endpoints = [f"tcp/127.0.0.1:{port}"]
    scouting = {"multicast": {"enabled": False}}
    daemon, client = tmp_path / "zenoh-daemon.json5", tmp_path / "zenoh-client.json5"
    daemon.write_text(
        json.dumps({"mode": "peer", "listen": {"endpoints": endpoints}, "scouting": scouting})
    )
    client.write_text(
        json.dumps({"mode": "client", "connect": {"endpoints": endpoints}, "scouting": scouting})
    )
    return daemon, client, port


@pytest.fixture
def bridge():
    """A python-can-remote bridge on 127.0.0.1; yields its channel URL."""
    port = find_free_port()
    proc = start_bridge(port)
    try:
        yield f"ws://127.0.0.1:{port}/"
    finally:
        stop_bridge(proc)


class OutputWatch:
    """A process's text output read on a thread (so that its pipe never fills up), and an
    event set once a line holding `marker` has come."""

    def __init__(self, proc: subprocess.Popen, marker: str) -> None:
        self.lines: list[str] = []
        self.seen = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(proc, marker), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen, marker: str) -> None:
        for line in proc.stdout:
            self.lines.append(line)
            if marker in line:
                self.seen.set()

    def text(self) -> str:
        return "".join(self.lines)

    def join(self, timeout_s: float = 10.0) -> None:
        self._thread.join(timeout_s)


def holds_wakeup_latency(pid: int) -> int:
    """How many descriptors process `pid` holds on the kernel's PM QoS wake-up latency."""
    from mrrig.loop.realtime import WAKEUP_LATENCY_DEVICE

    held = 0
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            held += os.readlink(fd) == WAKEUP_LATENCY_DEVICE
        except OSError:
            continue
    return held


def stall(pid: int, seconds: float) -> None:
    """Hold process `pid` up for `seconds` (SIGSTOP, SIGCONT): a transport stall, made."""
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def start(args: list[str], **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, *args], cwd=REPO, env=env, **kw)


def stop(proc: subprocess.Popen, timeout_s: float = 15.0) -> int:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


@pytest.fixture
def procs():
    """Processes started by a test; all stopped at its end, whatever happens."""
    started: list[subprocess.Popen] = []

    def _start(args, **kw):
        p = start(args, **kw)
        started.append(p)
        return p

    yield _start
    for p in reversed(started):
        stop(p)


def rig_config(tmp_path: Path, channel: str, model: Path | None, **sections) -> Path:
    """A daemon config for process tests, from configs/rig.toml with overrides."""
    import tomllib

    table = tomllib.loads((REPO / "configs/rig.toml").read_text())
    table["bus"]["channel"] = channel
    if model is not None:
        table["controller"]["model"] = str(model)
    table["telemetry"]["enabled"] = False
    table["recording"]["enabled"] = False
    # the Python reference numerics: loading numba and its cached kernels adds about 1.3 s to
    # each daemon's start (measured), and the process tests are of the daemon's behaviour; the
    # compiled numerics are tested equal to these (tests/test_compiled_path.py) and run by the
    # tests of the shipped configs (the demo, the walkthrough) and CI's smoke plan and fuzz
    table["loop"]["numerics"] = "python"
    for name, values in sections.items():
        table.setdefault(name, {}).update(values)
    path = tmp_path / "rig.toml"
    path.write_text(_toml(table))
    return path


def _toml(table: dict) -> str:
    lines: list[str] = []
    for section, values in table.items():
        lines.append(f"[{section}]")
        for k, v in values.items():
            lines.append(f"{k} = {_value(v)}")
    return "\n".join(lines) + "\n"


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + "}"
    return repr(v)


__all__ = ["REPO", "can", "rig_config", "start", "stop"]
