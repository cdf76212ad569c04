"""The real-time loop: what runs at 500 Hz in the daemon's loop thread, and its numerics.

The daemon (`daemon`), the supervisor (`safety`), the Kalman filter (`estimation`), the force
reference (`reference`), the controllers (`controllers`, `inversion`, `adaptation`, the numpy
network `mlp`), the per-frame sample and the run summary (`samples`, `summary`), and what the
loop needs of the OS (`realtime`, `memory`). Nothing here imports torch, the offline work or
the CLI; only the daemon's start-up touches Zenoh or Rerun (pyproject.toml's contracts).
"""
