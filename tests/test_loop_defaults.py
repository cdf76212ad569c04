"""A daemon's config that leaves out every optional field of `[loop]` runs on their defaults
(a rig on a virtual bus in threads: a process test, in a module of its own so that the config
refusals of tests/test_config_errors.py do not hold the machine alone)."""

from __future__ import annotations

import logging
import time

import pytest


@pytest.mark.process
def test_a_loop_section_without_its_optional_fields_runs_on_their_defaults(tmp_path, caplog):
    """Issue 40, finding 13: a `[loop]` that left out `max_frame_age_s` raised TypeError at
    start-up (the backlog's age compared with None). Every field of the daemon's config with a
    default is left out here but those a test on this machine needs; frames queue while the
    daemon starts, so that the backlog is discarded by the default frame age."""
    from mrrig.config import load_config
    from mrrig.loop.daemon import Daemon
    from tests.rig_harness import ThreadRig

    with ThreadRig() as rig:
        path = tmp_path / "rig.toml"
        path.write_text(
            f'[bus]\ninterface = "virtual"\nchannel = "{rig.channel}"\n'
            "[loop]\nrealtime = false\ntimeout_periods = 25\nduration_s = 0.5\n"
            '[controller]\nname = "constant"\n'
            "[telemetry]\nenabled = false\n[recording]\nenabled = false\n"
        )
        cfg = load_config(path)
        assert cfg.loop.max_frame_age_s is None and cfg.loop.frame_age_limit_s == 0.002
        time.sleep(0.2)  # the simulator streams
        with caplog.at_level(logging.INFO, logger="mrrig.loop.frame_age"):
            summary = Daemon(cfg).run()
    assert summary["frames_received"] > 0
    assert any("discarded" in r.getMessage() for r in caplog.records), "no backlog: not tested"
