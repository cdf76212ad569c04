"""The walls of the house (pyproject.toml's `[tool.importlinter]` contracts): `mrrig` never
imports `firmware_sim`; the damper's physics and the numerics never import I/O; the loop never
imports torch, Zenoh or Rerun; the daemon's modules are layered by job (`mrrig run` over the
daemon over its independent parts: the frame's path, control requests, the sidecar's supervision,
shutdown...); the loop and the rig's I/O never import the offline work or the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_import_contracts_hold() -> None:
    lint_imports = Path(sys.executable).parent / "lint-imports"
    done = subprocess.run(
        [str(lint_imports), "--no-cache"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 broken" in done.stdout, done.stdout
