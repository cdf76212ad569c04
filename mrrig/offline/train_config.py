"""`mrrig train --config FILE`: the training options as TOML, parsed once into typed objects.

The file gives the defaults of `mrrig train`; a flag given on the command line wins over it.
Every section and field is optional; absent ones keep the command line's built-in defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from mrrig.offline.datasets import CSV_UNITS
from mrrig.offline.training import (
    COIL_LAG_TAU_S,
    CURRENT_INPUTS,
    DEFAULT_HISTORY_SIGNALS,
    DEFAULT_RESTARTS,
    HOLDOUT_FRACTION,
    PAPER_N_TRAIN,
    PAPER_N_VAL,
    check_history,
)
from mrrig.typed_config import ConfigError, load_toml, parse

__all__ = [
    "ConfigError",
    "CsvSection",
    "FeaturesSection",
    "TrainConfig",
    "TrainingSection",
    "load_train_config",
]


@dataclass(frozen=True)
class FeaturesSection:
    """The forward network's inputs (spec/modeling.md 4 B)."""

    current_input: str = "lagged"  # one of CURRENT_INPUTS (the default inversion inverts the lag)
    lag_tau_s: float = COIL_LAG_TAU_S  # the coil lag of current_input = "lagged"
    history_samples: int = 0  # previous samples of history_signals as extra inputs
    history_signals: tuple[str, ...] = DEFAULT_HISTORY_SIGNALS
    history_stride: int = 1  # samples between history taps
    hidden: int = 30  # hidden neurons
    mode: str | None = None  # "auto" | "manual"; absent: auto (manual where the file gives the
    # structure, STRUCTURE_FIELDS, or --current-input or --history is given)

    def check(self) -> None:
        if self.mode not in (None, "auto", "manual"):
            raise ValueError(f"mode: expected 'auto' or 'manual', got {self.mode!r}")
        if self.history_stride < 1:
            raise ValueError(f"history_stride: must be >= 1, got {self.history_stride}")
        if self.hidden < 1:
            raise ValueError(f"hidden: must be >= 1, got {self.hidden}")
        if self.current_input not in CURRENT_INPUTS:
            choices = ", ".join(repr(c) for c in CURRENT_INPUTS)
            raise ValueError(
                f"current_input: expected one of {choices}, got {self.current_input!r}"
            )
        if not self.lag_tau_s > 0:
            raise ValueError(f"lag_tau_s: must be positive, got {self.lag_tau_s}")
        # the library's rules, the sample count alone first so the error names the right field
        try:
            check_history(self.history_samples, DEFAULT_HISTORY_SIGNALS)
        except ValueError as exc:
            raise ValueError(f"history_samples: {exc}") from None
        try:
            check_history(self.history_samples, self.history_signals)
        except ValueError as exc:
            raise ValueError(f"history_signals: {exc}") from None


@dataclass(frozen=True)
class TrainingSection:
    """Levenberg-Marquardt, the split and the validation report."""

    epochs: int = 1000
    seed: int = 0  # the split and the initial weights
    restarts: int = DEFAULT_RESTARTS  # forward-network starts; the best on-line inverse is kept
    n_train: int = PAPER_N_TRAIN  # 90/10 of all samples where the data has fewer
    n_val: int = PAPER_N_VAL
    split: str = "blocks"  # "blocks": the end of each run held out; "random": the paper's
    holdout_fraction: float = HOLDOUT_FRACTION
    i_max_a: float | None = None  # the inversion bound; absent: the data's largest current
    supervised: bool = True  # also train the supervised inverse MLP
    choice_budget_s: float = 300.0  # features auto: the time of the search and the kinds' folds

    def check(self) -> None:
        if not self.choice_budget_s > 0:
            raise ValueError(f"choice_budget_s: must be positive, got {self.choice_budget_s}")
        if self.epochs < 1:
            raise ValueError(f"epochs: must be >= 1, got {self.epochs}")
        if self.seed < 0:
            raise ValueError(f"seed: must be >= 0, got {self.seed}")
        if self.restarts < 1:
            raise ValueError(f"restarts: must be >= 1, got {self.restarts}")
        if self.n_train < 1:
            raise ValueError(f"n_train: must be >= 1, got {self.n_train}")
        if self.split not in ("blocks", "random"):
            raise ValueError(f"split: expected 'blocks' or 'random', got {self.split!r}")
        if not 0.0 < self.holdout_fraction < 0.5:
            raise ValueError(f"holdout_fraction: must be in (0, 0.5), got {self.holdout_fraction}")
        if self.n_val < 1:
            raise ValueError(f"n_val: must be >= 1, got {self.n_val}")
        if self.i_max_a is not None and not self.i_max_a > 0:
            raise ValueError(f"i_max_a: must be positive, got {self.i_max_a}")


@dataclass(frozen=True)
class CsvSection:
    """Column map and units of CSVs that are not tidy characterization files."""

    columns: dict[str, str] = field(default_factory=dict)  # field -> CSV header
    units: dict[str, str] = field(default_factory=dict)  # field -> unit

    def check(self) -> None:
        for table, values in (("columns", self.columns), ("units", self.units)):
            for key, value in values.items():
                if key not in CSV_UNITS:
                    known = ", ".join(CSV_UNITS)
                    raise ValueError(f"{table}.{key}: unknown field (known: {known})")
                if not isinstance(value, str) or not value.strip():
                    raise ValueError(f"{table}.{key}: expected a non-empty string, got {value!r}")
        for key, unit in self.units.items():
            if unit not in CSV_UNITS[key]:
                known = ", ".join(CSV_UNITS[key])
                raise ValueError(f"units.{key}: unknown unit {unit!r} (known: {known})")


@dataclass(frozen=True)
class TrainConfig:
    features: FeaturesSection = field(default_factory=FeaturesSection)
    training: TrainingSection = field(default_factory=TrainingSection)
    csv: CsvSection = field(default_factory=CsvSection)


# a [features] table that gives any of these and no mode gives the structure: mode "manual"
STRUCTURE_FIELDS = (
    "current_input",
    "lag_tau_s",
    "history_samples",
    "history_signals",
    "history_stride",
    "hidden",
)


def load_train_config(path: str | Path) -> TrainConfig:
    """Load and check a training config; a one-line ConfigError naming file and field. A
    [features] table that gives the structure (`STRUCTURE_FIELDS`) and no mode is manual."""
    raw = load_toml(path)
    cfg = parse(TrainConfig, raw, str(path))
    given = raw.get("features")
    if cfg.features.mode is None and isinstance(given, dict) and set(given) & {*STRUCTURE_FIELDS}:
        cfg = replace(cfg, features=replace(cfg.features, mode="manual"))
    return cfg
