"""Issue 36, item 4: `mrrig train --features auto` chooses among the kinds of forward model
(the static MLP, the history MLP, the GRU, the Bouc-Wen twin and, issue 43, the grey-box) by
their Et on tests they never saw, within the loop's budget (mrrig/offline/training/kinds.py).
On a few tests of the Labcontrol characterization matrix (A. N. Vargas, Zenodo, DOI
10.5281/zenodo.4445334)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from damper.plant_file import load_plant
from mrrig.cli.train import main as train_main
from mrrig.loop.greybox import GreyBoxModel
from mrrig.loop.model_fit import COST_BUDGET_S
from mrrig.loop.twin_model import load_forward_model
from mrrig.offline.training.kind_choice import KindScore, pick_kind
from mrrig.offline.training.kinds import GREYBOX, GRU, HISTORY_MLP, KIND_NAMES, STATIC_MLP, TWIN

LAB = Path(__file__).resolve().parents[2] / "shared" / "data" / "labcontrol-shaking-table"
# one test at 0 V, one at 3.212 V, one at 0.8712 V
FILES = [LAB / f for f in ("ensaio1.1.csv", "ensaio.A.1.csv", "ensaio1.2.2.csv")]


def _score(name: str, et: float, cost_us: float) -> KindScore:
    return KindScore(name, name, et, [], cost_us, cost_us <= COST_BUDGET_S * 1e6, 1.0)


def test_the_lowest_et_within_the_loops_budget_wins_and_the_reason_says_so():
    scores = [
        _score(STATIC_MLP, 0.30, 30.0),
        _score(HISTORY_MLP, 0.20, 50.0),
        _score(TWIN, 0.10, 400.0),  # the daemon would refuse it
    ]
    best, why = pick_kind(scores, several=True)
    assert best.name == HISTORY_MLP
    assert "the lowest Et on the tests left out (0.2000)" in why
    assert f"next {STATIC_MLP} 0.3000" in why
    assert f"lower but over the budget: {TWIN} 0.1000 (400 us)" in why
    # all over the budget: the lowest of them, said so
    best, why = pick_kind([_score(TWIN, 0.1, 400.0), _score(STATIC_MLP, 0.3, 500.0)], False)
    assert best.name == TWIN and "all over the loop's budget" in why


@pytest.mark.long
@pytest.mark.skipif(not LAB.is_dir(), reason=f"no {LAB}")
def test_features_auto_lists_every_kind_and_writes_the_lowest_et_within_budget(tmp_path, capsys):
    out, report = tmp_path / "model.json", tmp_path / "report.json"
    args = [*map(str, FILES), "--features", "auto", "--out", str(out), "--report", str(report)]
    args += ["--budget-s", "900"]  # every kind tried
    assert train_main([*args, "--epochs", "30", "--restarts", "1", "--no-supervised"]) == 0
    text = capsys.readouterr().out
    print(text)
    assert "kind of model, chosen by the other tests estimate: leave-one-test-out over 3" in text
    rows = {}  # kind: (Et, within the budget)
    for line in text.splitlines():
        m = re.match(r"  Et (\S+)  block hold-out .+\)  work per frame +\d+ us  ([^:]+): ", line)
        if m:
            rows[m[2]] = (float(m[1]), "(over the" not in line)
    assert set(rows) == set(KIND_NAMES) == {STATIC_MLP, HISTORY_MLP, GREYBOX, GRU, TWIN}, text
    within = {k: et for k, (et, ok) in rows.items() if ok}
    chosen = min(within, key=within.get)
    assert f"  chosen: {chosen}, the lowest Et on the tests left out" in text
    doc = json.loads(report.read_text()) if report.is_file() else None
    model = load_forward_model(out)
    if chosen == TWIN:  # the plant file the daemon inverts and firmware_sim runs
        assert load_plant(out).command_unit == "V"
        assert doc is not None and doc["kinds"]["chosen"]["kind"] == TWIN
    elif chosen == GREYBOX:  # the twin and its residual network, a mrrig-greybox/1 file
        assert isinstance(model, GreyBoxModel) and model.plant.command_unit == "V"
        assert doc is not None and doc["kinds"]["chosen"]["kind"] == GREYBOX
    else:
        assert model.meta["kinds"]["chosen"]["kind"] == chosen
