"""Velocity and acceleration of the piston from sampled displacement (paper eqs 15-29).

`KalmanEstimator` is the paper's estimator: a constant-acceleration Kalman filter whose
measurement noise shrinks with speed (eq. 24). `finite_difference` is the baseline it replaces
(eqs 15-16 plus a causal low-pass). Both are pure numerics in SI units (m, m/s, m/s^2).

Defaults are chosen for the rig (spec/modeling.md, data set B): 500 Hz sampling, about
10-20 um displacement noise, sines of 10-20 mm at 2-6 Hz, so |x'| <= 0.75 m/s and
|x''| <= 28 m/s^2. `python -m mrrig.offline.bench.estimation` prints how both do on such runs.
"""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy import signal

# Measurement noise variance at standstill, m^2: (20 um)^2, the upper end of the rig's sensor
# noise (quantisation to 1 um adds only 1e-12/12 m^2). Overstating R a little costs less than
# understating it: the filter then follows the noise into x''.
R0_M2 = (20e-6) ** 2
# Variance of the per-step change of x'' in the white-noise-jerk model, (m/s^2)^2. Bar-Shalom's
# rule puts its std at 0.5-1 times the largest change of x'' in one step, A w^3 T = 2.1 m/s^2 at
# 20 mm / 6 Hz / 2 ms; q = 1 (std 1 m/s^2, about 0.5x) favours noise rejection on the slower
# runs. The benchmark prints the trade-off for other values.
Q_VAR = 1.0
# Initial spread of the unmeasured states after reset(): about the rig's largest |x'|, |x''|.
_XD0_STD_MPS = 1.0
_XDD0_STD_MPS2 = 50.0


