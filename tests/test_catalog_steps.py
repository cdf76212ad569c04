"""Issue 42: a plan step's run is registered while the daemon's recording is still being
written (no sha256 yet, `check_recording` said "unchecked"); once the daemon's own run is
registered with the closed recording's sha256, the step's row has it too and is checked."""

from __future__ import annotations

import uuid
from datetime import timedelta

from mrrig.api.catalog import check_recording, get_run, register_run
from mrrig.catalog import find_runs
from tests.test_catalog import T0, pg_server, url  # noqa: F401 - the fixtures

__all__ = ["pg_server", "url"]


def test_the_daemons_closed_recording_gives_its_sha256_to_the_steps_inside_it(url, tmp_path):
    rrd = tmp_path / "rig1-20260101T000000Z.rrd"
    rrd.write_bytes(b"a recording being written")
    steps = [
        register_run(
            "rig1",
            T0 + timedelta(seconds=10 * k),
            catalog=url,
            plan="p",
            step=f"s{k}",
            recording_path=str(rrd.resolve()),
        )  # fmt: skip
        for k in range(2)
    ]
    other = register_run("rig1", T0, catalog=url, recording_path=str(tmp_path / "other.rrd"))
    assert check_recording(get_run(steps[0].run_id, url)).startswith("unchecked")
    rrd.write_bytes(b"a recording being written, now closed")
    daemon = register_run("rig1", T0, catalog=url, run_id=uuid.uuid4(), recording=rrd)
    for step in steps:
        row = get_run(step.run_id, url)
        assert row.recording_sha256 == daemon.recording_sha256 is not None
        assert check_recording(row) == "unchanged"
    assert get_run(other.run_id, url).recording_sha256 is None  # another recording's
    assert len(find_runs(url)) == 4
    rrd.write_bytes(b"changed after the run")
    assert check_recording(get_run(steps[1].run_id, url)).startswith("changed")
