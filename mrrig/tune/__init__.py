"""On-rig auto-tuning of the controller's free parameters (continuity, feedback time constant,
adaptation memory) by closed-loop trials on a tuning profile, chosen by measured Et.

`rule` is the pure part (the grid, the choice: `mrrig bench paper` uses it against its simulated
plant); `trials` runs the candidates on a live rig through its control plane (`mrrig tune`).
"""

from mrrig.tune.rule import (
    ADAPTATION_MEMORY_CANDIDATES_S,
    CONTINUITY_CANDIDATES,
    FEEDBACK_TAU_CANDIDATES_S,
    Candidate,
    Trial,
    TuneError,
    choose,
    grid,
)

__all__ = [
    "ADAPTATION_MEMORY_CANDIDATES_S",
    "CONTINUITY_CANDIDATES",
    "FEEDBACK_TAU_CANDIDATES_S",
    "Candidate",
    "Trial",
    "TuneError",
    "choose",
    "grid",
]
