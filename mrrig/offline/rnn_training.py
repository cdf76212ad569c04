"""Training the RNN inverse controller (paper eq. 40) so that it works in closed loop.

The RNN maps f_d(k), f_d(k-1), x(k), x(k-1) and its own previous outputs v(k-1) ... v(k-6) to
the command v(k). Fitted series-parallel (teacher forcing: the recorded past voltages as
inputs), it learns v(k) ~ extrapolation of v(k-1..k-6), which is almost exact for a smooth
command (held-out Et 1e-5), and ignores force and displacement; run in parallel mode (its own
outputs fed back, as in closed loop) it drifts to 0 V or Vmax (exposure bias). Two stages fix
that without changing the network:

1. Input-noise regularisation: the fed-back inputs v(k-1..k-6) of every training row are
   perturbed by Gaussian noise of `noise_v` volts, the target stays the true v(k) (Bishop 1995:
   noise on inputs acts as a Tikhonov penalty). The network can no longer extrapolate the
   command from its past alone and must read it from force and displacement: the loop through
   the fed-back inputs becomes contracting. LM as `train_lm` (trainlm), early stop on a random
   noisy split.
2. Parallel-mode fine-tune: LM on the unrolled error of the network run in parallel mode over
   1 s segments of the training signal (e = v_true - v_hat with v_hat fed back, as MATLAB's
   closed-loop NARX training), each run from a zero history as the controller starts after
   `reset`, with the exact Jacobian by forward sensitivities (real-time recurrent learning)
   through the clamp to [0, i_max]; early stop on the parallel-mode error of held-out blocks.

The held-out blocks (every `HOLDOUT_EVERY`-th block of `BLOCK_S`) are never fitted; they give
the early stop of stage 2 and `held_out_et`. Hyper-parameters were chosen on held-out stretches
of data set A's training signal in closed loop against the plant, never on the validation cases.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass

import numpy as np

from mrrig.loop.controllers import RNN_INPUTS, rnn_features
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series
from mrrig.offline.metrics import error_norm
from mrrig.offline.training.lm import limited_blas_threads, train_lm

log = logging.getLogger(__name__)

LAGS = 6  # v(k-1) ... v(k-6) fed back (eq. 40)
V_COLUMNS = slice(4, 4 + LAGS)  # their columns in RNN_INPUTS
RNN_UNITS = ("N", "N", "m", "m") + ("V",) * LAGS
NOISE_V = 1.0  # stage 1: std of the noise on the fed-back inputs
BLOCK_S = 2.0  # hold-out blocks: every HOLDOUT_EVERY-th, from HOLDOUT_OFFSET
HOLDOUT_EVERY = 10
HOLDOUT_OFFSET = 5  # on data set A: blocks at 10, 30, 50 s (noise), 70 s (6 V), 90 s (sine)
SEGMENT_S = 1.0  # stage 2: length of the parallel-mode segments
JACOBIAN_STRIDE = 8  # stage 2: one Jacobian row every this many samples
PARALLEL_MAX_EPOCHS = 50
N_TRAIN = 12771  # stage 1 rows, the paper's training and validation sizes
N_VAL = 1419
I_MAX_V = 12.0


@dataclass
class Segments:
    """Equally long stretches of a series, stacked: arrays (B, n)."""

    f: np.ndarray  # desired (recorded) force, N
    x: np.ndarray  # displacement, m
    v: np.ndarray  # recorded command, V

    @classmethod
    def cut(cls, s: Series, slices: list[slice]) -> Segments:
        return cls(*(np.stack([a[sl] for sl in slices]) for a in (s.force, s.x, s.current)))

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Teacher-forced rows of eq. 40 (inputs, target v(k)) from every segment."""
        triples = zip(self.f, self.x, self.v, strict=True)
        X = np.concatenate([rnn_features(f, x, v) for f, x, v in triples])
        return X, self.v[:, LAGS:].ravel()


