#!/usr/bin/env bash
# Inside the VM (scripts/vcan-vm -- bash tests/vm/rig_on_vcan.sh): firmware_sim and the rig
# daemon as separate processes on SocketCAN vcan0, `candump -L vcan0` logging the bus, then the
# log decoded with the project's DBC and checked (tests/vm/check_candump.py).
# Software emulation is slow: the simulator runs 5x slower than real time (100 Hz) and the
# daemon's sensor timeout is generous; the check is on correctness, and it prints the rate held.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=tests/vm/out
rm -rf "$out"
mkdir -p "$out"
SIM_SECONDS=${SIM_SECONDS:-4}           # simulated seconds (x5 on the wall clock)

# a large socket buffer and a real-time priority: candump must not drop frames itself
chrt -f 40 candump -L -r 8388608 vcan0 > "$out/candump.log" &
dump=$!
# each process on a CPU of its own: vcan passes a frame on through the backlog of the CPU
# that sent it, so the frames of a process that moves between CPUs can overtake each other
# when one CPU's softirq is held up (seen here under load: the daemon received a sensor frame
# before the 7 sent ahead of it, and answered them in that order)
taskset -c 1 python -m mrrig run --config configs/vcan-vm.toml --arm --summary-json "$out/daemon.json" \
    > "$out/daemon.log" 2>&1 &
daemon=$!
# the daemon is up when it has logged its start line (imports are slow in the VM)
for _ in $(seq 1 600); do
    grep -q "rig vm:" "$out/daemon.log" 2>/dev/null && break
    kill -0 "$daemon" 2>/dev/null || { cat "$out/daemon.log"; exit 1; }
    sleep 1
done
sleep 2
echo "rig_on_vcan: daemon up; simulator for ${SIM_SECONDS} simulated s"
taskset -c 0 python -m firmware_sim --config configs/sim-vcan-vm.toml --duration "$SIM_SECONDS" \
    --stats "$out/sim.json" > "$out/sim.log" 2>&1
sleep 1
kill -TERM "$daemon"
# exit 1 is `mrrig run`'s "ended in FAULT": expected here when, and only when, its one fault is
# the sensor_timeout that the simulator's end caused (after the last sensor frame); any other
# fault, or a fault while frames still came, fails the check
rc=0
wait "$daemon" || rc=$?
if [ "$rc" -ne 0 ]; then
    echo "daemon exit $rc"
    tail -20 "$out/daemon.log"
    [ "$rc" -eq 1 ] && python - "$out/daemon.json" <<'PY' || exit 1
import json, sys
s = json.load(open(sys.argv[1]))
faults = s["faults"]
end = [f for f in faults if f.get("fault") == "sensor_timeout" and f["t"] >= s["last_frame_t_s"]]
print(f"rig_on_vcan: faults {faults}; last sensor frame at t={s['last_frame_t_s']:.3f} s")
if len(faults) != 1 or len(end) != 1:
    sys.exit("rig_on_vcan: a fault other than the sensor_timeout of the simulator's end")
print("rig_on_vcan: the one fault is the simulator's end (sensor_timeout): exit 1 as documented")
PY
fi
kill -TERM "$dump"
wait "$dump" || true
tail -3 "$out/sim.log"
# the daemon's arming and faults, so that a low count of ACTIVE commands has its reason here
grep -E "armed|fault" "$out/daemon.log" | head -8 || true
python tests/vm/check_candump.py "$out/candump.log" --i-max 2.0 --min-frames 1000
