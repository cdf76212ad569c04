"""The per-cycle telemetry sample: one record per valid sensor frame.

The rig daemon fills one record per cycle into a preallocated numpy buffer and hands full
batches off (never blocking) to the telemetry process, which publishes them on Zenoh and writes
them to the Rerun recording. The same field names are the JSON keys on `mrrig/<rig>/telemetry`
and the entity names in the recording.
"""

from __future__ import annotations

import enum

import numpy as np


class RigState(enum.IntEnum):
    """The daemon's safety states (spec/system.md, Safety)."""

    IDLE = 0
    ARMED = 1
    FAULT = 2


SAMPLE_DTYPE = np.dtype(
    [
        ("t", "f8"),  # sensor time, s since the daemon started (frame receive time)
        ("counter", "u1"),  # E2E counter of the RigSensors frame this sample answers
        ("x", "f8"),  # measured displacement, m
        ("x_est", "f8"),  # Kalman-filtered displacement, m
        ("xd", "f8"),  # estimated velocity, m/s
        ("xdd", "f8"),  # estimated acceleration, m/s^2
        ("f_meas", "f8"),  # load-cell force, N
        ("f_des", "f8"),  # desired force, N
        ("f_model", "f8"),  # forward-model force at the commanded current, N
        ("i_cmd", "f8"),  # commanded current, A (0 when SAFE)
        ("i_meas", "f8"),  # measured coil current (latest RigStatus), A
        ("latency_us", "f8"),  # receive -> send of this cycle, microseconds
        ("adapt_gain", "f8"),  # on-line adaptation's gain on the model force (NaN: none)
        ("adapt_offset_n", "f8"),  # and its offset, N
        ("temp_degc", "f8"),  # damper temperature (latest RigStatus), degC
        ("state", "u1"),  # RigState
        # the frame against the model's training envelope (mrrig/loop/coverage.py): 0 inside,
        # else a bit per input outside its range; NaN where the model keeps no envelope
        ("outside", "f8"),
        # the hybrid simulation's (mrrig/loop/hil_loop.py; NaN without one): the model's frame
        # index, x_c (its stroke for this frame, m), the setpoint sent (m), the delay
        # estimate (s), the body's (building: roof's) absolute acceleration (m/s^2), the
        # dynamic tyre load (N)
        ("hil_k", "f8"),
        ("hil_x_c", "f8"),
        ("hil_setpoint", "f8"),
        ("hil_delay_s", "f8"),
        ("hil_acc", "f8"),
        ("hil_load_n", "f8"),
        # the model's states beside the rig's stroke and force (the recording's "Hybrid
        # simulation" tab): the quarter car's body and wheel displacement (m, from the static
        # equilibrium) and velocity (m/s); the building's storey 2 and 3 drifts (m; storey 1's
        # is x_c, the damper's stroke); NaN where the model has none
        ("hil_z_body", "f8"),
        ("hil_v_body", "f8"),
        ("hil_z_wheel", "f8"),
        ("hil_v_wheel", "f8"),
        ("hil_drift_2", "f8"),
        ("hil_drift_3", "f8"),
    ]
)

FIELDS: tuple[str, ...] = SAMPLE_DTYPE.names
