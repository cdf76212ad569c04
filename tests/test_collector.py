"""The garbage collector stays off the armed frames: no automatic collection while the rig is
armed, on again (after a collection) once it is disarmed, and on when the loop has ended."""

from __future__ import annotations

import gc

from tests.rig_harness import ScriptedRig


def test_no_automatic_collection_while_armed_and_it_is_back_after_the_disarm(tmp_path):
    assert gc.isenabled()
    with ScriptedRig(tmp_path) as rig:
        for _ in range(5):
            assert rig.exchange()["Mode"] == 1
        assert not gc.isenabled()
        assert rig.request({"cmd": "disarm"})["ok"]
        assert rig.exchange()["Mode"] == 0
        assert gc.isenabled()
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.exchange()["Mode"] == 1
        assert not gc.isenabled()
    assert gc.isenabled()
