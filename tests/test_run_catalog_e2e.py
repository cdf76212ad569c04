"""Issue 34: a daemon run registers itself in the run catalog (by its sidecar, after the loop),
carries its identity in its recording, and publishes itself on `mrrig/<rig>/runs`. The bridge,
the simulator and the daemon run as processes; the catalog is read back with `mrrig runs`."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest

from mrrig.offline.review import read_recording
from mrrig.rigio import client
from mrrig.rigio.run_identity import file_sha256
from tests.conftest import REPO, OutputWatch, rig_config, zenoh_configs

pytestmark = pytest.mark.process


def test_a_daemon_run_is_in_the_catalog_in_its_recording_and_on_zenoh(tmp_path, bridge, procs):
    stats = tmp_path / "sim.json"
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--stats", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert OutputWatch(sim, "rig firmware on").seen.wait(30)
    zconf, zclient, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": "cat1"},
        controller={"name": "constant", "current_a": 0.5},
        telemetry={"enabled": True, "zenoh_config": str(zconf)},
    )
    catalog = tmp_path / "lab" / "catalog.sqlite"
    rrd, summary_path = tmp_path / "run.rrd", tmp_path / "summary.json"
    published: list[dict] = []
    got = threading.Event()
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--duration", "3", "--record",
         str(rrd), "--summary-json", str(summary_path), "--catalog", str(catalog),
         "--specimen", "SN-1234", "--tag", "smoke", "--operator", "alice"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(daemon, "loop running")
    assert out.seen.wait(60), out.text()
    with client.open_session(zclient) as session:

        def on_run(sample) -> None:
            published.append(json.loads(sample.payload.to_bytes()))
            got.set()

        sub = session.declare_subscriber("mrrig/cat1/runs", on_run)
        rc = daemon.wait(timeout=60)
        got.wait(10)
        sub.undeclare()
    out.join()
    print(out.text()[-1500:])
    assert "Traceback" not in out.text(), out.text()[-3000:]
    assert rc in (0, 1), out.text()  # 1: ended in a fault (checked below against the catalog)
    summary = json.loads(summary_path.read_text())
    assert f"run {summary['run_id']} registered in sqlite" in out.text(), out.text()[-2000:]
    listed = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "--json", "--catalog", str(catalog)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert listed.returncode == 0, listed.stderr
    runs = json.loads(listed.stdout)
    runs = runs["runs"] if isinstance(runs, dict) else runs
    assert len(runs) == 1, runs
    run = runs[0]
    assert run["run_id"] == summary["run_id"]
    assert (run["rig"], run["specimen"], run["operator"]) == ("cat1", "SN-1234", "alice")
    assert run["tags"] == ["smoke"] and run["controller"] == "constant"
    assert run["controller_params"]["current_a"] == 0.5
    assert run["et"] == summary["et"]  # both through JSON: the same float, or both null
    assert run["faults_count"] == len(summary["faults"])
    assert run["latency_p99_us"] == pytest.approx(summary["latency_us"]["p99"])
    assert run["verdict"] == ("ok" if rc == 0 else "fault")
    assert run["recording_sha256"] == file_sha256(rrd)
    assert run["config_sha256"] == file_sha256(cfg)
    assert run["dbc_sha256"] == file_sha256(REPO / "configs" / "mrrig.dbc")
    # the recording says what it is, and the fleet heard of it
    ident = read_recording(rrd).identity
    assert ident is not None and ident["run_id"] == run["run_id"]
    assert ident["specimen"] == "SN-1234" and ident["config_sha256"] == run["config_sha256"]
    assert published and published[0]["run_id"] == run["run_id"], published
    assert published[0]["et"] == run["et"]


def test_characterize_and_validate_register_each_run_with_its_plan_and_step(
    tmp_path, bridge, procs, sim_model
):
    """`mrrig characterize` registers each matrix run (step `run-NNN`, its recording) and
    `mrrig validate` each model's window, in the rig config's [catalog]: the numbers equal to
    each recording's summary, and to validate's report."""
    from mrrig.api import Recording, runs

    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge],
        stdout=subprocess.DEVNULL,
    )
    catalog = tmp_path / "lab" / "catalog.sqlite"
    rig = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": "tools", "specimen": "SN-77", "operator": "carol"},
        catalog={"url": str(catalog)},
    )
    matrix = tmp_path / "matrix.toml"
    matrix.write_text(
        "[matrix]\namplitudes_m = [0.01]\nfreqs_hz = [2.0]\ncurrents_a = [0.3, 0.9]\n"
        "settle_s = 0.5\nduration_s = 1.0\n"
    )
    out, report = tmp_path / "char", tmp_path / "val.json"
    for args in (
        ["characterize", "--config", str(matrix), "--rig-config", str(rig), "--out", str(out)],
        ["validate", str(sim_model), "--rig-config", str(rig), "--duration", "2", "--json",
         str(report)],
    ):  # fmt: skip
        p = subprocess.run(
            [sys.executable, "-m", "mrrig", *args],
            cwd=REPO, capture_output=True, text=True, timeout=180,
        )  # fmt: skip
        assert p.returncode == 0, p.stdout + p.stderr
        assert "not registered" not in p.stderr, p.stderr
    assert sim.poll() is None
    found = runs(catalog)
    char = found[found["plan"] == "characterize"].set_index("step")
    assert sorted(char.index) == ["run-000", "run-001"], found[["plan", "step"]]
    for step, row in char.iterrows():
        rrd = out / f"{step}.rrd"
        s = Recording(rrd).summary
        print(f"characterize {step}: Et {row['et']}, I peak {row['peak_current_a']} A")
        assert row["recording_path"] == str(rrd.resolve())
        assert row["recording_sha256"] == file_sha256(rrd)
        assert row["controller_params"]["current_a"] == s["run"]["current_a"]
        assert row["peak_current_a"] == s["i_cmd_a"]["max"]
        assert row["latency_p99_us"] == s["latency_us"]["p99"]
        assert (row["specimen"], row["operator"], row["verdict"]) == ("SN-77", "carol", "ok")
    (val,) = found[found["plan"] == "validate"].to_dict("records")
    (r,) = json.loads(report.read_text())["reports"]
    print(f"validate {val['step']}: Et {val['et']} (report {r['et']})")
    assert val["step"] == sim_model.name and val["model_sha256"] == file_sha256(sim_model)
    assert val["et"] == r["et"] and val["faults_count"] == len(r["faults"])
    assert val["latency_p99_us"] == r["latency_us"]["p99"]
    assert val["config_sha256"] == file_sha256(rig)


OPERATOR_PLAN = """
[plan]
name = "who"

