"""`mrrig train`'s report: what was excluded, the structure search, every kind's figures, the
other-test estimate beside the block hold-out, the validation files and the random starts
(mrrig/cli/train.py trains and writes the model)."""

from __future__ import annotations

from typing import Any

from mrrig.offline.evaluate import format_coverage


def _pct(d: dict[str, float] | None) -> str:
    if d is None:
        return "n/a (no plant: offline data)"
    return f"p50 {d['p50']:.1f}  p95 {d['p95']:.1f}  max {d['max']:.1f}"


def format_excluded(ex: dict[str, Any] | None) -> list[str]:
    if ex is None:
        return []
    sub = ex.get("subset")
    lines = (
        [
            f"trained on {sub['samples']} of {sub['of_samples']} samples: whole segments chosen"
            f" at random (at most {sub['max_samples']})"
        ]
        if sub and sub["samples"] < sub["of_samples"]
        else []
    )
    if not ex["excluded_samples"]:
        what = "--keep-all" if ex["keep_all"] else "no saturation, idle or transient stretch found"
        return [*lines, f"excluded: nothing ({what})"]
    kinds = ", ".join(f"{k} {n}" for k, n in ex["by_kind"].items())
    keep = " (--keep-all: the implausible only)" if ex["keep_all"] else ""
    lines += [f"excluded {ex['excluded_samples']} of {ex['of_samples']} samples ({kinds}){keep}:"]
    lines += [
        f"  {st['kind']}: {st['file'] + ', ' if 'file' in st else ''}run {st['run']},"
        f" {st['t_start_s']:.4f}-{st['t_end_s']:.4f} s ({st['samples']} samples)"
        for st in ex["stretches"]
    ]
    if ex.get("stretches_not_listed"):
        lines.append(f"  and {ex['stretches_not_listed']} more stretches")
    return lines


def format_search(fs: dict[str, Any] | None) -> list[str]:
    if fs is None:
        return []
    lines = [
        f"features auto: {fs['method']}",
        "  inversion: median CPU us of the daemon's per-frame solve (prepared ahead), and of"
        " the full solve",
    ]
    if fs["lag_fit"]:
        lines.append(f"  command lag by 1-D search: tau {fs['lag_fit']['tau_s'] * 1e3:.2f} ms")
    for c in fs["candidates"]:
        budget = "" if c["in_budget"] else f" (over the {fs['inversion_budget_us']:g} us budget)"
        lines.append(
            f"  CV Et {c['cv_et']:.4f}  inversion {c['inversion_us']:5.1f} us"
            f" (full solve {c['inversion_full_us']:5.1f})  {c['label']}{budget}"
        )
    lines += [f"  not tried (search time spent): {label}" for label in fs["not_tried"]]
    lines.append(f"  chosen: {fs['chosen']['label']} (CV Et {fs['chosen']['cv_et']:.4f})")
    return lines


def format_kinds(k: dict[str, Any] | None) -> list[str]:
    """The kind of model chosen (`kind_choice.choose_kind`): every kind's Et and work per frame."""
    if k is None:
        return []
    lines = [
        f"kind of model, chosen by the {k['estimate']} estimate: {k['method']}",
        f"  folds fitted cut down: {k['fold_fit']}; time budget {k['budget_s']:.0f} s"
        f" (search and folds), spent {k['seconds']:.0f} s",
    ]
    for c in k["kinds"]:
        budget = "" if c["in_budget"] else f" (over the {k['budget_us']:.0f} us budget)"
        ratio = c["et"] / c["block_et"] if c["block_et"] > 0 else float("nan")
        lines.append(
            f"  Et {c['et']:.4f}  block hold-out {c['block_et']:.4f} ({ratio:.1f}x optimistic)"
            f"  work per frame {c['frame_cost_us']:5.0f} us"
            f"  {c['kind']}: {c['label']}{budget} ({c['seconds']:.0f} s{_kind_folds(k, c)})"
        )
    lines += [f"  not tried: {name} ({why})" for name, why in k["not_tried"].items()]
    ch = k["chosen"]
    lines.append(f"  chosen: {ch['kind']}, {ch['why']}")
    if k["block_holdout_would_choose"] != ch["kind"]:
        lines.append(f"  (the block hold-out would have chosen {k['block_holdout_would_choose']})")
    return lines


def _kind_folds(k: dict[str, Any], c: dict[str, Any]) -> str:
    """A kind scored on fewer folds than the method line says: how many (k-fold over tests)."""
    most = max((d.get("folds", 0) for d in k["kinds"]), default=0)
    n = c.get("folds", 0)
    return f", {n} folds over tests" if 0 < n < most and not k["optimistic"] else ""


