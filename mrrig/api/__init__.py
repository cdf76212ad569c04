"""mrrig from Python (Jupyter, scripts): recordings, the run catalog and live rigs.

- `Recording(path)`: a run's `.rrd` (or its `.parquet`/`.mf4` export): `samples` (numpy
  structured array, SI units: `t` s, `x` m, `xd` m/s, `f_meas` N, `i_cmd` A, ...), `events`,
  `summary`, `identity`, `to_pandas()` (columns named with their units, and `utc`).
- `runs(**filters)`: the run catalog (`mrrig runs`) as a pandas DataFrame (`run_records`:
  the same as `RunRecord`s), from `default_catalog()` ($MRRIG_CATALOG, else
  recordings/catalog.sqlite) unless given one; `get_run(id)`, `check_recording(run)`,
  `compare_figure(a, b, png)`, `sync_runs(src, dst)`, `unregistered_recordings()`,
  `register_recording(rrd)` (a run from the identity its recording carries),
  `replay_journals()` (runs journalled while their catalog could not take them)
  (`mrrig.api.catalog`).
- `register_run(rig, started_utc, ...)`: one run into the catalog (what a plan step,
  characterize and validate call; the daemon's sidecar registers its own runs).
- `run_hil(rig, law=..., compensation=..., duration_s=...)`: one hybrid-simulation run (a
  model's scenario or a stroke playback) on a rig whose daemon runs `[hil]`: set, armed,
  followed to its end, disarmed and judged against the all-numerical reference (a
  `HilResult`: `tracking` J1-J3, `errors`, `figures`, `end` the rig's status; a refusal is a
  `HilRunError`); the rig's HIL status is `Rig(name).status()["hil"]`; `hil_tracking(samples)`
  J1-J3 of any run's samples (a `Recording`'s, a `Telemetry`'s); `load_scenario(path)` a
  scenario file or stroke CSV, `run_reference(scenario)` its all-numerical run
  (`mrrig.api.hil`, `mrrig.hil`).
- `Rig(name)`: a running daemon over Zenoh: `status()`, `arm()`, `disarm()`, `reset()`,
  `stream_force(...)`, `telemetry(...)` (a `Telemetry`: its `samples`, `to_pandas()` with
  `utc`); a refused request raises `RigError`. Use it as a context manager (`with
  Rig("rig1") as rig:`) or call `close()`: it holds one Zenoh session, and an open session keeps the
  interpreter from exiting (a finalizer closes it at exit as a last resort).

The CLI (`mrrig status`, `arm`, ..., `send-force`, `runs`) is built on these; they are built
on `mrrig.rigio.client`, `mrrig.rigio.force_stream`, `mrrig.catalog` and `mrrig.export`: no
second client.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from mrrig.api.catalog import (
    check_recording,
    compare_figure,
    default_catalog,
    get_run,
    register_recording,
    register_run,
    replay_journals,
    run_records,
    runs,
    sync_runs,
    unregistered_recordings,
)

if TYPE_CHECKING:
    from mrrig.api.hil import HilResult, HilRunError, hil_tracking, run_hil
    from mrrig.api.live import Recording, Rig, RigError, Telemetry
    from mrrig.catalog import RunRecord
    from mrrig.hil.reference import run_reference
    from mrrig.hil.scenario import load_scenario

__all__ = [
    "HilResult",
    "HilRunError",
    "Recording",
    "Rig",
    "RigError",
    "RunRecord",
    "Telemetry",
    "check_recording",
    "compare_figure",
    "default_catalog",
    "get_run",
    "hil_tracking",
    "load_scenario",
    "register_recording",
    "register_run",
    "replay_journals",
    "run_records",
    "run_hil",
    "run_reference",
    "runs",
    "sync_runs",
    "unregistered_recordings",
]
# imported on first use: `mrrig runs` (the catalog alone) starts without numpy
_LAZY = {
    "Recording": "mrrig.api.live",
    "Rig": "mrrig.api.live",
    "RigError": "mrrig.api.live",
    "Telemetry": "mrrig.api.live",
    "RunRecord": "mrrig.catalog",
    "HilResult": "mrrig.api.hil",
    "HilRunError": "mrrig.api.hil",
    "hil_tracking": "mrrig.api.hil",
    "run_hil": "mrrig.api.hil",
    "load_scenario": "mrrig.hil.scenario",
    "run_reference": "mrrig.hil.reference",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mrrig.api' has no attribute {name!r}")


def __dir__() -> list[str]:
    # what the module documents, the lazy names too (a module's own dir() lists neither
    # those nor leaves out its imports)
    return sorted(__all__)
