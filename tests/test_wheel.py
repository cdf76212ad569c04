"""A wheel that installs anywhere: built from the working tree, installed into a fresh virtual
environment, `mrrig demo` from a directory outside the checkout finds its DBC, configs and
Zenoh templates as package data (mrrig.resources), nothing from the checkout."""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

from mrrig.resources import resolve, shipped, shipped_dir
from tests.conftest import REPO

# what the wheel is built from: the project's files, not the venv, the caches or the recordings
SOURCES = ("pyproject.toml", "README.md", "mrrig", "firmware_sim", "damper", "configs")


def _env() -> dict[str, str]:
    """No PYTHONPATH, no venv of the caller: the fresh venv's own interpreter decides."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = os.pathsep.join(
        p for p in env.get("PATH", "").split(os.pathsep) if ".venv" not in p
    )
    return env


def _build_wheel(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
            shutil.copytree(path, src / name, symlinks=True, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    dist = tmp_path / "dist"
    # no build isolation: the build backend (setuptools) of this venv, nothing downloaded
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q"]
        + ["-w", str(dist), str(src)],
        check=True,
        env=_env(),
    )
    (wheel,) = dist.glob("mrrig-*.whl")
    return wheel


def _fresh_venv(tmp_path: Path, wheel: Path) -> Path:
    """A new venv with the wheel installed and this venv's site-packages behind its own for
    the dependencies (torch, cantools, zenoh): --no-deps --no-index, no network."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "-q"]
        + ["--no-deps", "--no-index", str(wheel)],
        check=True,
        env=_env(),
    )
    own = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    # a path line only: the editable install's .pth files there are not run from it
    (own / "zz-dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    return venv


def test_a_checkout_finds_its_configs_as_package_data(tmp_path, monkeypatch):
    """The package data is the checkout's configs/ (the one editable copy), and a config
    named configs/... is found from any directory."""
    assert shipped_dir().resolve() == (REPO / "configs").resolve()
    assert shipped("mrrig.dbc").read_bytes() == (REPO / "configs" / "mrrig.dbc").read_bytes()
    monkeypatch.chdir(tmp_path)
    assert resolve("configs/rig.toml") == shipped("rig.toml")
    assert resolve("configs/plans/smoke.toml").is_file()
    # the working directory's own file wins; then the one beside the config file
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "rig.toml").write_text("")
    assert resolve("configs/rig.toml") == Path("configs/rig.toml")
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "lab.dbc").write_text("")
    assert resolve("lab.dbc", lab) == lab / "lab.dbc"
    assert resolve("absent.dbc", lab) == Path("absent.dbc")


def test_a_path_in_a_config_is_found_beside_the_config_file(tmp_path, monkeypatch):
    from mrrig.config import load_config

    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "zenoh.json5").write_text("{}")
    (lab / "rig.toml").write_text(
        '[bus]\ninterface = "virtual"\nchannel = "x"\n'
        '[telemetry]\nzenoh_config = "zenoh.json5"\n'
        '[controller]\nname = "constant"\n'
    )
    monkeypatch.chdir(tmp_path)
    cfg = load_config("lab/rig.toml")
    assert cfg.telemetry.zenoh_config == Path("lab/zenoh.json5")
    # the shipped default where the config names none
    default = load_config(
        "lab/rig.toml", {"telemetry": {"zenoh_config": "configs/zenoh-daemon.json5"}}
    )
    assert default.telemetry.zenoh_config == shipped("zenoh-daemon.json5")


@pytest.mark.process
@pytest.mark.long
def test_the_wheel_runs_the_demo_from_outside_the_checkout(tmp_path, sim_model):
    wheel = _build_wheel(tmp_path)
    venv = _fresh_venv(tmp_path, wheel)
    run = tmp_path / "run"  # under /tmp: no configs/ here, no checkout above
    (run / "models").mkdir(parents=True)
    # the demo's trained model lives in the working directory's models/ (README): the one
    # this test session trained, so that the demo does not train its own for 15 s
    shutil.copy2(sim_model, run / "models" / "sim-forward.json")
    where = subprocess.run(
        [
            str(venv / "bin" / "python"),
            "-c",
            "import mrrig, firmware_sim; from mrrig.rigio.canbus import DEFAULT_DBC_PATH;"
            " print(mrrig.__file__); print(firmware_sim.__file__); print(DEFAULT_DBC_PATH)",
        ],
        cwd=run,
        env=_env(),
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    for path in where:
        assert Path(path).is_relative_to(venv), where
    assert Path(where[2]).read_bytes() == (REPO / "configs" / "mrrig.dbc").read_bytes()
    proc = subprocess.run(
        [str(venv / "bin" / "mrrig"), "demo", "--duration", "5"],
        cwd=run,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert "demo: PASS" in out, out
    (recording,) = (run / "recordings").glob("sim-*.rrd")
    assert recording.stat().st_size > 0
