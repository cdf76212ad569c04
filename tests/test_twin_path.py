"""Issue 36, item 5: from a measured damper's data to a tracking run, as the README's command
sequence runs it. `mrrig identify` on the Dyke file gives the twin, `mrrig train` on the same
measured data (not on the twin) the forward model, whose command in V is mapped to the rig's
A (`mrrig identify --map-model`, 1 V per A as the twin's `[plant] command_per_a`), and
`mrrig demo` runs firmware_sim with the twin and the daemon tracking the twin's own force for
a current profile (configs/dyke-twin.toml, configs/sim-dyke-twin.toml)."""

from __future__ import annotations

import json
import tomllib

import pytest

from tests.conftest import REPO, _mrrig_ok, _toml, zenoh_configs
from tests.stall_proof import demo_files, explain

DURATION_S = 20.0


@pytest.mark.process
@pytest.mark.long
def test_the_dyke_twin_tracked_by_a_model_of_the_measured_data_et_at_most_0_03(
    tmp_path, dyke_twin_path
):
    twin, fwd = dyke_twin_path  # conftest's: `mrrig identify`, `train`, `identify --map-model`
    assert json.loads(fwd.read_text())["meta"]["command_unit"] == "A"

    zdaemon, zclient, _ = zenoh_configs(tmp_path)
    rig = tomllib.loads((REPO / "configs/dyke-twin.toml").read_text())
    rig["rig"]["name"] = "twin-test"
    rig["controller"]["model"] = str(fwd)
    rig["reference"]["preset"] = str(twin)
    rig["telemetry"].update(enabled=True, zenoh_config=str(zdaemon))
    rig["recording"]["enabled"] = False
    (tmp_path / "rig.toml").write_text(_toml(rig))
    sim = (REPO / "configs/sim-dyke-twin.toml").read_text()
    sim = sim.replace('file = "models/dyke-twin.json"', f'file = "{twin}"')
    assert str(twin) in sim
    (tmp_path / "sim.toml").write_text(sim)
    out = _mrrig_ok(
        "demo",
        *("--config", str(tmp_path / "rig.toml"), "--sim-config", str(tmp_path / "sim.toml")),
        *("--model", str(fwd), "--zenoh-config", str(zclient), "--duration", str(DURATION_S)),
        timeout_s=300,
    )
    summary, stats = demo_files(out)
    print(f"answered Et {summary['et_answered']:.4f}, faults {len(summary['faults'])}")
    explain(stats, summary["faults"], summary["clock_t0_s"], summary["kernel_stalls"])
    assert summary["et_answered"] <= 0.03
