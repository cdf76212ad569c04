"""An ensemble of forward networks as one network: the mean of several MLPs of the same inputs.

The mean of M one-hidden-layer networks is itself one: their hidden layers side by side (the
inputs' standardisation of the first member, each member's layer rescaled to it) and an output
layer that weighs each member's part by 1/M (its output scale folded in). So an averaged
ensemble is an `MLP` of M x H hidden units that the daemon loads, checks and inverts as any
other (`mrrig-mlp/1`), and its force is exactly the members' mean. Averaging fits that differ
in their initial weights and in the tests they stopped on lowers the part of the error that
comes from the fit rather than the data (on other tests: the variance of a fit on few tests).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mrrig.loop.mlp import MLP


def average_mlps(members: Sequence[MLP]) -> MLP:
    """One MLP whose output is the mean of the `members`' outputs (same inputs, in order, and
    output); its meta and fingerprint are the first member's, with meta["ensemble"] the
    members' count, hidden sizes and initial-weight seeds. A one-line ValueError where the
    members do not share inputs and output."""
    if not members:
        raise ValueError("average_mlps: no member")
    first = members[0]
    for k, m in enumerate(members[1:], start=1):
        if (m.input_names, m.output_name, m.output_unit) != (
            first.input_names,
            first.output_name,
            first.output_unit,
        ):
            raise ValueError(
                f"average_mlps: member {k} has inputs {m.input_names} -> {m.output_name}"
                f" ({m.output_unit}), member 0 {first.input_names} -> {first.output_name}"
                f" ({first.output_unit})"
            )
    if len(members) == 1:
        return first
    n = len(members)
    mean, std = first.in_mean, first.in_std
    out_mean = float(np.mean([m.out_mean for m in members]))
    out_std = float(np.mean([m.out_std for m in members]))
    W1, b1, W2 = [], [], []
    level = 0.0
    for m in members:
        # (x - m_k) / s_k = (x - mean) / std * (std / s_k) + (mean - m_k) / s_k
        W1.append(m.W1 * (std / m.in_std)[None, :])
        b1.append(m.b1 + m.W1 @ ((mean - m.in_mean) / m.in_std))
        W2.append(m.W2 * (m.out_std / (n * out_std)))
        level += (m.out_mean + m.out_std * m.b2) / n
    meta = dict(first.meta)
    meta["ensemble"] = {
        "members": n,
        "hidden": [m.hidden for m in members],
        "init_seeds": [m.meta.get("init_seed", m.meta.get("seed")) for m in members],
    }
    meta["hidden"] = int(sum(m.hidden for m in members))
    return MLP(
        input_names=list(first.input_names),
        input_units=list(first.input_units),
        output_name=first.output_name,
        output_unit=first.output_unit,
        in_mean=mean,
        in_std=std,
        out_mean=out_mean,
        out_std=out_std,
        W1=np.vstack(W1),
        b1=np.concatenate(b1),
        W2=np.concatenate(W2),
        b2=(level - out_mean) / out_std,
        fingerprint=first.fingerprint,
        metrics=dict(first.metrics),
        meta=meta,
    )