[[step]]
name = "hold"
duration_s = 1
settle_s = 0.2
controller = { name = "constant", current_a = 0.3 }
reference = { kind = "constant" }
criteria = { faults = "transport" }
"""


def test_the_operator_is_the_certificates_common_name_where_zenoh_authenticates_with_mtls(
    tmp_path, bridge, procs
):
    """A daemon on mutual TLS registers its run as its certificate's CN (`rig`); a plan driven
    through an operator's mTLS config registers its step as that certificate's CN
    (`operator`), not as the local user."""
    import getpass

    from mrrig.rigio.canbus.bus import find_free_port
    from tests.test_zenoh_security import _lab, _template

    _lab(tmp_path)
    port = find_free_port()
    rig_conf = _template("rig.json5", tmp_path, port)
    operator_conf = _template("operator.json5", tmp_path, port)
    catalog = tmp_path / "catalog.sqlite"
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": "mtls"},
        loop={"realtime": False},
        controller={"name": "constant", "current_a": 0.2},
        telemetry={"enabled": True, "zenoh_config": str(rig_conf), "rate_hz": 20.0},
    )
    procs(["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge])
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--record", str(tmp_path / "run.rrd"),
         "--catalog", str(catalog)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(daemon, "loop running")
    assert out.seen.wait(60), out.text()
    plan = tmp_path / "plan.toml"
    plan.write_text(OPERATOR_PLAN)
    tool = subprocess.run(
        [sys.executable, "-m", "mrrig", "test", str(plan), "--rig", "mtls", "--zenoh-config",
         str(operator_conf), "--catalog", str(catalog)],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert tool.returncode == 0, tool.stdout + tool.stderr
    daemon.terminate()
    daemon.wait(timeout=60)
    out.join()
    assert " registered in " in out.text(), out.text()[-2000:]
    listed = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "--json", "--catalog", str(catalog)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    operators = {r["step"]: r["operator"] for r in json.loads(listed.stdout)}
    print(f"operators: {operators} (local user {getpass.getuser()!r})")
    assert operators == {None: "rig", "hold": "operator"}
    assert read_recording(tmp_path / "run.rrd").identity["operator"] == "rig"


def test_the_operator_without_mtls_is_the_zenoh_user_else_the_local_user():
    import getpass

    import zenoh

    from mrrig.rigio.run_identity import operator_of

    usrpwd = zenoh.Config.from_json5(
        '{mode: "client", transport: {auth: {usrpwd: {user: "dana", password: "x"}}}}'
    )
    assert operator_of(usrpwd) == "dana"
    # TLS that does not authenticate the client names nobody
    tls = zenoh.Config.from_json5('{transport: {link: {tls: {root_ca_certificate: "ca.pem"}}}}')
    assert operator_of(tls) == operator_of(None) == getpass.getuser()


def test_each_tune_trial_is_a_run_in_the_catalog(tmp_path, bridge, procs, sim_model):
    """`mrrig tune`'s trials (mrrig.tune.trials.run_trials, as the CLI calls it with the
    default catalog): each one a run, plan `tune trial k/n`, step the candidate, its Et."""
    from dataclasses import replace

    from mrrig.api import Rig, runs
    from mrrig.tune import Candidate
    from mrrig.tune.trials import DEFAULT_PROFILE, run_trials
    from tests.live_rig import wait_status

    procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge],
        stdout=subprocess.DEVNULL,
    )
    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path, bridge, sim_model, rig={"name": "tune-cat"},
        telemetry={"enabled": True, "zenoh_config": str(daemon_z)},
    )  # fmt: skip
    procs(["-m", "mrrig", "run", "--config", str(cfg), "--no-record"])
    wait_status(client_z, rig="tune-cat")
    catalog = str(tmp_path / "catalog.sqlite")
    profile = replace(DEFAULT_PROFILE, settle_s=0.5, duration_s=2.0)
    candidates = [Candidate(0.03, None), Candidate(0.0, 0.02)]
    with Rig("tune-cat", zenoh_config=client_z) as rig:
        result = run_trials(rig, candidates, profile, print, catalog=catalog)
    found = runs(catalog)
    print(found[["plan", "step", "verdict", "et"]])
    assert list(found["plan"]) == ["tune trial 1/2", "tune trial 2/2"]
    for (_, row), trial in zip(found.iterrows(), result.trials, strict=True):
        assert row["step"] == trial.candidate.label()
        assert row["controller"] == "network_inversion" and row["rig"] == "tune-cat"
        assert row["et"] == pytest.approx(trial.et, rel=1e-12)
