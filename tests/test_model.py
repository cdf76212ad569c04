"""The forward MLP, its file format, and the Levenberg-Marquardt trainer."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from mrrig.loop.mlp import MLP, ModelError
from mrrig.offline.training.lm import MLPModule, train_lm

NAMES = ["x", "xd", "xdd", "current"]
UNITS = ["m", "m/s", "m/s^2", "A"]


def smooth_data(rng: np.random.Generator, n: int, noise_n: float = 0.0) -> tuple[np.ndarray, ...]:
    """A smooth damper-like force (N) of (x, xd, xdd, current)."""
    X = np.column_stack(
        [
            rng.uniform(-0.02, 0.02, n),
            rng.uniform(-0.3, 0.3, n),
            rng.uniform(-20.0, 20.0, n),
            rng.uniform(0.0, 2.0, n),
        ]
    )
    y = (
        (300.0 + 900.0 * X[:, 3]) * np.tanh(X[:, 1] / 0.1)
        + 800.0 * X[:, 1]
        + 2000.0 * X[:, 0]
        + 4.0 * X[:, 2]
    )
    return X, y + rng.normal(0.0, noise_n, n)


@pytest.fixture(scope="module")
def trained() -> tuple[MLP, np.ndarray]:
    X, y = smooth_data(np.random.default_rng(0), 400)
    model, _ = train_lm(X, y, NAMES, UNITS, "force", "N", hidden=8, max_epochs=40)
    return model, X


def test_lm_fits_a_smooth_function_to_near_zero_error() -> None:
    X, y = smooth_data(np.random.default_rng(1), 800)
    Xv, yv = smooth_data(np.random.default_rng(2), 200)
    model, report = train_lm(
        X, y, NAMES, UNITS, "force", "N", hidden=12, max_epochs=300, validation_fraction=0.0
    )
    rel_rms = np.sqrt(np.mean((model.predict(Xv) - yv) ** 2)) / np.std(yv)
    assert rel_rms < 1e-2  # on unseen points; a constant predictor scores 1
    assert report.train_mse == pytest.approx(np.mean((model.predict(X) - y) ** 2), rel=1e-9)


def test_lm_stops_on_validation_failures_and_keeps_the_best_weights() -> None:
    X, y = smooth_data(np.random.default_rng(3), 300, noise_n=60.0)
    Xv, yv = smooth_data(np.random.default_rng(4), 200, noise_n=60.0)
    calls: list[tuple[int, float, float | None, float]] = []
    model, report = train_lm(
        X,
        y,
        NAMES,
        UNITS,
        "force",
        "N",
        hidden=20,
        max_epochs=500,
        validation=(Xv, yv),
        max_fail=6,
        progress=lambda *a: calls.append(a),
    )
    assert report.stop_reason == "validation"
    assert report.best_epoch == report.epochs - 6
    assert [c[0] for c in calls] == list(range(1, report.epochs + 1))
    val = np.array([c[2] for c in calls])
    assert np.all(val[report.best_epoch :] > val[report.best_epoch - 1])
    best_val = np.mean((model.predict(Xv) - yv) ** 2)
    assert best_val == pytest.approx(val.min(), rel=1e-9)
    assert report.val_mse == pytest.approx(best_val, rel=1e-9)
    assert model.meta["best_epoch"] == report.best_epoch


def test_lm_training_mse_never_increases() -> None:
    X, y = smooth_data(np.random.default_rng(5), 300)
    calls: list[tuple[int, float, float | None, float]] = []
    _, report = train_lm(
        X,
        y,
        NAMES,
        UNITS,
        "force",
        "N",
        hidden=6,
        max_epochs=60,
        validation_fraction=0.0,
        progress=lambda *a: calls.append(a),
    )
    train = [c[1] for c in calls]
    assert report.stop_reason == "max_epochs" and len(train) == 60
    assert all(b < a for a, b in zip(train, train[1:], strict=False))
    assert all(c[2] is None for c in calls)


def test_lm_holds_out_a_random_validation_fraction() -> None:
    X, y = smooth_data(np.random.default_rng(6), 500)
    model, report = train_lm(
        X, y, NAMES, UNITS, "force", "N", hidden=5, max_epochs=5, validation_fraction=0.1
    )
    assert (report.n_train, report.n_val) == (450, 50)
    assert model.meta["n_val"] == 50 and len(model.fingerprint) == 64


def test_model_file_round_trip_is_bit_exact(
    trained: tuple[MLP, np.ndarray], tmp_path: Path
) -> None:
    model, X = trained
    path = tmp_path / "forward.json"
    model.save(path)
    back = MLP.load(path)
    for name in ("in_mean", "in_std", "W1", "b1", "W2"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))
    assert (back.out_mean, back.out_std, back.b2) == (model.out_mean, model.out_std, model.b2)
    assert back.fingerprint == model.fingerprint and back.metrics == model.metrics
    assert back.current_index == 3
    np.testing.assert_array_equal(back.predict(X), model.predict(X))


def test_model_file_loads_without_torch_and_gives_the_torch_module_forces(
    trained: tuple[MLP, np.ndarray], tmp_path: Path
) -> None:
    model, X = trained
    model.save(tmp_path / "forward.json")
    np.save(tmp_path / "X.npy", X)
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None
        import numpy as np
        from mrrig.loop.mlp import MLP
        m = MLP.load({str(tmp_path / "forward.json")!r})
        np.save({str(tmp_path / "f.npy")!r}, m.predict(np.load({str(tmp_path / "X.npy")!r})))
        assert "torch" not in sys.modules or sys.modules["torch"] is None
    """)
    subprocess.run([sys.executable, "-c", script], check=True, cwd=Path(__file__).parents[1])
    with torch.no_grad():
        f_torch = MLPModule(model)(torch.tensor(X)).numpy()
    np.testing.assert_allclose(
        np.load(tmp_path / "f.npy"), f_torch, rtol=0, atol=1e-9 * np.abs(f_torch).max()
    )


