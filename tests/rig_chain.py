"""The order in which pytest-xdist's two workers take the test modules.

A process module holds the machine alone (conftest's `_Machine`), so the run can be no shorter
than the process modules one after another: the rig chain. Under loadfile each worker took the
next module in turn, and a worker that drew a process module while the other ran one, or a
module that holds the machine shared, waited: measured, the 165 process tests' calls were 1423 s
of a 1747 s run. Here:
- every module is one work unit, as under loadfile (its module fixtures set up once);
- the workers write down what each module needs of the machine as they collect it ("rigs": a
  process module; "beside": pure numerics that run beside a rig at SCHED_IDLE; "shared": a
  module that holds the machine shared) in the file that $MRRIG_RIG_CHAIN names, which the
  controller sets before it starts them (xdist's own xdist_group tag does not reach the node
  ids under pytest 9);
- FIRST's modules go out before any other (a long session training);
- both workers take the shared modules first (they run side by side, and not beside a rig);
  then the first worker takes the rig modules one after another while the second takes the
  modules beside the rigs, then helps with the rig modules (they take the machine's lock in
  turn, as before).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from xdist.scheduler import LoadFileScheduling

RIGS = "rigs"
BESIDE = "beside"
SHARED = "shared"
# the kinds each worker takes, in turn: the first worker is the rig chain's
ORDER_FIRST = (SHARED, RIGS, BESIDE)
ORDER_OTHERS = (SHARED, BESIDE, RIGS)
KINDS_ENV = "MRRIG_RIG_CHAIN"
# handed out before anything else: a module whose session fixture trains long (under a shared
# hold) trains it while the shared modules run, not in the rig chain
FIRST = ("tests/test_session_models.py",)


def write_kinds(kinds: dict[str, str]) -> None:
    """A worker's module kinds ({module path: kind}) into $MRRIG_RIG_CHAIN's file (each worker
    collects every module, so each writes the same; written whole through a temporary file)."""
    path = os.environ.get(KINDS_ENV)
    if not path:
        return
    tmp = Path(f"{path}.{os.getpid()}")
    tmp.write_text(json.dumps(kinds))
    tmp.replace(path)


class RigChainScheduling(LoadFileScheduling):
    """loadfile's work units, taken in the order above."""

    _kinds: dict[str, str] | None = None

    def kind_of(self, scope: str) -> str:
        if self._kinds is None:
            path = os.environ.get(KINDS_ENV, "")
            self._kinds = json.loads(Path(path).read_text()) if os.path.isfile(path) else {}
        return self._kinds.get(scope, SHARED)

    def _assign_work_unit(self, node) -> None:
        order = ORDER_FIRST if node is self.nodes[0] else ORDER_OTHERS
        scope = next(
            (s for s in FIRST if s in self.workqueue),
            next(s for kind in order for s in self.workqueue if self.kind_of(s) == kind),
        )
        work_unit = self.workqueue.pop(scope)
        self.assigned_work.setdefault(node, {})[scope] = work_unit
        collection = self.registered_collections[node]
        node.send_runtest_some(
            [collection.index(nodeid) for nodeid, done in work_unit.items() if not done]
        )
