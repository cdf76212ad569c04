"""The session's GRU (conftest's `sim_gru`, the model of the daemon's GRU process test) predicts
the simulator's force on a matrix it was not trained on.

It is also the first module the scheduler hands out (tests/rig_chain.py `FIRST`): the GRU's
training (100-180 s here) then runs while the workers run the shared modules, not between two
rig modules, where the rig chain waited for it. So do the Dyke twin and its forward model in A
(conftest's `dyke_twin_path`, the models of the twin path's process test)."""

from __future__ import annotations

import json

import pytest

from mrrig.loop.gru import GRUModel
from mrrig.loop.twin_model import load_forward_model
from mrrig.offline.datasets import dataset_b
from mrrig.offline.metrics import error_norm
from mrrig.offline.training import measured_series
from mrrig.offline.training.gru import gru_forces

# the forward Et on the in-between matrix below at most: measured 0.072-0.073 (two noise seeds),
# each 1 s run predicted from the zero state
BOUND = 0.10
pytestmark = pytest.mark.long  # the GRU's training: with --all, as the process test that uses it


def test_the_session_gru_predicts_a_matrix_between_its_training_conditions(sim_gru):
    model = load_forward_model(sim_gru)
    assert isinstance(model, GRUModel)
    fresh = measured_series(
        dataset_b(amplitudes_m=(0.0125,), freqs_hz=(2.5, 4.5), currents_a=(0.3, 0.9, 1.5), seed=7)
    )
    _, measured, predicted = gru_forces(model, fresh)
    et = error_norm(measured, predicted)
    print(f"the session GRU's forward Et on the in-between matrix: {et:.4f}")
    assert et <= BOUND


def test_the_dyke_twin_paths_forward_model_takes_the_rigs_amperes(dyke_twin_path):
    twin, fwd = dyke_twin_path
    assert json.loads(fwd.read_text())["meta"]["command_unit"] == "A"
    assert twin.is_file()
