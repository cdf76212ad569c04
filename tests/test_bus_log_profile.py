"""`mrrig review --can-log` with the run's rig profile (a lab's DBC: its own IDs, units, no
E2E): the log decodes with the profile's DBC and matches the recording."""

from __future__ import annotations

import cantools
import numpy as np

from mrrig.pycan import can
from mrrig.rigio.canlog import check_bus_log
from tests.conftest import REPO


def test_a_lab_profiles_bus_log_decodes_with_its_dbc_and_matches(tmp_path):
    """Issue 42: `review --can-log` decoded every log with the contract's DBC and reported a
    correct log of a lab's rig (its own IDs, mm and kN, no E2E) as MISMATCH. With the run's
    rig profile (`--config`), the log's sensor frames are the recording's."""
    from mrrig.config import load_config
    from mrrig.loop.samples import SAMPLE_DTYPE
    from mrrig.rigio.canbus.profile import load_profile
    from mrrig.rigio.canlog import BusLogWriter

    cfg = load_config(REPO / "configs/profiles/lab-1khz.toml")
    profile = load_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source)
    db = cantools.database.load_file(str(REPO / "configs/profiles/lab-1khz.dbc"))
    n = 200
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = np.arange(n) * 1e-3
    s["x"] = np.round(0.01 * np.sin(2 * np.pi * 2.0 * s["t"]) * 1e6) / 1e6  # whole um
    s["f_meas"] = np.round(500.0 * np.cos(2 * np.pi * 2.0 * s["t"]) * 100) / 100  # whole 10 mN
    log = tmp_path / "lab.log"
    writer = BusLogWriter(log)
    for k in range(n):
        for name, values, rx in (
            ("LabSensors", {"Position": s["x"][k] * 1e3, "Load": s["f_meas"][k] * 1e-3,
                            "Enabled": 1, "EStop": 0, "Fault": 0, "Coil": 500}, True),
            ("HostCommand", {"Active": 1, "Current": 500.0, "Force": 0.0}, False),
        ):  # fmt: skip
            msg = db.get_message_by_name(name)
            writer._writer.on_message_received(
                can.Message(timestamp=float(s["t"][k]), arbitration_id=msg.frame_id,
                            data=msg.encode(values), is_rx=rx, is_extended_id=False)
            )  # fmt: skip
    writer.close()
    summary = {"sensor_frames_valid": n, "sensor_frames_invalid": 0, "commands_sent": n}
    check = check_bus_log(log, s, summary, profile)
    assert check.ok, check.text()
    assert check.rx_sensor_frames == n and check.tx_commands == n
    assert "matches the recording" in check.text()
    contract = check_bus_log(log, s, summary)  # the contract's DBC: the old report
    assert not contract.ok and "MISMATCH" in contract.text()
