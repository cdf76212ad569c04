"""What a daemon config leaves out that a test run needs, each as one line saying why it
matters: a desired force that never varies (Et, eqs 41-43, is then undefined: `n/a`) and an
actuator that does not move the damper (no velocity, so hardly a damper force to track).

A minimal config (a [bus] table alone) has both: the defaults are a constant 0 N reference and
the actuator stopped, which are safe, not a test. The daemon logs these lines at start-up and
`mrrig demo` gives them as the reason of an `Et n/a`.
"""

from __future__ import annotations

from mrrig.config import ActuatorSection, DaemonConfig, ReferenceSection

_TRACKED = '"bouc_wen", "sine", "noise", "csv", "paper_case" or "zenoh"'


def reference_gap(cfg: DaemonConfig) -> str | None:
    """Why the config's reference gives no Et, or None where it varies."""
    ref = cfg.reference
    if ref.kind == "constant":
        what = f'kind = "constant" ({ref.offset_n:g} N)'
    elif ref.kind in ("sine", "noise") and ref.amplitude_n == 0:
        what = f'kind = "{ref.kind}" with amplitude_n = 0'
    else:
        return None
    default = " (the default: no [reference] table)" if ref == ReferenceSection() else ""
    return (
        f"{cfg.source}: [reference] {what}{default}: the desired force never varies, so Et is"
        f" n/a (eqs 41-43 divide by its spread); to track a force set [reference] kind ="
        f" {_TRACKED}"
    )


def actuator_gap(cfg: DaemonConfig) -> str | None:
    """Why the config's actuator does not move the damper, or None where it does."""
    act = cfg.actuator
    if act.waveform in ("stop", "hold"):
        what = f'waveform = "{act.waveform}"'
    elif act.amplitude_m == 0:
        what = f'waveform = "{act.waveform}" with amplitude_m = 0'
    elif act.waveform == "sine" and act.frequency_hz == 0:
        what = 'waveform = "sine" with frequency_hz = 0'
    else:
        return None
    default = " (the default: no [actuator] table)" if act == ActuatorSection() else ""
    return (
        f"{cfg.source}: [actuator] {what}{default}: the actuator does not move the damper at"
        ' start (no velocity, hardly a damper force); set [actuator] waveform = "sine",'
        " amplitude_m and frequency_hz, or move it by request (set_profile, a plan's step)"
    )


def config_gaps(cfg: DaemonConfig) -> list[str]:
    """The lines of `reference_gap` and `actuator_gap` that apply, in that order."""
    return [line for line in (reference_gap(cfg), actuator_gap(cfg)) if line is not None]
