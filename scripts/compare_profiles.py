"""The demo on the CAN contract's profile and on the example lab profile, back to back.

    python scripts/compare_profiles.py [--duration 20]

Runs `mrrig demo` (bridge, firmware_sim, daemon as processes) twice with the same duration
and model: once on configs/rig.toml + configs/sim.toml (configs/mrrig.dbc: 500 Hz, E2E), once
on configs/profiles/lab-1khz.toml + lab-1khz-sim.toml (IDs 0x301-0x303, mm and kN, no E2E,
1 kHz), and prints each run's verdict lines (Et over the armed frames, armed share, faults
other than transport), the daemon's frames, the start-up line of the protections that are
off, and Et's ratio lab / contract. Exit 1 unless both demos pass.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from mrrig.rigio.canbus.bus import find_free_port

RUNS = {
    "contract (mrrig.dbc, 500 Hz, E2E)": ("configs/rig.toml", "configs/sim.toml"),
    "lab (lab-1khz.dbc, 1 kHz, no E2E)": (
        "configs/profiles/lab-1khz.toml",
        "configs/profiles/lab-1khz-sim.toml",
    ),
}


def _own_zenoh(config: str, work: Path, k: int) -> tuple[Path, Path]:
    """A copy of the daemon config on a Zenoh port of its own (other demos on this machine
    hold 7447) with its DBC named by absolute path: (daemon config, client Zenoh config)."""
    port = find_free_port()
    zd, zc = work / f"zenoh-daemon-{k}.json5", work / f"zenoh-client-{k}.json5"
    off = "scouting: { multicast: { enabled: false } }"
    zd.write_text(f'{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, {off} }}')
    zc.write_text(
        f'{{ mode: "client", connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, {off} }}'
    )
    source = Path(config)
    text = source.read_text().replace('"configs/zenoh-daemon.json5"', f'"{zd}"')
    text = re.sub(
        r'^dbc = "([^"]+)"', lambda m: f'dbc = "{source.parent.resolve() / m[1]}"', text, flags=re.M
    )
    copy = work / f"rig-{k}.toml"
    copy.write_text(text)
    return copy, zc


def run_demo(config: str, sim_config: str, duration_s: float, work: Path, k: int) -> dict:
    rig, zenoh_client = _own_zenoh(config, work, k)
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "demo", "--config", str(rig), "--sim-config", sim_config]
        + ["--zenoh-config", str(zenoh_client), "--duration", str(duration_s)]
        + ["--record", str(work / f"{k}.rrd")],
        capture_output=True,
        text=True,
    )
    out = proc.stdout + proc.stderr
    et = re.search(r"^\s+\w+\s+Et (\S+) <=", out, re.M)
    frames = re.search(r"^\s+sensor_frames_valid\s+(\d+)", out, re.M)
    verdict = [
        line for line in out.splitlines() if re.match(r"\s+(ok|FAIL)\s|demo: re-armed", line)
    ]
    off = [
        line.split("protections off: ", 1)[1]
        for line in out.splitlines()
        if "protections off" in line
    ]
    return {
        "rc": proc.returncode,
        "et": float(et.group(1)) if et else float("nan"),
        "frames": int(frames.group(1)) if frames else 0,
        "verdict": verdict or out.splitlines()[-5:],
        "off": off[-1] if off else "none",
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="s of force tracking per run")
    args = ap.parse_args()
    results = {}
    with tempfile.TemporaryDirectory(prefix="mrrig-profiles-") as work:
        for name, (config, sim_config) in RUNS.items():
            r = run_demo(config, sim_config, args.duration, Path(work), len(results))
            results[name] = r
            print(f"{name}: exit {r['rc']}, {r['frames']} sensor frames, Et {r['et']:.4f}")
            for line in r["verdict"]:
                print(f"  {line.strip()}")
            print(f"  protections off: {r['off']}")
    (contract, lab) = results.values()
    print(f"Et lab / contract: {lab['et'] / contract['et']:.3f}")
    return 0 if contract["rc"] == 0 and lab["rc"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