def holdout_blocks(
    n: int, block: int, every: int = HOLDOUT_EVERY, offset: int = HOLDOUT_OFFSET
) -> tuple[list[slice], list[slice]]:
    """Consecutive blocks of `block` samples: (fitted, held out = every `every`-th from
    `offset`). A tail shorter than a block is dropped."""
    n_blocks = n // block
    if n_blocks <= offset:
        raise ValueError(f"{n} samples make {n_blocks} blocks of {block}: need > {offset}")
    held = set(range(offset, n_blocks, every))
    blocks = [slice(b * block, (b + 1) * block) for b in range(n_blocks)]
    return [s for b, s in enumerate(blocks) if b not in held], [blocks[b] for b in sorted(held)]


def perturb_feedback(X: np.ndarray, noise_v: float, rng: np.random.Generator) -> np.ndarray:
    """A copy of the rows with Gaussian noise (std noise_v) on the fed-back v columns only."""
    Xn = np.array(X, dtype=float)
    Xn[:, V_COLUMNS] += rng.normal(0.0, noise_v, (Xn.shape[0], LAGS))
    return Xn


class _Weights:
    """The MLP's weights as one vector w = [A.ravel(), W2, b2], A = [W1 | b1] (train.py's order),
    with the model's input and output scaling held fixed."""

    def __init__(self, model: MLP) -> None:
        self.model = model
        self.hidden, self.n_in = model.W1.shape
        self.n_a = self.hidden * (self.n_in + 1)
        self.n_params = self.n_a + self.hidden + 1

    def pack(self) -> np.ndarray:
        m = self.model
        return np.concatenate([np.column_stack([m.W1, m.b1]).ravel(), m.W2, [m.b2]])

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        A = w[: self.n_a].reshape(self.hidden, self.n_in + 1)
        return A, w[self.n_a : self.n_a + self.hidden], float(w[-1])

    def model_with(self, w: np.ndarray) -> MLP:
        A, W2, b2 = self.unpack(w)
        m = copy.deepcopy(self.model)
        m.W1, m.b1, m.W2, m.b2 = A[:, :-1].copy(), A[:, -1].copy(), W2.copy(), b2
        return m


