"""Zenoh telemetry and control, and the Rerun recording, with the simulator and the daemon as
separate processes (issue: telemetry, recording and review)."""

from __future__ import annotations

import collections
import json
import math
import signal
import time

import numpy as np
import pytest
import zenoh

from mrrig.cli.review import main as review_main
from mrrig.offline.review import read_recording, verify_rrd
from mrrig.rigio.lease import Lease
from mrrig.rigio.rig_topics import keys
from mrrig.rigio.zenoh_config import local_config
from tests.conftest import rig_config, zenoh_configs
from tests.stall_proof import explain

pytestmark = pytest.mark.process
RIG = "e2e"


def _open_when_up(port: int, timeout_s: float = 30.0) -> zenoh.Session:
    """A client session to the daemon's sidecar, once it listens."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(local_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _query(session: zenoh.Session, payload: bytes | str, timeout_s: float = 3.0) -> dict:
    for reply in session.get(f"mrrig/{RIG}/control", payload=payload, timeout=timeout_s):
        assert reply.ok is not None, reply.err.payload.to_string()
        return json.loads(reply.ok.payload.to_bytes())
    raise AssertionError("no reply from the daemon")


class _Collect:
    """A subscriber callback keeping the decoded samples until drained. Zenoh's default
    handler is a FIFO of 256 samples that blocks the session's receiving thread when full:
    5 s of telemetry not drained would hold up the replies to control queries as well."""

    def __init__(self) -> None:
        self._samples: collections.deque[dict] = collections.deque()

    def __call__(self, sample: zenoh.Sample) -> None:
        self._samples.append(json.loads(sample.payload.to_bytes()))

    def drain(self) -> list[dict]:
        out = []
        while self._samples:
            out.append(self._samples.popleft())
        return out


def test_telemetry_control_recording_and_review(tmp_path, bridge, procs, sim_model, capsys):
    zcfg, _, port = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        bridge,
        sim_model,
        rig={"name": RIG},
        telemetry={"enabled": True, "zenoh_config": str(zcfg), "rate_hz": 50.0},
    )
    rrd = tmp_path / "run.rrd"
    summary_path = tmp_path / "summary.json"
    sim_stats = tmp_path / "sim.json"
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--measure-echo", "--stats", str(sim_stats)]
    )  # fmt: skip
    daemon = procs(
        [
            "-m",
            "mrrig",
            "run",
            "--config",
            str(cfg),
            "--record",
            str(rrd),
            "--summary-json",
            str(summary_path),
        ]
    )
    session = _open_when_up(port)
    try:
        telemetry, events = _Collect(), _Collect()
        subscribers = [
            session.declare_subscriber(f"mrrig/{RIG}/{key}", collect)
            for key, collect in (("telemetry", telemetry), ("events", events))
        ]
        deadline = time.monotonic() + 30
        status = None
        while time.monotonic() < deadline:
            try:
                status = _query(session, json.dumps({"cmd": "status"}), timeout_s=1.0)
                break
            except AssertionError:
                time.sleep(0.5)
        assert status is not None and status["ok"], "daemon never answered on Zenoh"
        # IDLE, or FAULT if a stall faulted it: every fault of the run is proved a measured
        # stall at the end; arming below is the explicit re-arm
        st = status["status"]
        assert st["state"] in ("IDLE", "FAULT"), st
        alive = session.liveliness().get(keys(RIG)["alive"], timeout=2.0)
        assert any(r.ok is not None for r in alive), "no liveliness token"

        # -- telemetry at the configured rate
        telemetry.drain()
        time.sleep(1.0)  # past any start-up backlog
        telemetry.drain()
        t0 = time.monotonic()
        time.sleep(2.0)
        batches = telemetry.drain()
        elapsed = time.monotonic() - t0
        rate = len(batches) / elapsed
        n_samples = sum(len(b["fields"]["t"]) for b in batches)
        print(f"telemetry: {rate:.1f} batches/s, {n_samples / elapsed:.0f} samples/s")
        assert 35 <= rate <= 60
        assert 400 <= n_samples / elapsed <= 560

        # -- control requests: bad ones change nothing
        assert _query(session, b"{not json")["ok"] is False
        assert _query(session, json.dumps([1, 2]))["ok"] is False
        bad = _query(session, json.dumps({"cmd": "fly"}))
        assert bad["ok"] is False and "unknown command" in bad["error"]
        bad = _query(
            session,
            json.dumps(
                {"cmd": "actuator", "waveform": "sine", "amplitude_m": 0.5, "frequency_hz": 2.0}
            ),
        )
        assert bad["ok"] is False and "amplitude_m" in bad["error"]
        bad = _query(
            session, json.dumps({"cmd": "set_controller", "name": "constant", "current_a": 9.0})
        )
        assert bad["ok"] is False and "current_a" in bad["error"]
        bad = _query(session, json.dumps({"cmd": "set_profile", "kind": "sine", "freq_hz": -1.0}))
        assert bad["ok"] is False and "freq_hz" in bad["error"]
        st = _query(session, json.dumps({"cmd": "status"}))["status"]
        assert st["controller"] == "network_inversion" and st["reference"] == "bouc_wen"

        # -- good ones work
        ok = _query(
            session,
            json.dumps(
                {"cmd": "actuator", "waveform": "sine", "amplitude_m": 0.012, "frequency_hz": 2.5}
            ),
        )
        assert ok["ok"] and ok["waveform"] == "sine"
        assert _query(session, json.dumps({"cmd": "reset"}))["ok"]  # a stall's FAULT, if any
        armed = _query(session, json.dumps({"cmd": "arm"}))
        assert armed["ok"]
        # held as a client holds the rig: its lease renewed (issue 40), or it would lapse
        lease = Lease(lambda req, t: _query(session, json.dumps(req), t), armed, RIG)
        wrong_state = _query(session, json.dumps({"cmd": "set_controller", "name": "heaviside"}))
        assert wrong_state["ok"] is False and "disarm" in wrong_state["error"]
        time.sleep(3.0)  # force tracking with network inversion
        st = _query(session, json.dumps({"cmd": "status"}))["status"]
        # ARMED, or FAULT from a stall (proved at the end)
        assert st["state"] in ("ARMED", "FAULT"), st
        assert _query(session, json.dumps({"cmd": "disarm"}))["ok"]
        lease.release()
        ok = _query(
            session, json.dumps({"cmd": "set_controller", "name": "constant", "current_a": 0.5})
        )
        assert ok["ok"] and ok["controller"] == "constant"
        assert (
            _query(session, json.dumps({"cmd": "set_model", "path": "nowhere.json"}))["ok"] is False
        )  # constant uses no model
        assert _query(session, json.dumps({"cmd": "status"}))["status"]["controller"] == "constant"

        # -- an external force reference that goes stale faults. A bridge stall while armed
        # faults first with a stall's fault (proved at the end): then re-arm and try
        # again; any other fault fails at once, and the stale reference must come in the end
        ok = _query(session, json.dumps({"cmd": "set_profile", "kind": "zenoh", "timeout_s": 0.1}))
        assert ok["ok"]
        pub = session.declare_publisher(f"mrrig/{RIG}/force_ref")
        for _attempt in range(3):
            for _ in range(20):
                pub.put(json.dumps({"force_n": 100.0}))
                time.sleep(0.01)
            assert _query(session, json.dumps({"cmd": "reset"}))["ok"]  # the attempt before's
            assert _query(session, json.dumps({"cmd": "arm"}))["ok"]
            for _ in range(50):
                pub.put(json.dumps({"force_n": 100.0}))
                time.sleep(0.01)
            time.sleep(0.5)  # no more force_ref
            st = _query(session, json.dumps({"cmd": "status"}))["status"]
            assert st["state"] == "FAULT", st
            if st["fault"] == "stale_reference":
                break
        pub.undeclare()
        assert st["fault"] == "stale_reference", st
        evs = events.drain()
        assert any(e.get("fault") == "stale_reference" for e in evs), evs

        # -- everything the subscriber got must be in the recording
        time.sleep(0.5)
        batches += telemetry.drain()
        for sub in subscribers:
            sub.undeclare()
    finally:
        session.close()
    daemon.send_signal(signal.SIGTERM)
    assert daemon.wait(timeout=30) == 1  # it ended in FAULT: the stale reference above
    sim.send_signal(signal.SIGTERM)
    assert sim.wait(timeout=10) == 0
    # every fault but the stale references this test made lies inside a measured stall
    daemon_summary = json.loads(summary_path.read_text())
    made = [f for f in daemon_summary["faults"] if f["reason"].startswith("stale force reference")]
    assert made, daemon_summary["faults"]
    others = [f for f in daemon_summary["faults"] if f not in made]
    k = daemon_summary["kernel_stalls"]
    explain(json.loads(sim_stats.read_text()), others, daemon_summary["clock_t0_s"], k)

    verify_rrd(rrd)
    rec = read_recording(rrd)
    by_counter_t = {
        (int(c), float(t)): i
        for i, (c, t) in enumerate(zip(rec.samples["counter"], rec.samples["t"], strict=True))
    }
    checked = 0
    for b in batches:
        f = b["fields"]
        for k in range(len(f["t"])):
            i = by_counter_t[(int(f["counter"][k]), float(f["t"][k]))]
            for name, values in f.items():
                v, r = values[k], rec.samples[name][i]
                if v is None:
                    assert not math.isfinite(r)
                else:
                    assert v == r, (name, v, r)
            checked += 1
    print(f"{checked} telemetry samples found in the recording with equal values")
    assert checked > 1000

    # -- review reproduces the daemon's own summary
    out = tmp_path / "review.json"
    capsys.readouterr()
    assert review_main([str(rrd), "--json", str(out)]) == 0
    review = json.loads(out.read_text())
    for key in ("duration_s", "frames", "armed_frames", "et"):
        assert review[key] == pytest.approx(daemon_summary[key], abs=1e-6), key
    for group in ("tracking_error_n", "latency_us", "i_cmd_a", "i_cmd_step_a", "frame_gap_ms"):
        for k, v in daemon_summary[group].items():
            assert review[group][k] == pytest.approx(v, abs=1e-6), (group, k)
    assert [f["reason"] for f in review["faults"]] == [
        f["reason"] for f in daemon_summary["faults"]
    ]
    assert np.isfinite(review["et"])
