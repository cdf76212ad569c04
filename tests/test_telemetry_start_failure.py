"""A telemetry process that cannot start (its port taken) stops the daemon before its loop runs
unobserved: one `error:` line naming the cause and the way out, exit code 2 (a process module:
the daemon on a bridge; the other set-up errors are tests/test_lifecycle_errors.py's)."""

from __future__ import annotations

import socket

import pytest

from tests.conftest import rig_config, zenoh_configs
from tests.test_lifecycle_errors import NO_MODEL, mrrig, one_error_line


@pytest.mark.process
def test_a_telemetry_process_that_cannot_start_stops_the_daemon(tmp_path, bridge):
    zcfg, _, _ = zenoh_configs(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        zcfg.write_text(
            f'{{mode: "peer", listen: {{endpoints: ["tcp/127.0.0.1:{taken.getsockname()[1]}"]}},'
            " scouting: {multicast: {enabled: false}}}"
        )
        cfg = rig_config(
            tmp_path,
            bridge,
            None,
            telemetry={"enabled": True, "zenoh_config": str(zcfg)},
            **NO_MODEL,
        )
        proc = mrrig("run", "--config", str(cfg), "--duration", "30", "--no-record")
    line = one_error_line(proc)
    assert "telemetry process could not start" in line and "Address already in use" in line
    assert "telemetry.enabled = false" in line
    assert "loop running" not in proc.stderr  # its loop never ran unobserved
    assert "frames" not in proc.stdout  # no run, so no summary