class KalmanEstimator:
    """Constant-acceleration Kalman filter on displacement, state [x, x', x''] (paper eq. 21).

    Built on filterpy's `KalmanFilter` (exposed as `kf`): one `update` costs 15-30 us (median) on
    the project VM, under 1.5 % of the 2 ms cycle, so no hand-rolled or steady-state path
    is kept (and R changes every sample, so there is no fixed steady-state gain anyway).
    """

    def __init__(self, dt_s: float, q: float = Q_VAR, r0: float = R0_M2) -> None:
        if dt_s <= 0 or q <= 0 or r0 <= 0:
            raise ValueError("dt_s, q and r0 must be positive")
        self.dt_s = dt_s
        self.r0 = r0
        kf = KalmanFilter(dim_x=3, dim_z=1)
        # eq. 21: x_{k+1} = A x_k + w_k, constant acceleration over one sample period
        kf.F = np.array([[1.0, dt_s, 0.5 * dt_s * dt_s], [0.0, 1.0, dt_s], [0.0, 0.0, 1.0]])
        # eq. 22: y_k = x_k + v_k, only the displacement is measured
        kf.H = np.array([[1.0, 0.0, 0.0]])
        # eq. 23: white-noise-jerk process noise scaled by a factor (the paper's 200 is in its
        # own units); filterpy's discrete form is G G^T q with G = [T^2/2, T, 1].
        kf.Q = Q_discrete_white_noise(dim=3, dt=dt_s, var=q)
        self.kf = kf
        self.reset(0.0)

    def measurement_variance(self, xd_mps: float) -> float:
        """Eq. 24 as we read the mangled text: R = r0 / (1 + |x'|), x' in m/s.

        The paper prints r0 = 0.12 (perhaps 0.1^2) in its own units; we keep the form with an
        r0 for this rig. Faster motion -> smaller R -> the filter follows the sensor more
        closely, which keeps the lag small where the signal is largest.
        """
        return self.r0 / (1.0 + abs(xd_mps))

    def reset(self, x0: float) -> None:
        """Start at displacement x0 (m), at rest, with the unmeasured states uncertain."""
        self.kf.x = np.array([[x0], [0.0], [0.0]])
        self.kf.P = np.diag([self.r0, _XD0_STD_MPS**2, _XDD0_STD_MPS2**2])

    def predict_only(self) -> tuple[float, float, float]:
        """Advance one period without a measurement (a lost frame): the prediction is kept."""
        kf = self.kf
        kf.predict()  # eqs 25-26 (no input: B u = 0)
        kf.update(None)  # keeps the prior as posterior
        x = kf.x
        return float(x[0, 0]), float(x[1, 0]), float(x[2, 0])

    def update(self, x_meas: float | None) -> tuple[float, float, float]:
        """One 2-ms step: predict, then correct with x_meas (m); None means a missing sample.

        Returns the filtered (x, x', x'') in m, m/s, m/s^2.
        """
        if x_meas is None:
            return self.predict_only()
        kf = self.kf
        kf.predict()  # eq. 25: x = A x (B u = 0); eq. 26: P = A P A^T + Q
        # eq. 24 with the predicted x'_k, the best velocity known before this measurement
        kf.R[0, 0] = self.measurement_variance(kf.x[1, 0])
        # eq. 27: K = P H^T (H P H^T + R)^-1; eq. 28: x = x + K (y - H x);
        # eq. 29: P = (I - K H) P, which filterpy computes in the equivalent Joseph form
        kf.update(x_meas)
        x = kf.x
        return float(x[0, 0]), float(x[1, 0]), float(x[2, 0])

    def estimate(self, x_series: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Filter a whole series (offline, e.g. training data): reset to its first sample, then
        `update` every sample; NaN samples count as missing. Returns arrays (x, x', x'')."""
        xs = np.asarray(x_series, dtype=float)
        out = np.empty((xs.size, 3))
        if xs.size == 0:
            return out[:, 0], out[:, 1], out[:, 2]
        finite = np.isfinite(xs)
        if not finite.any():
            raise ValueError("x_series has no finite sample")
        self.reset(float(xs[finite][0]))
        for k, (value, ok) in enumerate(zip(xs.tolist(), finite.tolist(), strict=True)):
            out[k] = self.update(value if ok else None)
        return out[:, 0].copy(), out[:, 1].copy(), out[:, 2].copy()


class RealtimeKalman(KalmanEstimator):
    """The same filter with `update` in plain floats, for the 2-ms loop.

    filterpy's update costs 25-200 us in the daemon (array allocation, a 1x1 matrix inverse,
    the Joseph form); this one a few us. Equal to filterpy's to rounding (a test checks it);
    the covariance update is eq. 29's standard form P = (I - K H) P.

    Everything of a step but the correction by the measurement itself is known before the
    measurement arrives: the prediction (eqs 25-26), the gain (eq. 27, with R of eq. 24 from
    the predicted x') and the updated covariance (eq. 29). `prepare()` computes them ahead
    (the daemon calls it after it has answered a frame); `update` then only applies eq. 28,
    and the estimate is affine in the measurement: `prior + gain * (x_meas - prior[0])`.
    `update` prepares by itself when nobody did.
    """

    def reset(self, x0: float) -> None:
        super().reset(x0)
        self._x = [float(x0), 0.0, 0.0]
        p = self.kf.P
        self._p = [[float(p[i, j]) for j in range(3)] for i in range(3)]
        self._q = [[float(v) for v in row] for row in self.kf.Q]
        self._prepared = False

    def prepare(self) -> None:
        """The next step's prediction, gain and updated covariance (idempotent until `update`)."""
        if self._prepared:
            return
        T = self.dt_s
        h = 0.5 * T * T
        x0, x1, x2 = self._x
        self._prior = (x0 + T * x1 + h * x2, x1 + T * x2, x2)  # eq. 25
        P, Q = self._p, self._q
        # eq. 26: P = A P A^T + Q, A = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]]
        ap = [
            [P[0][j] + T * P[1][j] + h * P[2][j] for j in range(3)],
            [P[1][j] + T * P[2][j] for j in range(3)],
            [P[2][j] for j in range(3)],
        ]
        Pp = [
            [
                ap[i][0] + T * ap[i][1] + h * ap[i][2] + Q[i][0],
                ap[i][1] + T * ap[i][2] + Q[i][1],
                ap[i][2] + Q[i][2],
            ]
            for i in range(3)
        ]
        self._p_prior = Pp
        r = self.measurement_variance(self._prior[1])  # eq. 24 with the predicted x'
        s = Pp[0][0] + r
        k = (Pp[0][0] / s, Pp[1][0] / s, Pp[2][0] / s)  # eq. 27
        self._gain = k
        row0 = Pp[0]
        self._p_post = [[Pp[i][j] - k[i] * row0[j] for j in range(3)] for i in range(3)]  # eq. 29
        self._prepared = True

    @property
    def prior(self) -> tuple[float, float, float]:
        """The prepared prediction (x, x', x'') of the next step."""
        self.prepare()
        return self._prior

    @property
    def gain(self) -> tuple[float, float, float]:
        """The prepared Kalman gain of the next step (eq. 27)."""
        self.prepare()
        return self._gain

    def predict_only(self) -> tuple[float, float, float]:
        return self.update(None)

    def update(self, x_meas: float | None) -> tuple[float, float, float]:
        self.prepare()
        self._prepared = False
        x = self._prior
        if x_meas is None:  # the prediction is kept, with its covariance
            self._x = list(x)
            self._p = self._p_prior
            return x
        k = self._gain
        y = x_meas - x[0]
        self._x = [x[0] + k[0] * y, x[1] + k[1] * y, x[2] + k[2] * y]  # eq. 28
        self._p = self._p_post
        return self._x[0], self._x[1], self._x[2]


def finite_difference(
    x: np.ndarray, dt_s: float, cutoff_hz: float = 50.0, order: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Baseline: backward differences (eqs 15-16), then a causal Butterworth low-pass.

    Causal (`lfilter`, not `filtfilt`) so that it could run in the loop; a differentiator has
    no history at the start, so x'_0 = 0 and x''_0 = x''_1 = 0. The default 50 Hz, 2nd order
    is about the best single setting for this rig's runs (the benchmark sweeps the cutoff):
    lower cutoffs lag, higher ones pass the amplified noise.
    """
    x = np.asarray(x, dtype=float)
    xd = np.zeros_like(x)
    xdd = np.zeros_like(x)
    xd[1:] = (x[1:] - x[:-1]) / dt_s  # eq. 15
    xdd[2:] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / dt_s**2  # eq. 16
    b, a = signal.butter(order, cutoff_hz, fs=1.0 / dt_s)
    return signal.lfilter(b, a, xd), signal.lfilter(b, a, xdd)


def kalman_lanes(
    x_lanes: np.ndarray, dt_s: float, q: float = Q_VAR, r0: float = R0_M2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`KalmanEstimator.estimate` for many series side by side: x_lanes (L, T), one lane per
    row, each reset to its first sample; NaN samples count as missing (a lane shorter than T
    is padded with NaN at its end). The same equations (21-29) in numpy over the lanes, so
    the cost per sample falls with the number of lanes (training data of millions of rows)."""
    xs = np.asarray(x_lanes, dtype=float)
    lanes, n = xs.shape
    out = np.empty((3, lanes, n))
    if n == 0:
        return out[0], out[1], out[2]
    T, h = dt_s, 0.5 * dt_s * dt_s
    Q = Q_discrete_white_noise(dim=3, dt=dt_s, var=q)
    first = np.where(np.isfinite(xs[:, 0]), xs[:, 0], 0.0)
    s = [first.copy(), np.zeros(lanes), np.zeros(lanes)]
    p0 = np.diag([r0, _XD0_STD_MPS**2, _XDD0_STD_MPS2**2])
    P = [[np.full(lanes, p0[i, j]) for j in range(3)] for i in range(3)]
    for k in range(n):
        prior = (s[0] + T * s[1] + h * s[2], s[1] + T * s[2], s[2])  # eq. 25
        # eq. 26: P = A P A^T + Q
        ap = [
            [P[0][j] + T * P[1][j] + h * P[2][j] for j in range(3)],
            [P[1][j] + T * P[2][j] for j in range(3)],
            [P[2][j] for j in range(3)],
        ]
        Pp = [
            [
                ap[i][0] + T * ap[i][1] + h * ap[i][2] + Q[i, 0],
                ap[i][1] + T * ap[i][2] + Q[i, 1],
                ap[i][2] + Q[i, 2],
            ]
            for i in range(3)
        ]
        r = r0 / (1.0 + np.abs(prior[1]))  # eq. 24 with the predicted x'
        sk = Pp[0][0] + r
        gain = [Pp[i][0] / sk for i in range(3)]  # eq. 27
        meas = xs[:, k]
        seen = np.isfinite(meas)
        y = np.where(seen, meas - prior[0], 0.0)
        s = [prior[i] + gain[i] * y for i in range(3)]  # eq. 28 (y = 0: the prediction kept)
        row0 = Pp[0]
        P = [  # eq. 29 where measured, the prior where not
            [np.where(seen, Pp[i][j] - gain[i] * row0[j], Pp[i][j]) for j in range(3)]
            for i in range(3)
        ]
        out[0, :, k], out[1, :, k], out[2, :, k] = s
    return out[0], out[1], out[2]
