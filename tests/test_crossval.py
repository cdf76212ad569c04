"""A model judged on tests it never saw (issue 36, item 1): leave-one-test-out, the search's
folds over whole tests, `mrrig train --validate`, Et per test in the report and in
`mrrig evaluate`. On the Labcontrol characterization matrix (A. N. Vargas, Zenodo, DOI
10.5281/zenodo.4445334, MIT licence): a few of its 38 tests, few epochs."""

import json
from pathlib import Path

import numpy as np
import pytest

from mrrig.cli.train import main as train_main
from mrrig.cli.train_report import format_other_tests
from mrrig.offline.datasets import DataError
from mrrig.offline.evaluate import main as evaluate_main
from mrrig.offline.metrics import error_norm
from mrrig.offline.training import features, train_forward
from mrrig.offline.training.crossval import (
    SEGMENT_GROUPS,
    cross_validate,
    fold_of_groups,
    subset,
)
from mrrig.offline.training.report import EtSum, predict
from mrrig.offline.training.select import FOLDS, Candidate, _folds
from mrrig.offline.training.stream import sample_tests, training_subset

LAB = Path(__file__).resolve().parents[2] / "shared" / "data" / "labcontrol-shaking-table"
pytestmark = pytest.mark.skipif(not LAB.is_dir(), reason=f"no {LAB}")
# two tests at 0 V, two at 3.212 V, one at 0.8712 V
FILES = [LAB / f for f in ("ensaio1.1.csv", "ensaio2.1.csv", "ensaio.A.1.csv", "ensaio.A.2.csv")]
OPTIONS = dict(
    current_input="commanded",
    lag_tau_s=1.0,
    history_samples=0,
    history_signals=("x", "xd"),
    history_stride=1,
    hidden=10,
    split="blocks",
    holdout_fraction=0.15,
)


@pytest.fixture(scope="module")
def lab():
    series, report = training_subset(FILES)
    return series, sample_tests(report), [t["file"] for t in report["tests"]]


def test_each_file_is_a_test_in_the_order_of_the_series(lab):
    series, tests, names = lab
    assert names == [str(f) for f in FILES]
    assert tests.size == len(series)
    assert np.all(np.diff(tests) >= 0) and set(tests.tolist()) == {0, 1, 2, 3}
    # each test's samples are its file's: the command is the file's constant voltage
    assert np.ptp(series.current[tests == 0]) == 0.0 and series.current[tests == 2][0] > 3.0


def test_leave_one_test_out_scores_each_test_with_a_model_that_never_saw_it(lab):
    series, tests, names = lab
    cv = cross_validate(series, tests, names, OPTIONS, seed=0, max_epochs=40)
    assert cv["kind"] == "test" and cv["folds"] == 4 and not cv["optimistic"]
    assert "leave-one-test-out" in cv["method"]
    # the third test's figure is that of a model trained on the three others, by itself
    other = subset(series, tests != 2)
    fit = {k: OPTIONS[k] for k in ("split", "holdout_fraction", "history_stride", "hidden")}
    feat = {k: v for k, v in OPTIONS.items() if k not in fit or k == "history_stride"}
    model, _ = train_forward(
        other,
        seed=0,
        max_epochs=40,
        current_input="commanded",
        lag_tau_s=1.0,
        history_samples=0,
        history_signals=("x", "xd"),
        **fit,
    )
    X, y = features(subset(series, tests == 2), **feat)
    assert cv["per_group"][2]["et"] == pytest.approx(error_norm(y, predict(model, X)), rel=1e-12)
    assert cv["per_group"][2]["n"] == y.size
    # overall: eqs 41-43 over every left-out row together
    assert cv["overall"]["n"] == sum(g["n"] for g in cv["per_group"])
    print("\n".join(format_other_tests(cv)))


def test_k_folds_over_many_tests_leave_each_test_out_once():
    fold = fold_of_groups(50, 40, seed=3)
    assert sorted(set(fold.tolist())) == list(range(40))
    assert np.bincount(fold).min() == 1 and np.bincount(fold).max() == 2
    assert fold_of_groups(7, 40).tolist() == list(range(7))  # one test per fold


