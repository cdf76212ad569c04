"""`mrrig run`'s exit codes (README: Exit codes): the daemon sets one, the run command returns
it, the catalog reads its verdict from it (`mrrig.catalog.finished`)."""


class Exit:
    """`mrrig run`'s exit codes (README: Exit codes)."""

    OK = 0  # stopped by its duration or a signal, not in FAULT
    FAULT = 1  # ended in FAULT (a fault that nobody re-armed)
    USAGE = 2  # a bad config, model or argument (the CLI's one-line error)
    BUS_LOST = 3  # the CAN bus failed or went away (a killed bridge)
    TELEMETRY_LOST = 4  # the telemetry process died again after its one restart
