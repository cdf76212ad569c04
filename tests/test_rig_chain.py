"""The order in which the two workers take the modules (tests/rig_chain.py), on a small suite
of its own run by pytest-xdist with two real workers: modules of the three kinds that log when
each test starts and on which worker."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap

from tests.conftest import REPO

CONFTEST = f"""
import os, sys, tempfile
sys.path.insert(0, {str(REPO)!r})
from tests import rig_chain

def pytest_configure(config):
    if not hasattr(config, "workerinput"):
        fd, path = tempfile.mkstemp(suffix=".json")
        os.close(fd)
        os.environ[rig_chain.KINDS_ENV] = path

def pytest_collection_modifyitems(config, items):
    def kind(path):
        name = path.rsplit("/", 1)[-1]
        return "rigs" if "_rig_" in name else "beside" if "_beside_" in name else "shared"
    paths = {{item.nodeid.split("::", 1)[0] for item in items}}
    rig_chain.write_kinds({{p: kind(p) for p in paths}})

def pytest_xdist_make_scheduler(config, log):
    return rig_chain.RigChainScheduling(config, log)
"""

MODULE = """
import json, os, time
def _log(name):
    with open(os.environ["CHAIN_LOG"], "a") as f:
        f.write(json.dumps([time.monotonic(), os.environ["PYTEST_XDIST_WORKER"], name]) + "\\n")
"""


def _module(name: str, tests: int, seconds: float) -> str:
    body = MODULE
    for k in range(tests):
        body += f"def test_{k}():\n    _log({name!r})\n    time.sleep({seconds})\n"
    return body


def test_shared_modules_go_first_then_the_rig_modules_on_one_worker_beside_the_others(tmp_path):
    modules = {
        "test_session_models.py": (1, 0.3),  # rig_chain.FIRST
        "test_a_shared.py": (3, 0.1),
        "test_b_shared.py": (2, 0.1),
        "test_c_shared.py": (1, 0.1),
        "test_1_rig_x.py": (2, 0.2),
        "test_2_rig_y.py": (2, 0.2),
        "test_3_rig_z.py": (1, 0.2),
        "test_4_beside_p.py": (3, 0.6),
        "test_5_beside_q.py": (3, 0.6),
    }
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "conftest.py").write_text(textwrap.dedent(CONFTEST))
    for name, (n, s) in modules.items():
        (tests / name).write_text(_module(name, n, s))
    log = tmp_path / "chain.log"
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadfile", "-p",
         "no:cacheprovider", "--rootdir", str(tmp_path), "-c", "/dev/null", "tests"],
        cwd=tmp_path, env={**__import__("os").environ, "CHAIN_LOG": str(log)},
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    starts = [json.loads(line) for line in log.read_text().splitlines()]
    order = sorted(starts)
    workers = {w for _, w, _ in order}
    # rig_chain.FIRST: the first module of one of the workers
    assert "test_session_models.py" in {next(n for _, w, n in order if w == x) for x in workers}
    # on each worker, no shared module after a rig or beside module
    for worker in workers:
        kinds = [
            "_rig_" not in name and "_beside_" not in name for _, w, name in order if w == worker
        ]
        assert kinds == sorted(kinds, reverse=True), order
    rig = [(t, w) for t, w, name in order if "_rig_" in name]
    beside = [(t, w) for t, w, name in order if "_beside_" in name]
    # the rig modules one after another on one worker, which takes a module beside them only
    # once they are done, while the other worker runs the modules beside them
    (chain,) = {w for _, w in rig}
    assert max(t for t, _ in rig) < min((t for t, w in beside if w == chain), default=math.inf)
    assert min(t for t, w in beside if w != chain) < max(t for t, _ in rig), order