def _parallel(
    wt: _Weights, w: np.ndarray, seg: Segments, i_max: float, stride: int | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Run eq. 40 in parallel mode over the segments, as `RecurrentInverse` runs it: v_hat
    (B, n), the clamped outputs fed back, a zero history before sample 0.

    With `stride`, also the transposed Jacobian Jt (n_params, rows): d v_hat(k) / d w in
    standardised output units at k = 0, stride, 2 stride, ... (columns: sample-major, then
    segment), by forward sensitivities (real-time recurrent learning):
    T(k) = d y/d w |direct + sum_j d y/d v_hat(k-j) T(k-j), zero where the clamp is active.
    """
    m = wt.model
    A, W2, b2 = wt.unpack(w)
    B, n = seg.f.shape
    mean, std = m.in_mean, m.in_std
    lag_mean, lag_std = mean[V_COLUMNS], std[V_COLUMNS]
    f_prev = np.concatenate([seg.f[:, :1], seg.f[:, :-1]], axis=1)
    x_prev = np.concatenate([seg.x[:, :1], seg.x[:, :-1]], axis=1)
    static = (np.stack([seg.f, f_prev, seg.x, x_prev], axis=-1) - mean[:4]) / std[:4]
    buf = np.zeros((B, LAGS + n))  # buf[:, LAGS + k] = v_hat(k); zeros before sample 0
    z1 = np.ones((B, wt.n_in + 1))
    Jt = None
    if stride is not None:
        sampled = range(0, n, stride)
        Jt = np.empty((wt.n_params, len(sampled) * B))
        T = np.zeros((B, LAGS, wt.n_params))  # ring buffer: T(k) in slot k % LAGS
        direct = np.empty((B, wt.n_params))
        direct[:, -1] = 1.0
        # d y_std / d v_hat(k-1-j) = D @ A_lags[:, j], with d v_hat = out_std d y_std
        A_lags = A[:, V_COLUMNS] * (m.out_std / lag_std)
        slots = np.arange(LAGS)
    for k in range(n):
        z1[:, :4] = static[:, k]
        z1[:, V_COLUMNS] = (buf[:, k : k + LAGS][:, ::-1] - lag_mean) / lag_std  # eq. 40
        o = np.tanh(z1 @ A.T)  # eqs 5, 7
        y = m.out_mean + m.out_std * (o @ W2 + b2)
        buf[:, LAGS + k] = np.clip(y, 0.0, i_max)
        if Jt is None:
            continue
        D = (1.0 - o * o) * W2
        direct[:, : wt.n_a] = (D[:, :, None] * z1[:, None, :]).reshape(B, wt.n_a)
        direct[:, wt.n_a : -1] = o
        g_slots = (D @ A_lags)[:, (k - 1 - slots) % LAGS]  # lag of each ring slot
        t_k = direct + np.matmul(g_slots[:, None, :], T)[:, 0, :]
        t_k[(y <= 0.0) | (y >= i_max)] = 0.0
        T[:, k % LAGS] = t_k
        if k % stride == 0:
            r = k // stride
            Jt[:, r * B : (r + 1) * B] = t_k.T
    return buf[:, LAGS:], Jt


def rollout(model: MLP, seg: Segments, i_max: float = I_MAX_V) -> np.ndarray:
    """The network in parallel mode over the segments, its own clamped outputs fed back from
    a zero history (what `RecurrentInverse` commands after `reset`): v_hat (B, n)."""
    wt = _Weights(model)
    return _parallel(wt, wt.pack(), seg, i_max, None)[0]


def parallel_lm(
    model: MLP,
    fit: Segments,
    held: Segments,
    i_max: float = I_MAX_V,
    max_epochs: int = PARALLEL_MAX_EPOCHS,
    stride: int = JACOBIAN_STRIDE,
    mu0: float = 1e-3,
    max_fail: int = 6,
) -> tuple[MLP, dict]:
    """Levenberg-Marquardt on the parallel-mode error over `fit` (stage 2), early stop on the
    parallel-mode MSE over `held`; returns the best-held-out model and a summary."""
    wt = _Weights(model)
    w = wt.pack()

    def fit_error(w: np.ndarray) -> np.ndarray:
        v_hat = _parallel(wt, w, fit, i_max, None)[0]
        return ((fit.v - v_hat)[:, ::stride].T / model.out_std).ravel()

    def held_mse(w: np.ndarray) -> float:
        v_hat = _parallel(wt, w, held, i_max, None)[0]
        return float(np.mean((held.v - v_hat) ** 2))

    t0 = time.perf_counter()
    # one BLAS thread, as in train_lm: spinning OpenBLAS workers stall a busy 2-core machine
    with limited_blas_threads(1):
        best_w, best_mse, best_epoch, fails = w.copy(), held_mse(w), 0, 0
        start_mse = best_mse
        e = fit_error(w)
        perf = float(e @ e) / e.size
        mu, epoch, stop = mu0, 0, "max_epochs"
        while epoch < max_epochs:
            Jt = _parallel(wt, w, fit, i_max, stride)[1]
            JtJ, g = Jt @ Jt.T, Jt @ e
            accepted = False
            while mu <= 1e10:
                M = JtJ.copy()
                M[np.diag_indices_from(M)] += mu
                w_try = w + np.linalg.solve(M, g)
                e_try = fit_error(w_try)
                perf_try = float(e_try @ e_try) / e_try.size
                if perf_try < perf:
                    w, e, perf, mu, accepted = w_try, e_try, perf_try, mu * 0.1, True
                    break
                mu *= 10.0
            if not accepted:
                stop = "mu_max"
                break
            epoch += 1
            mse = held_mse(w)
            log.info(
                "parallel LM epoch %d: fit MSE %.4g V^2, held-out MSE %.4g V^2, mu %.3g",
                epoch,
                perf * model.out_std**2,
                mse,
                mu,
            )
            if mse < best_mse:
                best_w, best_mse, best_epoch, fails = w.copy(), mse, epoch, 0
            else:
                fails += 1
                if fails >= max_fail:
                    stop = "validation"
                    break
    return wt.model_with(best_w), {
        "epochs": epoch,
        "best_epoch": best_epoch,
        "stop_reason": stop,
        "seconds": time.perf_counter() - t0,
        "held_out_mse_before_v2": start_mse,
        "held_out_mse_v2": best_mse,
        "segments": int(fit.f.shape[0]),
        "jacobian_rows": int(fit.f.shape[0] * len(range(0, fit.f.shape[1], stride))),
    }


def train_rnn(
    train: Series,
    seed: int,
    max_epochs: int,
    noise_v: float = NOISE_V,
    fine_tune: bool = True,
    i_max: float = I_MAX_V,
) -> tuple[MLP, dict]:
    """The RNN of eq. 40 (10-30-1, inputs `RNN_INPUTS`) trained for parallel-mode use.

    Stage 1 (always): LM on teacher-forced rows of the fitted blocks with the fed-back inputs
    perturbed by `noise_v` volts (at most `max_epochs`); stage 2 (`fine_tune`): LM on the
    parallel-mode error (at most min(max_epochs, PARALLEL_MAX_EPOCHS)). Returns the model and a
    summary: seconds, epochs, held_out_et (parallel-mode Et of v on the held-out blocks, all
    blocks together), teacher_forced_et (held-out blocks, noise-free inputs), and the settings.
    """
    t0 = time.perf_counter()
    dt_s = float(np.median(np.diff(train.t)))
    block = round(BLOCK_S / dt_s)
    fit_blocks, held_blocks = holdout_blocks(len(train), block)
    seg = min(round(SEGMENT_S / dt_s), block)
    fit_segments = [
        slice(b.start + o, b.start + o + seg)
        for b in fit_blocks
        for o in range(0, block // seg * seg, seg)
    ]
    fit, held = Segments.cut(train, fit_segments), Segments.cut(train, held_blocks)

    rng = np.random.default_rng(seed)
    X, y = fit.rows()
    pick = rng.permutation(len(y))
    n_val = min(N_VAL, len(y) // 10)
    tr, va = pick[n_val : n_val + N_TRAIN], pick[:n_val]
    Xn = perturb_feedback(X, noise_v, rng)
    model, report = train_lm(
        Xn[tr],
        y[tr],
        input_names=list(RNN_INPUTS),
        input_units=list(RNN_UNITS),
        output_name="current",
        output_unit="V",
        validation=(Xn[va], y[va]),
        max_epochs=max_epochs,
        seed=seed,
        description=f"RNN eq. 40, feedback noise {noise_v} V",
    )
    procedure = "feedback-input noise" + (" + parallel-mode LM" if fine_tune else "")
    info: dict = {
        "procedure": procedure,
        "noise_v": noise_v,
        "epochs": report.epochs,
        "stage1_seconds": report.seconds,
        "stage1_stop_reason": report.stop_reason,
        "fit_blocks": len(fit_blocks),
        "held_out_blocks": [(s.start, s.stop) for s in held_blocks],
    }
    if fine_tune:
        model, info["parallel"] = parallel_lm(
            model, fit, held, i_max, max_epochs=min(max_epochs, PARALLEL_MAX_EPOCHS)
        )
    Xh, yh = held.rows()
    v_hat = rollout(model, held, i_max)
    info["held_out_et"] = error_norm(held.v.ravel(), v_hat.ravel())
    info["teacher_forced_et"] = error_norm(yh, model.predict(Xh))
    info["seconds"] = time.perf_counter() - t0
    model.meta.update({"procedure": procedure, "noise_v": noise_v})
    model.metrics.update({"parallel_held_out_et": info["held_out_et"]})
    log.info(
        "RNN (eq. 40): %.1f s, parallel-mode held-out Et %.4f, teacher-forced %.4f",
        info["seconds"],
        info["held_out_et"],
        info["teacher_forced_et"],
    )
    return model, info
