#!/usr/bin/env bash
# Create (or update) the project's virtual environment in .venv: torch 2.13.0 (CPU) first, so
# that the project's torch range does not pull a multi-GB CUDA build, then mrrig with its dev
# extra. Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv with $($PY --version)"
    "$PY" -m venv .venv
fi
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    echo "bootstrap: installing torch==2.13.0 (CPU)"
    .venv/bin/pip install --quiet --disable-pip-version-check torch==2.13.0
fi
stamp=.venv/.mrrig-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "bootstrap: installing mrrig and its dependencies"
    .venv/bin/pip install --quiet --disable-pip-version-check -e '.[dev]'
    touch "$stamp"
    # the 2 GB just written go to disk now, not during the next command's 500 Hz run: the
    # demo right after a fresh install stalled 15-30 ms on the writeback and failed
    sync
fi
# the loop's compiled numerics (numba, mrrig/loop/compiled.py) compiled now into __pycache__,
# so that a daemon's start loads them (about 0.5 s) instead of compiling (about 10 s); a second
# run only loads them
echo "bootstrap: compiling the loop's numerics (numba, cached)"
.venv/bin/python -c "from mrrig.loop import compiled, compiled_hil; compiled.warm(); compiled_hil.warm()"
# the rerun CLI asks about analytics once; never in CI or at a rig
.venv/bin/rerun analytics disable >/dev/null 2>&1 || true
echo "bootstrap: .venv ready"