def _corrupt(doc: dict, field: str, value: object) -> dict:
    doc = dict(doc)
    if value is _MISSING:
        del doc[field]
    else:
        doc[field] = value
    return doc


_MISSING = object()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("format", "mrrig-mlp/0"),
        ("W1", _MISSING),
        ("W1", [[1.0, 2.0]]),
        ("W1", [[1.0, 2.0, 3.0, 4.0], [1.0]]),
        ("b1", [0.0]),
        ("W2", ["a"] * 8),
        ("in_std", [1.0, 0.0, 1.0, 1.0]),
        ("out_std", "big"),
        ("input_units", ["m"]),
        ("hidden", 9),
        ("b2", float("nan")),
    ],
)
def test_bad_model_file_raises_one_line_error_naming_file_and_field(
    trained: tuple[MLP, np.ndarray], tmp_path: Path, field: str, value: object
) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(_corrupt(trained[0].to_dict(), field, value)))
    with pytest.raises(ModelError) as info:
        MLP.load(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and f"'{field}'" in message


def test_unreadable_or_non_json_model_file_raises_model_error(tmp_path: Path) -> None:
    for path, text in ((tmp_path / "a.json", "{not json"), (tmp_path / "b.json", "[1, 2]")):
        path.write_text(text)
        with pytest.raises(ModelError, match="^" + str(path)):
            MLP.load(path)
    with pytest.raises(ModelError, match="cannot read"):
        MLP.load(tmp_path / "missing.json")


def test_lm_stops_at_the_time_limit() -> None:
    X, y = smooth_data(np.random.default_rng(7), 200)
    _, report = train_lm(
        X, y, NAMES, UNITS, "force", "N", hidden=5, max_epochs=1000, time_limit_s=0.0
    )
    assert (report.stop_reason, report.epochs) == ("time_limit", 1)
