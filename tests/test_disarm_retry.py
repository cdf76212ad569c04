"""A disarm that the rig's control plane did not answer in time is asked again (mrrig.api.Rig):
on CI, three rigs on two cores, a plan step was aborted on "disarm: daemon did not answer"
although the daemon disarmed a second later. The control endpoint here is a Zenoh queryable on
127.0.0.1 that answers as an overloaded sidecar does (its `NO_ANSWER`, then `busy`), then ok."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from mrrig.api import Rig
from mrrig.api.live import DISARM_TRIES
from mrrig.rigio.rig_topics import keys
from mrrig.rigio.sidecar import NO_ANSWER
from mrrig.rigio.zenoh_config import load_zenoh_config
from tests.conftest import zenoh_configs

RIG = "disarm-retry-test"
OVERLOADED = [NO_ANSWER, {"ok": False, "error": "busy: the control plane is overloaded"}]


def _serve(tmp_path, answers: list[dict]):
    daemon_conf, client_conf, _ = zenoh_configs(tmp_path)
    session = zenoh.open(load_zenoh_config(daemon_conf))
    asked: list[dict] = []

    def on_query(query: zenoh.Query) -> None:
        asked.append(json.loads(query.payload.to_string()))
        reply = answers[len(asked) - 1] if len(asked) <= len(answers) else {"ok": True}
        query.reply(query.key_expr, json.dumps(reply))
        query.drop()

    queryable = session.declare_queryable(keys(RIG)["control"], on_query)
    time.sleep(0.3)
    return session, queryable, client_conf, asked


def test_a_disarm_the_daemon_did_not_answer_is_asked_again_until_it_is(tmp_path):
    session, queryable, client_conf, asked = _serve(tmp_path, OVERLOADED)
    try:
        with Rig(RIG, client_conf, timeout_s=2.0) as rig:
            assert rig.disarm() == {"ok": True}
    finally:
        queryable.undeclare()
        session.close()
    assert asked == [{"cmd": "disarm"}] * 3


def test_a_disarm_still_unanswered_after_its_tries_is_an_error_and_a_refusal_is_not_asked_again(
    tmp_path,
):
    answers = [NO_ANSWER] * DISARM_TRIES + [{"ok": False, "error": "no such rig state"}]
    session, queryable, client_conf, asked = _serve(tmp_path, answers)
    try:
        with Rig(RIG, client_conf, timeout_s=2.0) as rig:
            with pytest.raises(Exception, match="disarm: daemon did not answer"):
                rig.disarm()
            assert len(asked) == DISARM_TRIES
            with pytest.raises(Exception, match="disarm: no such rig state"):
                rig.disarm()  # an error that is the daemon's answer: not asked again
    finally:
        queryable.undeclare()
        session.close()
    assert len(asked) == DISARM_TRIES + 1


def test_an_arm_the_daemon_did_not_answer_is_disarmed_then_asked_again(tmp_path):
    """The lost arm may have armed the rig under a lease no client holds: disarm first."""
    answers = [NO_ANSWER, {"ok": True}, OVERLOADED[1], {"ok": True}]
    session, queryable, client_conf, asked = _serve(tmp_path, answers)
    try:
        with Rig(RIG, client_conf, timeout_s=2.0) as rig:
            assert rig.arm() == {"ok": True}
            n = len(asked)
    finally:
        queryable.undeclare()
        session.close()
    assert asked[:n] == [{"cmd": "arm"}, {"cmd": "disarm"}, {"cmd": "arm"}, {"cmd": "disarm"}] + [
        {"cmd": "arm"}
    ]


def test_an_arm_refused_by_the_daemon_is_not_asked_again(tmp_path):
    answers = [{"ok": False, "error": "not allowed: the actuator is off"}]
    session, queryable, client_conf, asked = _serve(tmp_path, answers)
    try:
        with Rig(RIG, client_conf, timeout_s=2.0) as rig:
            with pytest.raises(Exception, match="arm: not allowed: the actuator is off"):
                rig.arm()
            n = len(asked)
    finally:
        queryable.undeclare()
        session.close()
    assert asked[:n] == [{"cmd": "arm"}]


def test_a_status_the_control_plane_did_not_answer_is_told_apart_from_a_refusal(tmp_path):
    """A plan asks a loaded rig's status again within its patience (mrrig.plans.runner): on CI
    three rigs on two cores answered "busy" and the plan ended with an error (exit 2)."""
    from mrrig.api.live import RigError, RigUnanswered

    answers = [OVERLOADED[1], NO_ANSWER, {"ok": False, "error": "unknown command"}]
    session, queryable, client_conf, _asked = _serve(tmp_path, answers)
    try:
        with Rig(RIG, client_conf, timeout_s=2.0) as rig:
            for _ in OVERLOADED:
                with pytest.raises(RigUnanswered):
                    rig.status()
            with pytest.raises(RigError) as refused:
                rig.status()
            assert not isinstance(refused.value, RigUnanswered)
    finally:
        queryable.undeclare()
        session.close()
