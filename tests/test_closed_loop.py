"""The closed loop of `bench paper` scores tracking only: a damper that starts as the reference's
did, commanded the reference's own voltage, reproduces the desired force exactly."""

from __future__ import annotations

import numpy as np

from damper.plant import BoucWenParams
from mrrig.loop.controllers import ConstantCurrent
from mrrig.offline.datasets import dataset_a_validation
from mrrig.offline.metrics import error_norm
from mrrig.offline.simulation import closed_loop


def test_the_references_own_command_tracks_it_exactly_from_the_references_initial_state():
    set1 = dataset_a_validation()[:3]  # x = 1 cm sin(2 k pi t), v = 1.5 V throughout
    assert all(np.all(c.current == 1.5) for c in set1)
    x, xd, xdd, f_des = (
        np.stack([getattr(c, a) for c in set1]) for a in ("x", "xd", "xdd", "force")
    )
    params = BoucWenParams.preset("paper-volt")

    def run(u0: float) -> list[float]:
        res = closed_loop(ConstantCurrent(12.0, 1.5), params, 1e-3, x, xd, xdd, f_des, u0=u0)
        assert np.all(res.command == 1.5)
        return [error_norm(d, a) for d, a in zip(res.f_des, res.f_act, strict=True)]

    assert max(run(1.5)) < 1e-12
    # from a coil at 0 V the damper lags behind the reference for tens of ms: no controller
    # could avoid that error, so the benchmark starts it at the reference's 1.5 V
    assert min(run(0.0)) > 0.01
