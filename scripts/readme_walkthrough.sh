#!/usr/bin/env bash
# The commands of the README and docs/guide.md after the two (quick start, three-terminal start, send-force, viewing
# recordings, bus logs), run as written on this machine: the terminals' commands in the
# background, every other command in turn with its exit code. Run after
# `bash scripts/bootstrap.sh`; needs the ports the README uses (54701 and 7447) free.
#   bash scripts/readme_walkthrough.sh [OUT_DIR]
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-$(mktemp -d)}
mkdir -p "$out"
failed=0

step() {  # a command as the README writes it, its output, and its exit code
    echo "\$ $*"
    "$@"
    local rc=$?
    echo "-> exit $rc"
    [ "$rc" -eq 0 ] || failed=$((failed + 1))
}

wait_for() {  # a line in a log, up to 60 s
    for _ in $(seq 1 120); do
        grep -q "$2" "$1" 2>/dev/null && return 0
        sleep 0.5
    done
    echo "readme_walkthrough: no '$2' in $1" >&2
    cat "$1" >&2
    return 1
}

cleanup() { kill "$daemon" "$sim" "$bridge" 2>/dev/null; wait 2>/dev/null; }
trap cleanup EXIT

echo "== the three-terminal start (logs in $out) =="
.venv/bin/mrrig bridge --port 54701 >"$out/bridge.txt" 2>&1 &
bridge=$!
wait_for "$out/bridge.txt" "virtual channel" || exit 1
.venv/bin/mrrig sim --config configs/sim.toml >"$out/sim.txt" 2>&1 &
sim=$!
.venv/bin/mrrig run --config configs/rig.toml --can-log "$out/run.log" >"$out/daemon.txt" 2>&1 &
daemon=$!
wait_for "$out/daemon.txt" "loop running" || exit 1
sleep 1

echo "== a fourth terminal =="
step .venv/bin/mrrig status --rig sim
step .venv/bin/mrrig arm --rig sim
echo "\$ .venv/bin/mrrig watch --rig sim    (Ctrl-C after 4 s)"
timeout -s INT 4 .venv/bin/mrrig watch --rig sim
echo "-> exit $? (130 or 124: stopped by the Ctrl-C)"
step .venv/bin/mrrig disarm --rig sim
step .venv/bin/mrrig control --rig sim '{"cmd": "set_profile", "kind": "zenoh", "timeout_s": 0.1}'
printf 't_s,force_n\n0,0\n0.5,300\n1.5,300\n2.0,-200\n3.0,0\n' >"$out/profile.csv"
step .venv/bin/mrrig send-force --rig sim --csv "$out/profile.csv" --arm
step .venv/bin/mrrig status --rig sim

echo "== Ctrl-C in terminal 3: the daemon's summary =="
kill -INT "$daemon"
wait "$daemon"
echo "-> the daemon exited $?"
tail -12 "$out/daemon.txt"
kill "$sim" "$bridge" 2>/dev/null
wait 2>/dev/null

rrd=$(grep -o "recordings/[^ ]*\.rrd" "$out/daemon.txt" | tail -1)
echo "== viewing the recording $rrd =="
step .venv/bin/mrrig review "$rrd"
step .venv/bin/mrrig review "$rrd" --from 10 --to 12 --plot "$out/zoom.png"
step .venv/bin/mrrig review "$rrd" --html "$out/report.html"
echo "== bus logs =="
step .venv/bin/mrrig review "$rrd" --can-log "$out/run.log"
echo "\$ python -m cantools decode --single-line configs/mrrig.dbc < run.log | head -3"
.venv/bin/python -m cantools decode --single-line configs/mrrig.dbc <"$out/run.log" 2>/dev/null | head -3
ls -la "$out"
echo "readme_walkthrough: $failed command(s) failed"
[ "$failed" -eq 0 ]