def test_one_test_is_cut_into_segments_and_called_optimistic(lab):
    series, tests, names = lab
    one = subset(series, tests == 0)
    cv = cross_validate(one, np.zeros(len(one), int), names[:1], OPTIONS, max_epochs=20)
    assert cv["kind"] == "segment" and cv["optimistic"] and cv["folds"] == SEGMENT_GROUPS
    assert all(g["n"] > 0 for g in cv["per_group"])
    assert "optimistic" in "\n".join(format_other_tests(cv))


def test_the_search_folds_are_whole_tests_when_several_are_given(lab):
    series, tests, _ = lab
    fold = _folds(series, [Candidate()], 0.15, tests, seed=0)
    for k in range(4):
        in_search = fold[tests == k]
        assert len(set(in_search[in_search >= 0].tolist())) == 1  # a test is in one fold
    assert sorted(set(fold[fold >= 0].tolist())) == list(range(min(FOLDS, 4)))
    assert (fold == -1).any()  # the block hold-out of each run stays out of the search


def test_et_sums_piece_by_piece_equal_the_error_norm_of_all_rows():
    rng = np.random.default_rng(1)
    y = rng.normal(100.0, 30.0, 1000)
    f = y + rng.normal(0.0, 5.0, 1000)
    s = EtSum()
    for a, b in ((0, 10), (10, 500), (500, 1000)):
        s.add(y[a:b], f[a:b])
    assert s.numbers()["et"] == pytest.approx(error_norm(y, f), rel=1e-12)


def test_train_reports_et_per_test_and_keeps_validation_tests_out(tmp_path, capsys):
    model, report = tmp_path / "m.json", tmp_path / "r.json"
    held = LAB / "ensaio3.1.csv"
    args = [*map(str, FILES[:3]), "--validate", str(held), "--out", str(model)]
    args += ["--report", str(report), "--no-supervised", "--restarts", "1", "--epochs", "30"]
    args += ["--features", "manual"]
    assert train_main(args) == 0
    out = capsys.readouterr().out
    print(out)
    assert "[optimistic: the end of each run of the tests trained on" in out
    assert "other-test estimate, leave-one-test-out (3 folds)" in out
    for f in FILES[:3]:
        assert f"  {f}: Et " in out
    assert "overall Et" in out and "validation tests (--validate" in out
    r = json.loads(report.read_text())
    m = json.loads(model.read_text())
    assert str(held) not in m["meta"]["data_files"] and m["meta"]["validate"]["files"] == [
        str(held)
    ]
    assert r["validate"]["per_test"][0]["file"] == str(held)
    # the same model on the same test in `mrrig evaluate`: the same Et
    e = tmp_path / "e.json"
    assert evaluate_main([str(model), str(held), "--json", str(e)]) == 0
    ev = json.loads(e.read_text())
    assert ev["per_test"][0]["et"] == r["validate"]["per_test"][0]["et"]
    assert ev["forward"]["et"] == m["metrics"]["validate_et"]
    assert "forward Et per test (1; overall" in capsys.readouterr().out


def test_a_validation_test_that_is_also_trained_on_is_refused_with_one_line(tmp_path):
    args = [str(FILES[0]), str(FILES[1]), "--validate", str(FILES[1]), "--out", str(tmp_path / "m")]
    with pytest.raises(DataError, match=r"--validate .*ensaio2.1.csv: also given as training"):
        train_main(args)


def test_evaluate_prints_et_per_test_and_the_pooled_overall(tmp_path, capsys, lab):
    model = tmp_path / "m.json"
    args = [str(FILES[0]), str(FILES[2]), "--out", str(model), "--no-supervised"]
    args += ["--features", "manual"]
    assert train_main([*args, "--restarts", "1", "--epochs", "20", "--cv-folds", "0"]) == 0
    assert "other-test estimate" not in capsys.readouterr().out  # --cv-folds 0: none
    e = tmp_path / "e.json"
    others = [FILES[1], FILES[3]]
    assert evaluate_main([str(model), *map(str, others), "--json", str(e)]) == 0
    out = capsys.readouterr().out
    ev = json.loads(e.read_text())
    assert [t["file"] for t in ev["per_test"]] == [str(f) for f in others]
    assert all(f"  {f}: Et " in out for f in others)
    assert sum(t["n"] for t in ev["per_test"]) == ev["n"]
