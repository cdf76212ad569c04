"""What `mrrig status` and `mrrig watch` print for a person (pure: no daemon)."""

from __future__ import annotations

import datetime as dt
import json
import logging
import uuid

from mrrig.catalog.record import RunRecord
from mrrig.cli.client import format_status
from mrrig.rigio import audit
from mrrig.rigio.audit import parse_claims
from mrrig.rigio.client import no_telemetry_line
from mrrig.safe_text import MAX_CHARS, one_line

STATUS = {
    "rig": "rig1",
    "state": "FAULT",
    "armed": False,
    "controller": "network_inversion",
    "reference": "zenoh",
    "fault": "stale_reference",
    "fault_reason": "stale force reference: force_ref is 140 ms old (timeout 100 ms)",
    "t": 12.5,
    "frames_received": 6250,
    "lost_frames": 0,
}


def test_status_for_a_person_names_state_reference_fault_and_what_to_do():
    lines = format_status(STATUS).splitlines()
    assert lines[0] == "rig rig1: FAULT (SAFE 0 A), up 12.5 s"
    assert lines[1] == "  controller network_inversion, force reference zenoh"
    assert lines[2].startswith("  fault stale_reference: stale force reference: force_ref is")
    assert (
        lines[3] == "  after checking the rig: mrrig reset --rig rig1 (acknowledge), then mrrig arm"
    )
    assert "  frames_received  6250" in lines


def test_status_for_a_person_shows_the_recording_path_and_size():
    recording = {"path": "recordings/rig1.rrd", "bytes": 1234567, "frames": 6000}
    lines = format_status({**STATUS, "recording": recording}).splitlines()
    assert "  recording        recordings/rig1.rrd (1234567 bytes, 6000 samples)" in lines


def test_watch_without_telemetry_says_what_is_known_or_what_to_check():
    assert no_telemetry_line("rig1", 3, STATUS) == (
        "no telemetry for 3 s; the daemon's status says FAULT (fault"
        " stale force reference: force_ref is 140 ms old (timeout 100 ms))"
    )
    line = no_telemetry_line("rig1", 2, None)
    assert "mrrig status --rig rig1" in line and "telemetry.enabled" in line


# ---- issue 40, finding 14: claimed and user-given text is one bounded, printable line
def test_one_line_escapes_what_acts_and_bounds_what_is_long():
    assert one_line("rig\nINFO audit: forged") == "rig\\x0aINFO audit: forged"
    assert one_line("\x1b[2J\x1b[31mred\u202e\ud800") == "\\x1b[2J\\x1b[31mred\\u202e\\ud800"
    assert one_line("plain name-1_ä") == "plain name-1_ä"
    cut = one_line("h" * 3_000_000)
    assert cut == "h" * MAX_CHARS + f"...[{3_000_000 - MAX_CHARS} more characters]"


def test_forged_claims_give_one_audit_line_without_escapes_and_a_bounded_host(caplog):
    forged = {
        "zid": "abc",
        "user": "mallory\x1b[31m",
        "host": "pc\n2026-12-05 INFO mrrig.rigio.audit: audit: control arm from root@rig: accepted",
    }
    huge = {"zid": "abc", "user": "x", "host": "h" * 3_000_000}
    with caplog.at_level(logging.INFO, logger="mrrig.rigio.audit"):
        ev = audit.event(
            1.0,
            {"cmd": "arm"},
            {"ok": True},
            {"claimed": parse_claims(json.dumps(forged).encode())},
        )
        big = audit.event(
            1.0, {"cmd": "arm"}, {"ok": True}, {"claimed": parse_claims(json.dumps(huge).encode())}
        )
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and all("\n" not in line for line in lines)
    assert all("\x1b" not in line for line in lines)
    assert "\\x1b[31m" in ev["text"] and "\\x0a" in ev["requester"]["claimed"]["host"]
    host = big["requester"]["claimed"]["host"]
    assert len(host) < 400 and host.endswith(f"...[{3_000_000 - MAX_CHARS} more characters]")
    assert len(big["text"]) < 1000


def test_a_run_records_given_and_claimed_text_is_one_bounded_line():
    record = RunRecord(
        run_id=uuid.uuid4(),
        rig="rig1",
        started_utc=dt.datetime(2026, 12, 5, tzinfo=dt.UTC),
        host="pc\nforged row",
        operator="eve\x1b[2J",
        step="s" * 3_000_000,
        tags=["a\rb"],
    )
    assert record.host == "pc\\x0aforged row" and record.operator == "eve\\x1b[2J"
    assert record.tags == ["a\\x0db"]
    assert record.step.endswith(f"...[{3_000_000 - MAX_CHARS} more characters]")
