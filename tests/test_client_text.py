"""What `mrrig status` and `mrrig watch` print for a person (pure: no daemon)."""

from __future__ import annotations

from mrrig.cli.client import format_status
from mrrig.rigio.client import no_telemetry_line

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