def format_other_tests(cv: dict[str, Any] | None) -> list[str]:
    """The other-test estimate (`crossval.cross_validate`): Et per left-out test and overall."""
    if cv is None:
        return []
    kind = cv["kind"]
    lines = [f"other-test estimate, {cv['method']} ({cv['seconds']:.0f} s):"]
    lines += [
        f"  {g[kind]}: Et {g['et']:.4f} ({g['n']} rows)" if g["n"] else f"  {g[kind]}: no rows"
        for g in cv["per_group"]
    ]
    o = cv["overall"]
    lines.append(
        f"  overall Et {o['et']:.4f} (pooled over the {o['n']} left-out rows;"
        f" mean of the {kind}s {cv['mean_et']:.4f})"
    )
    if cv["optimistic"]:
        lines.append(
            f"  (one test: its {kind}s are the same test, so this is optimistic too; only"
            " another test, --validate FILE, says how the model holds elsewhere)"
        )
    return lines


def format_validate(v: dict[str, Any] | None) -> list[str]:
    """The validation tests' numbers (`--validate`: kept out of training and choice)."""
    if v is None:
        return []
    lines = [
        f"validation tests (--validate: never trained on nor chosen by),"
        f" {len(v['per_test'])} test(s):"
    ]
    lines += [
        f"  {t['file']}: Et {t['et']:.4f} ({t['n']} rows)" if t["n"] else f"  {t['file']}: no rows"
        for t in v["per_test"]
    ]
    lines.append(f"  overall Et {v['forward']['et']:.4f} (pooled over {v['n']} rows)")
    lines += ["  " + line for line in format_coverage(v["coverage"], v["command_unit"])]
    return lines


def _format_starts(st: dict[str, Any] | None, unit: str) -> list[str]:
    """The forward network's starts: the one kept, or their mean (`average_starts`)."""
    if not st:
        return []
    seeds = ", ".join(map(str, st["init_seeds"]))
    if st.get("averaged"):
        return [
            f"  the mean of {len(st['init_seeds'])} starts (initial weights and rows seeds"
            f" {seeds}; epochs {' / '.join(map(str, st['epochs']))}), one network of their"
            " hidden layers side by side, as the kind choice's fold fits"
        ]
    return [
        f"  kept start {st['kept'] + 1} of {len(st['init_seeds'])} (initial weights"
        f" seeds {seeds}): on-line inverse command RMSE on the training rows "
        + " / ".join(f"{e:.4f}" for e in st["training_rmse_a"])
        + f" {unit}"
    ]


def format_report(r: dict[str, Any]) -> str:
    ni = r["network_inversion"]
    unit = r.get("command_unit", "A")
    stride = r.get("history_stride", 1)
    lines = [
        *format_excluded(r.get("excluded")),
        *format_search(r.get("features_search")),
        *format_kinds(r.get("kinds")),
        f"split: {r['split']['rule']} (seed {r['split']['seed']})",
        f"command input ({unit}): {r['current_input']}"
        + (f" (lag tau {r['lag_tau_s'] * 1e3:.2f} ms)" if r["lag_tau_s"] else ""),
        "history inputs: "
        + (
            f"the previous {r['history_samples']} samples of {', '.join(r['history_signals'])}"
            + (f" ({stride} samples apart)" if stride > 1 else "")
            if r["history_samples"]
            else "none"
        ),
        f"hidden neurons: {r.get('hidden', 30)}"
        + (
            f" per start ({r['hidden'] * len(st['init_seeds'])} in the averaged network)"
            if (st := r.get("starts") or {}).get("averaged")
            else ""
        ),
        f"forward network: {r['epochs']} epochs ({r['stop_reason']}), {r['seconds']:.1f} s",
        *_format_starts(r.get("starts"), unit),
        f"forward Et on the {r['n_val']} held-out samples ({r['split']['kind']}):"
        f" {r['forward']['et']:.4f}"
        f" (RMSE {r['forward']['rmse_n']:.2f} N)"
        + (
            "  [optimistic: the end of each run of the tests trained on, beside samples trained on]"
            if r["split"]["kind"] == "blocks"
            else "  [optimistic: random samples, neighbours of samples trained on]"
        ),
        *format_other_tests(r.get("other_tests")),
        *format_validate(r.get("validate")),
        f"network inversion: inverse-command RMSE {ni['current_rmse_a']:.4f} {unit}"
        f" (paper 0.09 A), i_max {r['i_max_a']:g} {unit}",
        "  tracking error, forward model at the inverted current (N): "
        + _pct(ni["tracking_model_n"]),
    ]
    on = r.get("network_inversion_online")
    if on is not None:
        lines += [
            f"network inversion on-line (runs in time order, continuity {on['continuity']:g}"
            f" chosen on the training rows): inverse-command RMSE {on['current_rmse_a']:.4f}"
            f" {unit}",
            "  tracking error, forward model at the inverted current (N): "
            + _pct(on["tracking_model_n"]),
            f"  (the model file keeps continuity {on['continuity']:g}: the daemon inverts this"
            " way unless [controller] continuity is set)",
        ]
    sup = r.get("supervised")
    if sup is not None:
        lines += [
            f"supervised inverse MLP: command RMSE {sup['current_rmse_a']:.4f} {unit}"
            " (paper 0.20 A)",
            f"  tracking error, forward model at its current (N): {_pct(sup['tracking_model_n'])}",
        ]
    lines.append(f"(tracking: desired force = {r['definitions']['desired force']})")
    return "\n".join(lines)
