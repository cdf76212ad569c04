"""Every config shipped in configs/ loads as the tool it is for reads it, rig profile included:
a check made only at start-up (the rig profile's period against the DBC's cycle time) once
stopped the SocketCAN VM check of CI, whose daemon config no test had started."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from damper.plant import BoucWenParams
from damper.plant_file import Plant, save_plant
from firmware_sim.config import load_config as load_sim_config
from mrrig.config import load_config
from mrrig.rigio.canbus.profile import load_profile

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (REPO / "configs").rglob("*.toml") if "plans" not in p.parts)


def _kind(path: Path) -> str:
    tables = set(tomllib.loads(path.read_text()))
    if "commands" in tables or path.name.startswith("sim") or path.stem.endswith("-sim"):
        return "sim"
    if "rig" in tables and "loop" in tables:
        return "daemon"
    return "other"  # characterize's matrix, train's config: their own tests load them


def test_the_shipped_configs_are_found():
    kinds = [_kind(p) for p in CONFIGS]
    assert kinds.count("daemon") >= 5 and kinds.count("sim") >= 5, list(
        zip(CONFIGS, kinds, strict=True)
    )


@pytest.mark.parametrize("path", [p for p in CONFIGS if _kind(p) == "daemon"], ids=lambda p: p.name)
def test_a_shipped_daemon_config_loads_with_its_rig_profile(path, monkeypatch):
    monkeypatch.chdir(REPO)
    cfg = load_config(path)
    load_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, str(path))


@pytest.mark.parametrize("path", [p for p in CONFIGS if _kind(p) == "sim"], ids=lambda p: p.name)
def test_a_shipped_simulator_config_loads_with_its_rig_profile(path, monkeypatch, tmp_path):
    # a [plant] file is what `mrrig identify` writes (README, "A twin of a measured damper"):
    # a clean checkout has none, so the run's directory gets one, of the paper's damper
    plant = tomllib.loads(path.read_text()).get("plant", {}).get("file")
    if plant is not None:
        (tmp_path / plant).parent.mkdir(parents=True)
        save_plant(Plant(BoucWenParams.preset("paper-volt")), tmp_path / plant)
    monkeypatch.chdir(tmp_path)
    cfg = load_sim_config(path)
    load_profile(cfg.can.dbc, cfg.can.signals, None, str(path))
