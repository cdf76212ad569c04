"""The numerical substructures of spec/hil.md: a quarter car on a road and a shear building under
ground motion, each a linear model stepped exactly (zero-order hold of its state-space model,
computed once), one step per sensor frame, with the measured damper force as an input.

Sign conventions (spec/hil.md, Conventions): the damper stroke s is positive in extension; the
damper force F is the load cell's, positive in tension, so the damper pulls the mass above it
down by F and the mass below it up by F. A damper resists: F ~ +c s', and the power it delivers
to the masses is -F s' (a passive run has sum F s' dt > 0).

Each substructure is driven by an excitation record (the road under the wheel, the ground
acceleration), one sample per frame, held over the frame. `step(force_n)` takes the force
measured at frame k (the answer to the stroke commanded before), records the outputs at frame
k and advances to frame k + 1, whose stroke is the next setpoint.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm


def zoh(a: np.ndarray, b: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation with the inputs held over dt: [[Ad, Bd], [0, I]] = expm([[A, B],
    [0, 0]] dt) (the spec's 'exact discretisation of the linear part')."""
    n, m = b.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = a, b
    phi = expm(block * dt_s)
    return phi[:n, :n], phi[:n, n:]


_FRACTIONS = 100


@functools.lru_cache(maxsize=8)
def _fraction_table(
    a_key: bytes, b_key: bytes, n: int, m: int, period_s: float
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The exact steps of 0, 1, ..., 100 % of a frame of the model (A, B) given as bytes,
    computed once per process: 101 matrix exponentials took 0.6-2.5 s on a loaded 2-core VM,
    and a run builds its substructure at its first frame (a building's arm frame answered
    1.4 s late: a stall fault). The daemon builds one at start (`HilLoop`), so a run's
    first frame finds them here."""
    a = np.frombuffer(a_key).reshape(n, n)
    b = np.frombuffer(b_key).reshape(n, m)
    steps = tuple(zoh(a, b, j / _FRACTIONS * period_s) for j in range(_FRACTIONS + 1))
    for ad, bd in steps:
        ad.setflags(write=False)
        bd.setflags(write=False)
    return steps


class _Predicting:
    """The model's own prediction of its stroke `lead_frames` ahead (whole and fractional
    frames): the exact step with the last measured force held and the excitation record ahead
    (known: the road, the ground motion). The model-based delay compensation sends it."""

    a: np.ndarray
    b: np.ndarray
    x: np.ndarray
    k: int
    period_s: float
    force_n: float
    _ad: np.ndarray
    _bd: np.ndarray
    _excitation: np.ndarray
    _fractions: tuple[tuple[np.ndarray, np.ndarray], ...]

    def _fraction_steps(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """The exact steps of 0, 1, ..., 100 % of a frame, computed once per model (a
        fraction's step is then a look-up in the loop, never an expm; the last is the whole
        frame's)."""
        a, b = np.ascontiguousarray(self.a, float), np.ascontiguousarray(self.b, float)
        return _fraction_table(a.tobytes(), b.tobytes(), *b.shape, self.period_s)

    def predicted_state(self, lead_frames: float) -> np.ndarray:
        whole = int(lead_frames)
        x = self.x
        last = self._excitation.size - 1
        for j in range(whole):
            x = self._ad @ x + self._bd @ np.array(
                [self.force_n, self._excitation[min(self.k + j, last)]]
            )
        j = round((lead_frames - whole) * _FRACTIONS)  # to 1 % of a frame (20 us at 500 Hz)
        if j > 0:
            ad, bd = self._fractions[j]
            x = ad @ x + bd @ np.array([self.force_n, self._excitation[min(self.k + whole, last)]])
        return x


@dataclass(frozen=True)
class QuarterCarParams:
    """A passenger car's corner (spec/hil.md: 250-400 kg, 35-45 kg, 16-25 kN/m, 160-230 kN/m)."""

    m_s_kg: float = 300.0
    m_u_kg: float = 40.0
    k_s_n_per_m: float = 20_000.0
    k_t_n_per_m: float = 190_000.0

    def check(self) -> None:
        for name in ("m_s_kg", "m_u_kg", "k_s_n_per_m", "k_t_n_per_m"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")


class QuarterCar(_Predicting):
    """Sprung and unsprung masses, suspension spring, tyre; the damper between them.

    State x = [z_s, z_s', z_u, z_u'] from the static equilibrium, input [F, z_r]:
        m_s z_s'' = -k_s s - F                        (spec/hil.md, Conventions)
        m_u z_u'' =  k_s s + F - k_t (z_u - z_r)      s = z_s - z_u
    """

    def __init__(self, params: QuarterCarParams, road_m: np.ndarray, period_s: float) -> None:
        p = params
        self.params, self.period_s = p, period_s
        self._road = self._excitation = np.asarray(road_m, dtype=float)
        self.a = np.array(
            [
                [0.0, 1.0, 0.0, 0.0],
                [-p.k_s_n_per_m / p.m_s_kg, 0.0, p.k_s_n_per_m / p.m_s_kg, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [p.k_s_n_per_m / p.m_u_kg, 0.0, -(p.k_s_n_per_m + p.k_t_n_per_m) / p.m_u_kg, 0.0],
            ]
        )
        self.b = np.array(
            [
                [0.0, 0.0],
                [-1.0 / p.m_s_kg, 0.0],
                [0.0, 0.0],
                [1.0 / p.m_u_kg, p.k_t_n_per_m / p.m_u_kg],
            ]
        )
        self._fractions = self._fraction_steps()
        self._ad, self._bd = self._fractions[-1]
        self.reset()

    @property
    def steps(self) -> int:
        """How many frames the excitation record holds."""
        return self._road.size - 1

    def reset(self) -> None:
        """At rest in static equilibrium on the road's first height (body and wheel at
        z_r[0]): stroke 0, no tyre deflection. From zeros, a road that starts 17 mm off
        dropped the car onto it at over 1 m/s in the first 16 ms, beyond the actuator."""
        z0 = float(self._road[0]) if self._road.size else 0.0
        self.x = np.array([z0, 0.0, z0, 0.0])
        self.k = 0
        self.force_n = 0.0
        self.body_acceleration_m_s2 = 0.0
        self.tyre_load_n = 0.0

    @property
    def stroke_m(self) -> float:
        return float(self.x[0] - self.x[2])

    @property
    def stroke_velocity_m_s(self) -> float:
        return float(self.x[1] - self.x[3])

    def predicted_stroke(self, lead_frames: float) -> tuple[float, float]:
        """(s, s') `lead_frames` ahead, the measured force held."""
        x = self.predicted_state(lead_frames)
        return float(x[0] - x[2]), float(x[1] - x[3])

    @property
    def body_velocity_m_s(self) -> float:
        return float(self.x[1])

    @property
    def wheel_velocity_m_s(self) -> float:
        return float(self.x[3])

    def step(self, force_n: float) -> None:
        """Frame k's outputs with the measured force, then advance to frame k + 1."""
        p, z_r = self.params, self._road[self.k]
        s = self.stroke_m
        self.body_acceleration_m_s2 = (-p.k_s_n_per_m * s - force_n) / p.m_s_kg
        # the dynamic tyre load, compression positive (the static m g left out)
        self.tyre_load_n = p.k_t_n_per_m * (z_r - self.x[2])
        self.x = self._ad @ self.x + self._bd @ np.array([force_n, z_r])
        self.k += 1
        self.force_n = force_n

    def control_state(self) -> np.ndarray:
        """[s, z_s', z_u - z_r, z_u']: the coordinates the LQR of `control_model` uses."""
        return np.array([self.stroke_m, self.x[1], self.x[2] - self._road[self.k], self.x[3]])

    @staticmethod
    def default_lqr_weights() -> tuple[float, ...]:
        """Body acceleration (m/s^2)^-2, suspension travel and tyre deflection m^-2."""
        return (1.0, 1.0e4, 1.0e5)

    def control_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, D) in the coordinates of `control_state`, input F (the road velocity a
        disturbance), performance outputs y = [z_s'', s, z_u - z_r] = C x + D F."""
        p = self.params
        ks, kt, ms, mu = p.k_s_n_per_m, p.k_t_n_per_m, p.m_s_kg, p.m_u_kg
        a = np.array(
            [
                [0.0, 1.0, 0.0, -1.0],
                [-ks / ms, 0.0, 0.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [ks / mu, 0.0, -kt / mu, 0.0],
            ]
        )
        b = np.array([[0.0], [-1.0 / ms], [0.0], [1.0 / mu]])
        c = np.array([[-ks / ms, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
        d = np.array([[-1.0 / ms], [0.0], [0.0]])
        return a, b, c, d


@dataclass(frozen=True)
class BuildingParams:
    """A shear frame, the damper between the ground and the first floor. Defaults: the
    three-storey scale model of Dyke, Spencer, Sain & Carlson (1996): floors of 98.3 kg, its
    stiffness and damping matrices written as storey values (K = 1e5 [12.0 -6.84 0; -6.84 13.7
    -6.84; 0 -6.84 6.84] N/m, C = [175 -50 0; -50 100 -50; 0 -50 50] N s/m)."""

    masses_kg: tuple[float, ...] = (98.3, 98.3, 98.3)
    storey_stiffness_n_per_m: tuple[float, ...] = (5.16e5, 6.84e5, 6.84e5)
    storey_damping_n_s_per_m: tuple[float, ...] = (125.0, 50.0, 50.0)

    def check(self) -> None:
        n = len(self.masses_kg)
        if not 1 <= n <= 6:
            raise ValueError(f"masses_kg: 1 to 6 storeys, got {n}")
        for name in ("storey_stiffness_n_per_m", "storey_damping_n_s_per_m"):
            if len(getattr(self, name)) != n:
                raise ValueError(
                    f"{name}: one value per storey ({n}), got {len(getattr(self, name))}"
                )
        if min(self.masses_kg) <= 0.0 or min(self.storey_stiffness_n_per_m) <= 0.0:
            raise ValueError("masses_kg: masses and storey stiffnesses must be positive")
        if min(self.storey_damping_n_s_per_m) < 0.0:
            raise ValueError("storey_damping_n_s_per_m: must not be negative")


def _storey_matrix(values: tuple[float, ...]) -> np.ndarray:
    """The tridiagonal matrix of a shear frame from its storey values (storey i between floor
    i - 1 and floor i, floor 0 the ground)."""
    n = len(values)
    k = np.zeros((n, n))
    for i, v in enumerate(values):
        k[i, i] += v
        if i > 0:
            k[i - 1, i - 1] += v
            k[i - 1, i] -= v
            k[i, i - 1] -= v
    return k


class ShearBuilding(_Predicting):
    """M q'' + C q' + K q = -M 1 a_g - e_1 F  (q: floor displacements relative to the ground;
    the damper's stroke is the first storey's drift q_1, its tension pulls floor 1 down).

    State x = [q, q'], input [F, a_g].
    """

    def __init__(self, params: BuildingParams, ground_m_s2: np.ndarray, period_s: float) -> None:
        self.params, self.period_s = params, period_s
        self._ground = self._excitation = np.asarray(ground_m_s2, dtype=float)
        n = len(params.masses_kg)
        m_inv = np.diag(1.0 / np.asarray(params.masses_kg))
        k = _storey_matrix(params.storey_stiffness_n_per_m)
        c = _storey_matrix(params.storey_damping_n_s_per_m)
        self.n = n
        self.a = np.block([[np.zeros((n, n)), np.eye(n)], [-m_inv @ k, -m_inv @ c]])
        e1 = np.zeros(n)
        e1[0] = 1.0
        self.b = np.zeros((2 * n, 2))
        self.b[n:, 0] = -m_inv @ e1
        self.b[n:, 1] = -1.0
        self._fractions = self._fraction_steps()
        self._ad, self._bd = self._fractions[-1]
        self.reset()

    @property
    def steps(self) -> int:
        return self._ground.size - 1

    def reset(self) -> None:
        self.x = np.zeros(2 * self.n)
        self.k = 0
        self.force_n = 0.0
        self.drifts_m = np.zeros(self.n)
        self.accelerations_m_s2 = np.zeros(self.n)

    @property
    def stroke_m(self) -> float:
        return float(self.x[0])

    @property
    def stroke_velocity_m_s(self) -> float:
        return float(self.x[self.n])

    def predicted_stroke(self, lead_frames: float) -> tuple[float, float]:
        """(s, s') `lead_frames` ahead, the measured force held."""
        x = self.predicted_state(lead_frames)
        return float(x[0]), float(x[self.n])

    def step(self, force_n: float) -> None:
        """Frame k's drifts and absolute accelerations with the measured force, then advance."""
        a_g = self._ground[self.k]
        u = np.array([force_n, a_g])
        q = self.x[: self.n]
        self.drifts_m = np.diff(q, prepend=0.0)
        # absolute acceleration: q'' + a_g
        self.accelerations_m_s2 = (self.a @ self.x + self.b @ u)[self.n :] + a_g
        self.x = self._ad @ self.x + self._bd @ u
        self.k += 1
        self.force_n = force_n

    def control_state(self) -> np.ndarray:
        return self.x.copy()

    def default_lqr_weights(self) -> tuple[float, ...]:
        """Storey drifts m^-2, then relative floor accelerations (m/s^2)^-2."""
        return (1.0e6,) * self.n + (1.0,) * self.n

    def control_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, D), input F, performance outputs y = [drifts, relative accelerations]."""
        n = self.n
        drift = np.eye(n) - np.eye(n, k=-1)
        c = np.vstack([np.hstack([drift, np.zeros((n, n))]), self.a[n:, :]])
        d = np.vstack([np.zeros((n, 1)), self.b[n:, :1]])
        return self.a, self.b[:, :1], c, d
