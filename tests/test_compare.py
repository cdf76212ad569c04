"""Issue 42, item 3: `mrrig compare`, the paper's controllers on the lab's damper in one
command: the plan it writes, its table, and a run on the simulated rig."""

from __future__ import annotations

import math
import re
import subprocess
import sys

import pytest

from mrrig.compare import CompareError, Comparison, Row, plan_text, table
from mrrig.plans.plan import load_plan
from tests.conftest import REPO


def test_the_plan_has_a_step_per_controller_on_one_stroke_and_force_with_the_gains(tmp_path):
    c = Comparison(
        controllers=["network_inversion", "continuous_state", "heaviside"],
        settings={
            "continuous_state": {"gain": 0.004, "b": 0.8},
            "heaviside": {"on_current_a": 1.5},
        },  # fmt: skip
        i_max_a=2.0,
    )
    path = tmp_path / "c.toml"
    path.write_text(plan_text(c, rig="rig1"))
    plan = load_plan(path)
    assert plan.rig == "rig1"
    names = [s.name for s in plan.steps]
    assert names == ["passive off (0 A)", "passive on (2 A)", "heaviside", "continuous_state",
                     "network_inversion"]  # fmt: skip
    cs = plan.steps[3].controller
    assert (cs.name, cs.gain, cs.b) == ("continuous_state", 0.004, 0.8)
    assert plan.steps[2].controller.on_current_a == 1.5
    assert plan.steps[1].controller.current_a == 2.0
    assert len({(s.actuator, s.reference) for s in plan.steps}) == 1  # one stroke and force


@pytest.mark.parametrize(
    ("c", "message"),
    [
        (Comparison(controllers=["pid"]), "controller 'pid': not one of the paper's"),
        (Comparison(controllers=["rnn"]), "controller rnn: needs its own inverse model"),
        (Comparison(duration_s=math.inf), "duration: inf s must be in (0, 3600]"),
    ],
)
def test_a_comparison_that_cannot_be_made_is_one_line(c, message):
    with pytest.raises(CompareError, match=re.escape(message)):
        plan_text(c)


def test_the_table_puts_et_beside_the_best_and_the_better_passive():
    rs = [
        Row("passive off (0 A)", "constant", "0 A", 0.8, 0.0, 300.0, "passed"),
        Row("passive on (2 A)", "constant", "2 A", 0.4, 2.0, 300.0, "passed"),
        Row("heaviside", "heaviside", "on at i_max", 0.2, 2.0, 300.0, "passed"),
        Row("network_inversion", "network_inversion", "m.json", 0.02, 1.5, 300.0, "passed"),
        Row("rnn", "rnn", "r.json", math.nan, math.nan, math.nan, "aborted"),
    ]
    lines = table(rs).splitlines()
    assert re.search(r"^heaviside .* 0\.2000 +10\.00 +0\.50 ", lines[4])
    assert re.search(r"^network_inversion .* 0\.0200 +1\.00 +0\.05 ", lines[5])
    assert re.search(r"^rnn .* - +- +- +- +- aborted$", lines[6])


@pytest.mark.process
@pytest.mark.long
def test_compare_on_the_simulated_rig_prints_the_controllers_et_side_by_side(tmp_path):
    plan = tmp_path / "compare.toml"
    done = subprocess.run(
        [sys.executable, "-m", "mrrig", "compare", "--sim", "--duration", "2", "--settle",
         "0.5", "--controllers", "continuous_state,network_inversion", "--gain", "0.01",
         "--plan-out", str(plan), "--catalog", str(tmp_path / "c.sqlite")],
        cwd=REPO, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    out = done.stdout
    assert done.returncode == 0, out[-3000:] + done.stderr[-3000:]
    side = out[out.index("the controllers side by side on rig") :].splitlines()
    print("\n".join(side))
    rows = {line.split("  ")[0]: line for line in side[3:]}
    assert set(rows) == {"passive off (0 A)", "passive on (2 A)", "continuous_state",
                         "network_inversion"}, side  # fmt: skip
    assert "G 0.01 A/N, B 1" in rows["continuous_state"]
    ets = {k: float(re.search(r"\s(\d\.\d{4})\s", v)[1]) for k, v in rows.items()}
    assert ets["network_inversion"] < ets["continuous_state"] < ets["passive off (0 A)"]
    assert load_plan(plan).steps[2].controller.gain == 0.01
