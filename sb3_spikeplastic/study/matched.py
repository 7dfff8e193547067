"""The comparisons a study file declares with ``matched_r0: true`` (``report.compare``): each compared group against
the reference's checkpoint whose R0 is nearest its own.

A model may keep a larger fraction of its return under noise (the AUC of its ratio-to-R0 curve) only because it
starts lower (R0). For each compared group (and the pooled groups), the reference's budget whose group R0 (the mean
over its seeds of each seed's mean noise-free return) lies nearest the compared group's R0 is chosen among every
budget the reference is declared and evaluated at (the first on a tie), and the differences (model minus that
reference) of the AUC, of R0 and of the return at the largest sigma come with the two-stage bootstrap intervals and
verdict words of the plain comparisons (:mod:`sb3_spikeplastic.study.report`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .declaration import Study, budget_label
from .groups import comparisons, variant_of
from .intervals import Interval, MeanStatistic, bootstrap_mean_differences, fmt, robustness_difference_row


def r0_of(seeds: Sequence[np.ndarray]) -> float:
    """A group's R0: the mean over seeds of each seed's mean return at sigma 0.

    :param seeds: one array per seed, sigma on the first axis (sigma 0 first), episodes on the last.
    """
    return float(np.mean([s[0].mean() for s in seeds]))


def matched_rows(
    env: str,
    name: str,
    noise: str,
    sigmas: Sequence[float],
    study: Study,
    kind: dict[str, str],
    groups: list[str],
    seeds_of: Callable[[str, str], list[np.ndarray]],
    statistics: Sequence[MeanStatistic],
    boot: dict,
) -> list[dict]:
    """The verdict rows at matched R0 of one robustness evaluation and noise type.

    :param env: the environment.
    :param name: the robustness evaluation.
    :param noise: the noise type.
    :param sigmas: the evaluation's sigmas.
    :param study: the study.
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``.
    :param groups: the groups of the evaluation.
    :param seeds_of: ``(group, noise)`` -> the raw returns of each of the group's seeds that learned.
    :param statistics: the AUC, the mean return at the largest sigma and at sigma 0, of per-seed means.
    :param boot: keyword arguments of :func:`~sb3_spikeplastic.study.intervals.bootstrap_mean_differences`.
    :return: one row per compared group (and pooled groups), keyed like the plain rows, with ``matched`` (``R0``),
        the compared and the reference's R0, the plain reference and the reference's budgets without raw data.
    """
    rows = []
    found = comparisons(study, kind, groups, lambda g: bool(seeds_of(g, noise)), matched_r0=True)
    for label, plain, compared in found:
        variant = variant_of(plain)
        declared = [
            f"{variant}@{budget_label(b)}"
            for b in study.budgets_of(variant)
            if any(name == e for s in study.seeds_of(variant) for e, _, _ in study.evaluations_of(variant, s, b))
        ]
        if len(declared) < 2:
            continue
        r0s = {g: r0_of(seeds_of(g, noise)) for g in declared if seeds_of(g, noise)}
        seeds = [s for g in compared for s in seeds_of(g, noise)]
        r0 = r0_of(seeds)
        reference = min(r0s, key=lambda g: abs(r0s[g] - r0))
        ref = seeds_of(reference, noise)
        differences = bootstrap_mean_differences(seeds, ref, statistics, **boot)
        rows.append(
            dict(
                **robustness_difference_row(
                    env, name, noise, label, reference, len(seeds), len(ref), sigmas[-1], differences
                ),
                matched="R0",
                model_r0=round(r0, 1),
                reference_r0=round(r0s[reference], 1),
                plain_reference=plain,
                reference_budgets_without_data=" ".join(g.split("@")[1] for g in declared if g not in r0s),
            )
        )
    return rows


def matched_table(rows: list[dict]) -> list[str]:
    """The section "at matched R0" of one evaluation's verdicts in Markdown, per noise type; empty without matched
    rows.

    :param rows: the evaluation's verdict rows, plain (for the plain AUC difference beside) and matched.
    """
    matched = [r for r in rows if r.get("matched")]
    if not matched:
        return []
    plain = {(r["noise"], r["model"], r["reference"]): r for r in rows if not r.get("matched")}

    def ival(r: dict, prefix: str, digits: int) -> str:
        return fmt(Interval(r[f"{prefix}_estimate"], r[f"{prefix}_low"], r[f"{prefix}_high"]), digits)

    lines = [
        "## at matched R0",
        "",
        "Each model against the reference's checkpoint (budget) whose R0, the mean over its seeds, lies nearest the "
        "model's R0: is the AUC difference more than a lower start? Differences model minus that reference, "
        "intervals and verdicts as above; the last column: the AUC difference against the reference of the same "
        "budget.",
        "",
    ]
    for noise in dict.fromkeys(r["noise"] for r in matched):
        mine = [r for r in matched if r["noise"] == noise]
        top = next(k for k in mine[0] if k.startswith("return_at_sigma_")).split("_difference")[0]
        lines += [f"### {noise} noise", ""]
        for reference, without in dict.fromkeys(
            (variant_of(r["reference"]), r["reference_budgets_without_data"]) for r in mine
        ):
            if without:
                lines += [
                    f"{reference}: no raw data at {', '.join(without.split())} (not trained or not evaluated yet); "
                    "R0 matched among its other budgets.",
                    "",
                ]
        lines += [
            "| model | R0 | reference at matched R0 | reference R0 | seeds | R0 difference | AUC difference | "
            f"relative loss | {top.replace('_', ' ')} difference | absolute return under noise | "
            "AUC difference at the same budget |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in mine:
            same = plain.get((noise, r["model"], r["plain_reference"]))
            lines.append(
                f"| {r['model']} | {r['model_r0']:.0f} | {r['reference']} | {r['reference_r0']:.0f} | "
                f"{r['seeds']} vs {r['reference_seeds']} | {ival(r, 'r0_difference', 0)} | "
                f"{ival(r, 'auc_difference', 3)} | {r['auc_verdict']} | {ival(r, top + '_difference', 0)} | "
                f"{r['return_verdict']} | "
                + (f"{ival(same, 'auc_difference', 3)} vs {r['plain_reference']} |" if same else "- |")
            )
        lines.append("")
    return lines
