"""Issue 43, item 1: the kind of model is chosen by the other-test estimate, by default, for every
kind of data: leave one test out where there are tests, on one test its segments of different
character (never their neighbours), within a time budget; the report names the estimate and
puts the block hold-out beside it (mrrig/offline/training/kinds.py, crossval.py).

Two toy kinds on synthetic data make the difference: "memo" remembers each command level's
force offset (perfect on the end of a run it trained on, wrong on a level it never saw), "line"
is one straight line in velocity and command (fair everywhere). The block hold-out prefers memo,
the other-test estimate line. Pure numerics, seconds."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from mrrig.cli.train import main as train_main
from mrrig.cli.train_report import format_kinds
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.offline.datasets import Series, dataset_b
from mrrig.offline.training.crossval import (
    GUARD_FRACTION,
    SEGMENTS,
    character_groups,
    guard,
    leave_out_groups,
)
from mrrig.offline.training.fit import stretch_split
from mrrig.offline.training.kind_choice import choose_kind
from mrrig.offline.training.kinds import ModelKind, block_holdout, mlp_kind
from mrrig.offline.training.select import Candidate
from tests.data_files import write_tidy

HOLDOUT = 0.05  # of the 16 s one-test run: the end of its last piece
RATE_HZ = 200.0


def _sine(n: int, amp: float, freq: float, t0: float = 0.0) -> tuple[np.ndarray, ...]:
    t = t0 + np.arange(n) / RATE_HZ
    w = 2 * np.pi * freq
    return t, amp * np.sin(w * t), amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t)


def _series(pieces: list[tuple[float, float, float, float]], one_run: bool) -> Series:
    """Pieces of (amplitude m, frequency Hz, command level, force offset N), 2 s each: one run
    (one test) or a run per piece; force = 2000 * xd + offset of the piece."""
    parts = [
        (*_sine(400, a, f, 2.0 * k if one_run else 0.0), lvl, off)
        for k, (a, f, lvl, off) in enumerate(pieces)
    ]
    cat = [np.concatenate([p[j] for p in parts]) for j in range(4)]
    level = np.concatenate([np.full(400, p[4]) for p in parts])
    offset = np.concatenate([np.full(400, p[5]) for p in parts])
    run = np.zeros(400 * len(pieces), int) if one_run else np.repeat(np.arange(len(pieces)), 400)
    t, x, xd, xdd = cat
    return Series(t, x, xd, xdd, level, 2000.0 * xd + offset, run)


def _trained_rows(series: Series) -> np.ndarray:
    """A toy fit keeps the block hold-out out, as the real kinds do."""
    every = np.arange(len(series))
    return every[~block_holdout(series, every, HOLDOUT)]


def _memo() -> ModelKind:
    def fit(s: Series) -> dict[float, float]:
        r = _trained_rows(s)
        resid = s.force[r] - 2000.0 * s.xd[r]
        return {float(c): float(resid[s.current[r] == c].mean()) for c in np.unique(s.current[r])}

    def forces(m: dict[float, float], s: Series) -> tuple[np.ndarray, ...]:
        levels = np.array(sorted(m))
        near = levels[np.abs(s.current[:, None] - levels[None, :]).argmin(axis=1)]
        f = 2000.0 * s.xd + np.array([m[float(c)] for c in near])
        return np.arange(len(s)), s.force, f

    return _kind("memo", fit, forces)


def _line() -> ModelKind:
    def fit(s: Series) -> np.ndarray:
        r = _trained_rows(s)
        a = np.column_stack([s.xd[r], s.current[r], np.ones(r.size)])
        return np.linalg.lstsq(a, s.force[r], rcond=None)[0]

    def forces(w: np.ndarray, s: Series) -> tuple[np.ndarray, ...]:
        f = np.column_stack([s.xd, s.current, np.ones(len(s))]) @ w
        return np.arange(len(s)), s.force, f

    return _kind("line", fit, forces)


def _kind(name, fit, forces) -> ModelKind:
    constant = make_controller("constant", ControllerSettings(1.0, dt_s=0.002))
    return ModelKind(name, f"toy {name}", fit, forces, lambda _m: constant)


# offsets that the command level does not explain (as the Labcontrol tests' force offsets)
OFFSETS = (40.0, -35.0, 25.0, -45.0, 50.0, -30.0, 35.0, -40.0)
PIECES = [
    (amp, freq, level, off)
    for (amp, freq, level), off in zip(
        [(0.01, 1.0, 0.0), (0.02, 1.5, 0.5), (0.01, 2.0, 1.0), (0.03, 1.0, 1.5)]
        + [(0.02, 2.5, 2.0), (0.01, 3.0, 2.5), (0.03, 2.0, 3.0), (0.02, 1.0, 3.5)],
        OFFSETS,
        strict=True,
    )
]


def test_several_tests_the_kind_is_chosen_by_leaving_tests_out_not_by_the_block_hold_out():
    s = _series(PIECES, one_run=False)
    tests = np.repeat(np.arange(len(PIECES)), 400)
    names = [f"test{k}.csv" for k in range(len(PIECES))]
    best, rep = choose_kind(s, tests, names, [_memo(), _line()], holdout_fraction=HOLDOUT)
    k = {r["kind"]: r for r in rep["kinds"]}
    # memo is the better on the block hold-out, line on the tests left out
    assert k["memo"]["block_et"] < k["line"]["block_et"]
    assert k["line"]["et"] < k["memo"]["et"]
    assert best.name == "line" and rep["chosen"]["kind"] == "line"
    assert rep["block_holdout_would_choose"] == "memo"
    assert rep["estimate"] == "other tests" and "leave-one-test-out over 8 tests" in rep["method"]
    text = "\n".join(format_kinds(rep))
    print(text)
    assert "chosen by the other tests estimate" in text
    assert "(the block hold-out would have chosen memo)" in text
    assert "x optimistic" in text


def test_one_test_the_kind_is_chosen_on_segments_of_different_character():
    s = _series(PIECES, one_run=True)
    names = ["long.csv"]
    best, rep = choose_kind(
        s, np.zeros(len(s), int), names, [_memo(), _line()], holdout_fraction=HOLDOUT
    )
    k = {r["kind"]: r for r in rep["kinds"]}
    assert k["memo"]["block_et"] < k["line"]["block_et"]  # the end of the run: a level it saw
    assert k["line"]["et"] < k["memo"]["et"]
    assert best.name == "line" and rep["block_holdout_would_choose"] == "memo"
    assert rep["estimate"] == "segments of different character"
    text = "\n".join(format_kinds(rep))
    print(text)
    assert "chosen by the segments of different character estimate" in text
    assert "never" not in text or "neighbours" in text


def test_segments_are_grouped_by_character_and_their_neighbours_are_not_trained_on():
    # amplitude alternates small / large: a group holds like segments, not neighbours
    char = np.array([[a, 6.0, 1.0] for a in (1.0, 5.0, 1.1, 5.2, 0.9, 4.8, 1.2, 5.1)])
    g = character_groups(char, 4)
    small, large = set(g[[0, 2, 4, 6]].tolist()), set(g[[1, 3, 5, 7]].tolist())
    assert not small & large and np.bincount(g).tolist() == [2, 2, 2, 2]
    # the one-test groups of the series: SEGMENTS segments, each group two like ones
    s = _series(PIECES, one_run=True)
    group, labels, kind = leave_out_groups(s, np.zeros(len(s), int), ["long.csv"])
    assert kind == "segment" and len(labels) == 4 and "amplitude" in labels[0]
    assert np.bincount(group).tolist() == [len(s) // 4] * 4
    # guard: the left-out rows widened on each side
    out = np.zeros(100, dtype=bool)
    out[40:50] = True
    wide = guard(out, 5)
    assert np.flatnonzero(wide).tolist() == list(range(35, 55))
    assert guard(out, 0) is out and GUARD_FRACTION > 0 and SEGMENTS == 8


def test_a_kind_whose_folds_would_not_end_in_the_budget_is_not_tried_and_says_why():
    s = _series(PIECES, one_run=False)
    tests = np.repeat(np.arange(len(PIECES)), 400)
    names = [f"test{k}.csv" for k in range(len(PIECES))]
    slow = _line()
    slow = ModelKind(
        "slow", "toy slow", slow.fit, slow.forces, slow.controller, None, min_fold_s=1e6
    )
    best, rep = choose_kind(
        s, tests, names, [_line(), slow], holdout_fraction=HOLDOUT, deadline=time.perf_counter()
    )
    assert best.name == "line"  # the first kind is scored whatever the budget
    assert "slow" in rep["not_tried"] and "time budget" in rep["not_tried"]["slow"]
    assert "  not tried: slow (not within the time budget" in "\n".join(format_kinds(rep))


@pytest.fixture
def constant_command_matrix(tmp_path):
    """Three tests (files), the command held in each (the characterization matrix's kind of
    data, where the default used to be the manual static MLP)."""
    paths = []
    for k, cur in enumerate((0.0, 0.8, 1.6)):
        b = dataset_b(duration_s=0.6, amplitudes_m=(0.01,), freqs_hz=(2.0,), currents_a=(cur,))
        s = Series(b.t, b.x, b.xd, b.xdd, b.current, b.force_meas, b.run_id)
        paths.append(tmp_path / f"test{k}.csv")
        write_tidy(paths[-1], s)
    return paths


def test_the_default_on_constant_command_tests_chooses_by_leaving_tests_out(
    tmp_path, constant_command_matrix, capsys
):
    out = tmp_path / "m.json"
    args = [*map(str, constant_command_matrix), "--out", str(out), "--no-supervised"]
    args += ["--epochs", "5", "--restarts", "1", "--budget-s", "2"]
    assert train_main(args) == 0
    text = capsys.readouterr().out
    print(text)
    assert "kind of model, chosen by the other tests estimate: leave-one-test-out over 3" in text
    assert "time budget 2 s" in text
    assert "not tried: GRU (not within the time budget" in text
    scored = [line.split() for line in text.splitlines() if line.startswith("  Et ")]
    assert scored and all(math.isfinite(float(r[1])) for r in scored)
    assert "[optimistic: the end of each run" in text and "other-test estimate, leave-one" in text


def test_a_fold_fit_early_stops_on_whole_tests_and_the_block_figure_keeps_its_block_out():
    """Issue 43 item 1: an MLP fold's early stopping was on a block of the very tests it trains
    on (it stopped where the fit held on the same tests); it now stops on whole tests of the
    fold's training data that it does not train on (`fit.stretch_split`), while the kind's
    block hold-out figure is still fitted with that block kept out."""
    sp = stretch_split(np.repeat(np.arange(8), 10))
    stop_tests = set((sp.stop // 10).tolist())
    assert stop_tests == {0, 6} and sp.stop.size == 20  # whole tests, every 6th
    assert sp.train.size == 80 and sp.val.size == 0
    assert stretch_split(np.repeat(np.arange(3), 10)).kind == "blocks"  # too few to keep one out
    s = _series(PIECES, one_run=False)
    kind = mlp_kind(
        "history MLP",
        Candidate(history_samples=2, hidden=4),
        "toy",
        seed=0,
        max_epochs=3,
        holdout_fraction=HOLDOUT,
        i_max=4.0,
    )
    assert kind.fit_fold(s, 1.0).meta["split"] == "stretches"
    assert kind.block_fit is not None and kind.block_fit(s, 1.0).meta["split"] == "blocks"
