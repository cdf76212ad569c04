"""Levenberg-Marquardt training of the one-hidden-layer MLP, like MATLAB `trainlm` (float64).

The paper trains its forward network with `trainlm` (adaptive damping mu, early stop after
`max_fail` validation failures, at most 1000 epochs); this module follows that loop:

    dw = (J^T J + mu I)^-1 J^T e        J = d f_net / d w, e = y - f_net (standardised units)

accept the step and divide mu by 10 if the training MSE falls, otherwise multiply mu by 10 and
solve again with the same J. The Jacobian is analytic (one hidden layer); J^T J is the cost of
an epoch. The epoch runs in numpy float64: numpy computes J J^T as one BLAS syrk (half the
flops of torch's gemm), and one BLAS thread pool avoids contention with torch's OpenMP. BLAS
runs on `blas_threads` threads during training (default 1: spinning worker threads stall a
busy machine; docs/measurements.md). Torch provides `MLPModule`, the autograd twin of the
numpy model.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mrrig.loop.mlp import MLP, data_fingerprint
from mrrig.offline.metrics import error_norm

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, float, float | None, float], None]


@dataclass
class TrainReport:
    """Outcome of `train_lm`; MSEs are in physical units squared (N^2 for force)."""

    epochs: int
    best_epoch: int
    seconds: float
    train_mse: float
    val_mse: float | None
    mu: float
    stop_reason: str  # max_epochs | validation | mu_max | min_grad | time_limit
    n_train: int
    n_val: int


def _tensor(a: np.ndarray | float) -> torch.Tensor:
    return torch.tensor(np.asarray(a), dtype=torch.float64)


class MLPModule(torch.nn.Module):
    """Torch twin of `MLP` (same weights, physical units in and out), for autograd."""

    def __init__(self, model: MLP) -> None:
        super().__init__()
        self.register_buffer("in_mean", _tensor(model.in_mean))
        self.register_buffer("in_std", _tensor(model.in_std))
        self.register_buffer("out_mean", _tensor(model.out_mean))
        self.register_buffer("out_std", _tensor(model.out_std))
        self.W1 = torch.nn.Parameter(_tensor(model.W1))
        self.b1 = torch.nn.Parameter(_tensor(model.b1))
        self.W2 = torch.nn.Parameter(_tensor(model.W2))
        self.b2 = torch.nn.Parameter(_tensor(model.b2))

    def forward(self, X: torch.Tensor) -> torch.Tensor:
        z = (X - self.in_mean) / self.in_std
        o = torch.tanh(z @ self.W1.T + self.b1)  # eqs 5, 7
        return self.out_mean + self.out_std * (o @ self.W2 + self.b2)


class _Net:
    """Flat parameter vector w = [A.ravel(), W2, b2] with A = [W1 | b1] (H x (n+1)).

    Samples run along the last axis (Z1t: (n+1) x N, Jt: n_params x N): contiguous rows.
    """

    def __init__(self, n_in: int, hidden: int) -> None:
        self.n_in, self.hidden = n_in, hidden
        self.n_a = hidden * (n_in + 1)
        self.n_params = self.n_a + hidden + 1

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        A = w[: self.n_a].reshape(self.hidden, self.n_in + 1)
        return A, w[self.n_a : self.n_a + self.hidden], float(w[-1])

    def forward(self, w: np.ndarray, Z1t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f (N,), o (H x N)) for standardised inputs with a row of ones, Z1t ((n+1) x N)."""
        A, W2, b2 = self.unpack(w)
        o = np.tanh(A @ Z1t)  # eqs 5, 7
        return W2 @ o + b2, o

    def jacobian(self, w: np.ndarray, Z1t: np.ndarray, o: np.ndarray, Jt: np.ndarray) -> None:
        """Fill Jt (n_params x N) with d f / d w."""
        _, W2, _ = self.unpack(w)
        D = o * o
        np.subtract(1.0, D, out=D)
        D *= W2[:, None]  # d f / d pre-activation
        np.multiply(
            D[:, None, :],
            Z1t[None, :, :],
            out=Jt[: self.n_a].reshape(self.hidden, self.n_in + 1, -1),
        )
        Jt[self.n_a : self.n_a + self.hidden] = o
        Jt[-1] = 1.0

    def init(self, rng: np.random.Generator) -> np.ndarray:
        """Nguyen-Widrow hidden layer (as MATLAB's initnw) for inputs of about unit range."""
        H, n = self.hidden, self.n_in
        beta = 0.7 * H ** (1.0 / n)
        W = rng.uniform(-1.0, 1.0, (H, n))
        W *= beta / np.linalg.norm(W, axis=1, keepdims=True)
        b = rng.uniform(-beta, beta, H)
        W2 = rng.uniform(-1.0, 1.0, H) / np.sqrt(H)
        return np.concatenate([np.column_stack([W, b]).ravel(), W2, [0.0]])


