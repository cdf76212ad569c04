"""Live telemetry's DataFrame carries `utc` beside the run's time `t_s` (issue 42: telemetry
DataFrames lack `utc`): the sidecar's message gives the run's UTC start, `mrrig.api.Telemetry`
adds it to each sample's `t_s`; over real Zenoh sessions on 127.0.0.1, in one process."""

from __future__ import annotations

import datetime as dt
import json
import threading

import numpy as np
import zenoh

from mrrig.api import Telemetry
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.rig_topics import keys, telemetry_json
from mrrig.rigio.zenoh_config import local_config

RIG = "utc1"
STARTED = dt.datetime(2026, 3, 4, 5, 6, 7, 123456, tzinfo=dt.UTC)


def _batch(k: int, n: int = 10) -> np.ndarray:
    batch = np.zeros(n, SAMPLE_DTYPE)
    batch["t"] = (k * n + np.arange(n)) * 0.002
    batch["f_meas"] = 100.0 + k
    return batch


def test_a_telemetry_message_carries_the_runs_utc_start_when_known():
    message = json.loads(telemetry_json(RIG, _batch(0), STARTED.isoformat()))
    assert message["utc_start"] == "2026-03-04T05:06:07.123456+00:00"
    assert message["fields"]["t"][1] == 0.002
    assert "utc_start" not in json.loads(telemetry_json(RIG, _batch(0)))


def test_live_telemetrys_frame_has_utc_the_runs_start_plus_t_s():
    port = find_free_port()
    rig = zenoh.open(local_config("peer", listen=[f"tcp/127.0.0.1:{port}"]))
    client = zenoh.open(local_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        tele = Telemetry(client, RIG, duration_s=None, quiet_s=1.0)
        pub = rig.declare_publisher(keys(RIG)["telemetry"])
        done = threading.Event()

        def feed() -> None:  # 50 batches at 50 Hz, as the sidecar sends them
            for k in range(50):
                pub.put(telemetry_json(RIG, _batch(k), STARTED.isoformat()))
                if done.wait(0.02):
                    return

        feeder = threading.Thread(target=feed)
        feeder.start()
        try:
            batches = list(tele)
        finally:
            done.set()
            feeder.join()
        pub.undeclare()
        assert batches, "no telemetry arrived"
        frame = tele.to_pandas()
        assert tele.utc_start == STARTED
        assert list(frame.columns[:2]) == ["utc", "t_s"] and len(frame) == tele.samples.size
        t0_ns = int(STARTED.timestamp()) * 1_000_000_000 + STARTED.microsecond * 1000
        utc_ns = np.array([ts.value for ts in frame["utc"]])  # pandas Timestamps: ns
        assert np.array_equal(utc_ns, t0_ns + np.round(frame["t_s"].to_numpy() * 1e9))
        assert str(frame["utc"].dt.tz) == "UTC"
    finally:
        client.close()
        rig.close()
