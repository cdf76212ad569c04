"""`mrrig train` on a characterization matrix (one tidy file, one run per amplitude, frequency
and current) leaves it out run by run and names each run by its condition (issue 42: the
other-test folds of a 36-run matrix were all labelled by segment times such as `0.00-2.00 s`,
which every run shares). Synthetic matrix, a small MLP, few epochs: seconds."""

from __future__ import annotations

import json
import re

import numpy as np

from mrrig.cli.train import main as train_main
from mrrig.offline.datasets import Series
from mrrig.offline.training.crossval import (
    MIN_RUNS,
    SEGMENT_GROUPS,
    leave_out_groups,
    run_folds,
)
from tests.data_files import write_tidy

RATE_HZ = 500.0
# run k of the matrix: (amplitude m, frequency Hz, current A), current innermost
CONDITIONS = [(a, f, i) for a in (0.005, 0.01, 0.02) for f in (1.0, 2.0) for i in (0.0, 1.0)]


def _matrix() -> Series:
    """Two cycles of sine per run; a damper's force: viscous plus the current's yield force."""
    parts = []
    for k, (a, f, i) in enumerate(CONDITIONS):
        t = np.arange(int(2 * RATE_HZ / f)) / RATE_HZ
        w = 2 * np.pi * f
        x, xd, xdd = a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)
        force = 1500.0 * xd + (50.0 + 400.0 * i) * np.tanh(xd / 0.01)
        parts.append((t, x, xd, xdd, np.full(t.size, i), force, np.full(t.size, k)))
    cols = [np.concatenate([p[j] for p in parts]) for j in range(7)]
    return Series(*cols[:6], name="matrix", run_id=cols[6].astype(int))


def test_a_matrix_is_left_out_run_by_run_each_named_by_its_condition():
    s = _matrix()
    assert len(CONDITIONS) >= MIN_RUNS
    group, labels, kind = leave_out_groups(s, np.zeros(len(s), int), ["matrix.csv"])
    assert kind == "run" and np.array_equal(group, s.run_id)
    assert labels[0] == "matrix.csv run 0 (5 mm, 1.00 Hz, command 0 A)"
    assert labels[11] == "matrix.csv run 11 (20 mm, 2.00 Hz, command 1 A)"
    assert len(set(labels)) == len(CONDITIONS)  # no two runs share a name
    fold = run_folds(s, group, len(labels), max_folds=40)
    assert sorted(set(fold.tolist())) == list(range(SEGMENT_GROUPS))
    assert run_folds(s, group, len(labels), max_folds=2).max() == 1


def test_train_reports_et_per_run_of_a_matrix_named_by_its_condition(tmp_path, capsys):
    path = tmp_path / "matrix.csv"
    write_tidy(path, _matrix())
    report = tmp_path / "r.json"
    args = [str(path), "--out", str(tmp_path / "m.json"), "--report", str(report)]
    args += ["--features", "manual", "--no-supervised", "--restarts", "1", "--epochs", "5"]
    assert train_main(args) == 0
    out = capsys.readouterr().out
    print(out)
    assert f"4 folds over the {len(CONDITIONS)} runs of one test" in out
    for k, (a, f, i) in enumerate(CONDITIONS):
        line = f"  {path} run {k} ({a * 1e3:g} mm, {f:.2f} Hz, command {i:g} A): Et "
        assert line in out, line
    assert not re.search(r"segments? \d", out)  # no segment labels
    assert "(one test: its runs are the same test, so this is optimistic too" in out
    per_run = json.loads(report.read_text())["other_tests"]["per_group"]
    assert len(per_run) == len(CONDITIONS) and all(r["n"] > 0 for r in per_run)