@contextlib.contextmanager
def limited_blas_threads(n: int | None) -> Iterator[None]:
    """Limit numpy's bundled OpenBLAS to n threads inside the block (no-op if n is None or
    numpy uses another BLAS)."""
    libs = sorted((Path(np.__file__).parent.parent / "numpy.libs").glob("libscipy_openblas*.so*"))
    lib = ctypes.CDLL(str(libs[0])) if libs and n is not None else None
    setter = getattr(lib, "scipy_openblas_set_num_threads64_", None)
    getter = getattr(lib, "scipy_openblas_get_num_threads64_", None)
    if setter is None or getter is None:
        yield
        return
    before = getter()
    setter(n)
    try:
        yield
    finally:
        setter(before)


def _standardise(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = a.mean(axis=0)
    std = a.std(axis=0)
    return mean, np.where(std > 0.0, std, 1.0)


def train_lm(
    X: np.ndarray,
    y: np.ndarray,
    input_names: Sequence[str],
    input_units: Sequence[str],
    output_name: str,
    output_unit: str,
    *,
    hidden: int = 30,
    max_epochs: int = 1000,
    validation: tuple[np.ndarray, np.ndarray] | None = None,
    validation_fraction: float = 0.1,
    mu0: float = 1e-3,
    mu_inc: float = 10.0,
    mu_dec: float = 0.1,
    mu_max: float = 1e10,
    max_fail: int = 6,
    min_grad: float = 1e-7,
    seed: int = 0,
    progress: ProgressFn | None = None,
    time_limit_s: float | None = None,
    description: str = "",
    blas_threads: int | None = 1,
) -> tuple[MLP, TrainReport]:
    """Train an n_in-hidden-1 tanh MLP on (X (N x n_in), y (N,)) by Levenberg-Marquardt.

    Validation: `validation=(Xv, yv)`, or else a random `validation_fraction` of X held out
    (0: no early stop). Returns the best-validation weights (the last ones without
    validation). `progress(epoch, train_mse, val_mse, mu)` is called after every epoch, MSEs
    in physical units squared. `blas_threads`: see the module docstring.
    """
    with limited_blas_threads(blas_threads):
        return _train_lm(
            X,
            y,
            input_names,
            input_units,
            output_name,
            output_unit,
            hidden,
            max_epochs,
            validation,
            validation_fraction,
            mu0,
            mu_inc,
            mu_dec,
            mu_max,
            max_fail,
            min_grad,
            seed,
            progress,
            time_limit_s,
            description,
        )


def _train_lm(
    X: np.ndarray,
    y: np.ndarray,
    input_names: Sequence[str],
    input_units: Sequence[str],
    output_name: str,
    output_unit: str,
    hidden: int,
    max_epochs: int,
    validation: tuple[np.ndarray, np.ndarray] | None,
    validation_fraction: float,
    mu0: float,
    mu_inc: float,
    mu_dec: float,
    mu_max: float,
    max_fail: int,
    min_grad: float,
    seed: int,
    progress: ProgressFn | None,
    time_limit_s: float | None,
    description: str,
) -> tuple[MLP, TrainReport]:
    t_start = time.perf_counter()
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64).ravel()
    if X.ndim != 2 or X.shape[0] != y.shape[0] or X.shape[1] != len(input_names):
        raise ValueError(
            f"train_lm: X {X.shape} and y {y.shape} do not match {len(input_names)} inputs"
        )
    fingerprint_arrays = [X, y]
    if validation is not None:
        Xv, yv = (np.asarray(a, dtype=np.float64) for a in validation)
        yv = yv.ravel()
        fingerprint_arrays += [Xv, yv]
        Xt, yt = X, y
    else:
        perm = np.random.default_rng(seed).permutation(X.shape[0])
        n_val = int(round(validation_fraction * X.shape[0]))
        Xv, yv = X[perm[:n_val]], y[perm[:n_val]]
        Xt, yt = X[perm[n_val:]], y[perm[n_val:]]
    has_val = Xv.shape[0] > 0

    in_mean, in_std = _standardise(Xt)
    out_mean, out_std = float(yt.mean()), float(yt.std()) or 1.0

    def prepare(Xa: np.ndarray, ya: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Z1t = np.empty((Xa.shape[1] + 1, Xa.shape[0]))
        Z1t[:-1] = ((Xa - in_mean) / in_std).T
        Z1t[-1] = 1.0
        return Z1t, (ya - out_mean) / out_std

    Z1, ys = prepare(Xt, yt)
    Z1v, ysv = prepare(Xv, yv)
    net = _Net(X.shape[1], hidden)
    w = net.init(np.random.default_rng(seed))
    N, P = Z1.shape[1], net.n_params
    Jt = np.empty((P, N))
    diag = np.diag_indices(P)

    def val_mse(w_: np.ndarray) -> float:
        return float(((ysv - net.forward(w_, Z1v)[0]) ** 2).mean()) if has_val else float("nan")

    f, o = net.forward(w, Z1)
    e = ys - f
    perf = float(e @ e) / N
    vperf = val_mse(w)
    best_w, best_epoch, best_vperf, fails = w.copy(), 0, vperf, 0
    mu = mu0
    epoch = 0
    stop = "max_epochs"
    scale = out_std**2
    while epoch < max_epochs:
        net.jacobian(w, Z1, o, Jt)
        JtJ = Jt @ Jt.T  # numpy makes this one BLAS syrk: the epoch's main cost
        g = Jt @ e
        if 2.0 * float(np.linalg.norm(g)) / N < min_grad:
            stop = "min_grad"
            break
        accepted = False
        while mu <= mu_max:
            M = JtJ.copy()
            M[diag] += mu
            try:
                # numpy, not scipy: scipy's own OpenBLAS would spin up its threads here
                step = np.linalg.solve(M, g)
            except np.linalg.LinAlgError:
                step = None
            if step is not None:
                w_try = w + step
                f_try, o_try = net.forward(w_try, Z1)
                e_try = ys - f_try
                perf_try = float(e_try @ e_try) / N
                if perf_try < perf:
                    w, o, e, perf = w_try, o_try, e_try, perf_try
                    mu *= mu_dec
                    accepted = True
                    break
            mu *= mu_inc
        if not accepted:
            stop = "mu_max"
            break
        epoch += 1
        vperf = val_mse(w)
        if not has_val or vperf < best_vperf:
            best_w, best_epoch, best_vperf, fails = w.copy(), epoch, vperf, 0
        elif vperf > best_vperf:
            fails += 1
        v_phys = vperf * scale if has_val else None
        if progress is not None:
            progress(epoch, perf * scale, v_phys, mu)
        if epoch % 50 == 0:
            log.info(
                "LM epoch %d: train MSE %.6g, val MSE %s, mu %.3g",
                epoch,
                perf * scale,
                f"{v_phys:.6g}" if v_phys is not None else "-",
                mu,
            )
        if has_val and fails >= max_fail:
            stop = "validation"
            break
        if time_limit_s is not None and time.perf_counter() - t_start > time_limit_s:
            stop = "time_limit"
            break

    A, W2, b2 = net.unpack(best_w)
    f_best_t = net.forward(best_w, Z1)[0] * out_std + out_mean
    train_mse = float(np.mean((yt - f_best_t) ** 2))
    seconds = time.perf_counter() - t_start
    metrics: dict[str, float | None] = {
        "train_mse": train_mse,
        "train_et": error_norm(yt, f_best_t),
        "val_mse": None,
        "val_et": None,
    }
    if has_val:
        f_best_v = net.forward(best_w, Z1v)[0] * out_std + out_mean
        metrics["val_mse"] = float(np.mean((yv - f_best_v) ** 2))
        metrics["val_et"] = error_norm(yv, f_best_v)
    report = TrainReport(
        epochs=epoch,
        best_epoch=best_epoch,
        seconds=seconds,
        train_mse=train_mse,
        val_mse=metrics["val_mse"],
        mu=mu,
        stop_reason=stop,
        n_train=int(Xt.shape[0]),
        n_val=int(Xv.shape[0]),
    )
    model = MLP(
        input_names=list(input_names),
        input_units=list(input_units),
        output_name=output_name,
        output_unit=output_unit,
        in_mean=in_mean,
        in_std=in_std,
        out_mean=out_mean,
        out_std=out_std,
        W1=A[:, :-1],
        b1=A[:, -1],
        W2=W2,
        b2=float(b2),
        fingerprint=data_fingerprint(*fingerprint_arrays),
        metrics=metrics,
        meta={
            "trainer": "levenberg-marquardt",
            "hidden": hidden,
            "epochs": epoch,
            "best_epoch": best_epoch,
            "stop_reason": stop,
            "seconds": seconds,
            "mu_final": mu,
            "mu0": mu0,
            "max_fail": max_fail,
            "seed": seed,
            "n_train": int(Xt.shape[0]),
            "n_val": int(Xv.shape[0]),
            "data": description,
            "numpy": np.__version__,
        },
    )
    log.info(
        "LM stopped (%s) after %d epochs in %.2f s: train MSE %.6g, val MSE %s",
        stop,
        epoch,
        seconds,
        train_mse,
        metrics["val_mse"],
    )
    return model, report
