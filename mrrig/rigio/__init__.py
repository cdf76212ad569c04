"""The rig's I/O around the loop: what may block, kept off the loop thread.

The CAN bus and its codec (`canbus`), the pipes to the telemetry process (`ipc`), the sidecar
with every Zenoh and Rerun call (`sidecar`, `recording`, `canlog`, `audit`, `zenoh_config`), the
control requests' checks and worker (`control`), the router, the clients (`client`,
`force_stream`, `fleet`), certificates, systemd notification, and `rig_session` (a loop run in a
thread of a tool's process). No torch, and never the offline work or the CLI.
"""

# python-can without asammdf (and pandas), before any module here or a library it uses
# (can_remote, cantools) imports python-can: see mrrig/pycan.py
import mrrig.pycan  # noqa: E402, F401
