"""Adaptation within an episode to a change of dynamics at a known step (``HalfCheetahSwitch-v5``'s
``switch_step``), from a final evaluation with ``bins``, ``align`` and ``reward`` in ``info_keys``: does the return
fall at the change and recover later in the same episode (Najarro & Risi 2020: Hebbian networks recover from a
damaged leg within ~100 steps)?

Every measure is taken per episode against the same episode before the change, so episodes of different switch
steps and models of different speeds are on one scale:

* the reference: the episode's mean step reward over the :data:`PRE_BINS` whole bins before the aligned step
  (fewer where the episode has fewer before it);
* the relative return of a bin ``[b N, (b + 1) N)`` relative to the aligned step (the first step under the changed
  dynamics): the bin's summed reward over ``N`` times the reference (the bin's reward over the mean pre-switch bin's;
  1: as before the change), where the episode has the whole bin;
* the drop: the mean step reward over the first ``early`` steps after the change over the reference;
* the recovery: (the mean step reward over the episode's last ``late`` steps minus that over the first ``early``
  steps after the change) over the reference (positive: the return comes back), where the episode has at least
  ``early + late`` steps after the change.

An episode without an aligned step or without a whole bin before it is left out, and so is one whose reference is
not above the evaluation's ``min_reference`` (0 unless declared: a model that did not move forward before the
change, where a ratio to its reference means nothing); the tables count them. Each value
is the mean over a group's seeds of each seed's mean over its episodes, with the two-stage bootstrap 95 % interval
of :mod:`sb3_spikeplastic.study.intervals` (seeds, then episodes).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..zoo.evaluation import REWARD_KEY
from .declaration import Evaluation, Study
from .groups import comparisons, group_of, groups_of
from .intervals import Interval, bootstrap_mean_differences, bootstrap_mean_intervals, fmt, verdict
from .step_info import figure_style

#: Bins before the aligned step in the table, and whose mean is each episode's reference.
PRE_BINS = 4


def reference(rewards: np.ndarray, aligned: int, bins: int) -> Optional[float]:
    """The episode's mean step reward over the whole bins before the aligned step, at most :data:`PRE_BINS`.

    :param rewards: the episode's step rewards
    :param aligned: the first step under the changed dynamics
    :param bins: the bin length
    :return: the mean, or ``None`` where no whole bin lies before the aligned step
    """
    whole = min(PRE_BINS, aligned // bins)
    return float(rewards[aligned - whole * bins : aligned].mean()) if whole else None


def relative_bins(rewards: np.ndarray, aligned: int, bins: int, ref: float) -> dict[int, float]:
    """Bin index ``b`` (the steps ``[b bins, (b + 1) bins)`` relative to the aligned one) -> the bin's summed reward
    over ``bins * ref``, for every whole bin of the episode from ``-PRE_BINS`` on.

    :param rewards: the episode's step rewards
    :param aligned: the first step under the changed dynamics
    :param bins: the bin length
    :param ref: the episode's :func:`reference`
    """
    out = {}
    for b in range(-PRE_BINS, (len(rewards) - aligned) // bins):
        start = aligned + b * bins
        if start >= 0:
            out[b] = float(rewards[start : start + bins].sum()) / (bins * ref)
    return out


def drop_and_recovery(
    rewards: np.ndarray, aligned: int, ref: float, early: int, late: int
) -> Optional[tuple[float, float]]:
    """The episode's drop (the mean step reward over the first ``early`` steps after the change over ``ref``) and
    recovery (the mean over its last ``late`` steps minus that over the first ``early``, over ``ref``).

    :param rewards: the episode's step rewards
    :param aligned: the first step under the changed dynamics
    :param ref: the episode's :func:`reference`
    :param early: the steps after the change of the drop
    :param late: the episode's last steps of the recovered level
    :return: ``(drop, recovery)``, or ``None`` where fewer than ``early + late`` steps follow the change
    """
    after = rewards[aligned:]
    if len(after) < early + late:
        return None
    first, last = after[:early].mean(), after[-late:].mean()
    return float(first / ref), float((last - first) / ref)


def _references(data: dict, evaluation: Evaluation):
    """Each episode's ``(rewards, aligned step, reference)``; the reference ``None`` where the episode has no aligned
    step or no whole bin before it."""
    for rewards, aligned in zip(data["steps"][REWARD_KEY], data["align"][evaluation.align]):
        yield rewards, aligned, None if aligned is None else reference(rewards, aligned, evaluation.bins)


def episode_drop_recovery(data: dict, evaluation: Evaluation) -> np.ndarray:
    """Each episode's drop and recovery, in episode order, for pairing the same episodes of two evaluations.

    :param data: one model's final evaluation (:func:`sb3_spikeplastic.study.layout.read_final`)
    :param evaluation: the declaration (``bins``, ``align``, ``recovery``)
    :return: ``(2, episodes)``: drops, then recoveries; NaN where the episode has none (no aligned step or whole
        bin before it, a reference not above ``min_reference``, or fewer than ``early + late`` steps after the change)
    """
    early, late = evaluation.recovery
    out = np.full((2, len(data["align"][evaluation.align])), np.nan)
    for k, (rewards, aligned, ref) in enumerate(_references(data, evaluation)):
        low = ref is None or ref <= evaluation.min_reference
        measured = None if low else drop_and_recovery(rewards, aligned, ref, early, late)
        if measured is not None:
            out[:, k] = measured
    return out


def episode_measures(models: dict, model: str, evaluation: Evaluation) -> tuple[dict, int, int]:
    """One model's per-episode measures.

    :param models: model -> :func:`sb3_spikeplastic.study.layout.read_final`
    :param model: the model
    :param evaluation: the declaration (``bins``, ``align``, ``recovery``)
    :return: measure (a bin index, ``"drop"``, ``"recovery"``, ``"reference"``) -> the values of the episodes that
        have it; the episodes left out for a reference not above ``min_reference``; those left out for no aligned
        step or no whole bin before it
    """
    bins, (early, late) = evaluation.bins, evaluation.recovery
    values: dict = {}
    not_learned = unaligned = 0
    for rewards, aligned, ref in _references(models[model], evaluation):
        if ref is None:
            unaligned += 1
            continue
        if ref <= evaluation.min_reference:
            not_learned += 1
            continue
        values.setdefault("reference", []).append(ref)
        for b, value in relative_bins(rewards, aligned, bins, ref).items():
            values.setdefault(b, []).append(value)
        measured = drop_and_recovery(rewards, aligned, ref, early, late)
        if measured is not None:
            values.setdefault("drop", []).append(measured[0])
            values.setdefault("recovery", []).append(measured[1])
    return values, not_learned, unaligned


def _interval(seeds: list[list[float]], boot: dict) -> Optional[tuple[Interval, int, int]]:
    """(interval of the mean over seeds of the per-seed means, seeds, episodes) of the seeds with an episode."""
    data = [np.array(s) for s in seeds if s]
    if not data:
        return None
    (interval,) = bootstrap_mean_intervals(data, [lambda means: means.mean(axis=-1)], **boot)
    return interval, len(data), sum(d.size for d in data)


def _differences(
    env: str,
    name: str,
    study: Study,
    kind: dict[str, str],
    groups: list[str],
    has: list[str],
    measured: dict,
    boot: dict,
    rows: list[dict],
) -> list[str]:
    """The drop and recovery of each of the study's declared comparisons (``report.compare``), model minus reference
    with the unpaired two-stage interval; their CSV rows (measure ``drop_difference`` / ``recovery_difference``, the
    group the comparison's label, ``reference`` its reference) appended to ``rows``.

    :param env: the environment
    :param name: the evaluation's name
    :param study: the study
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param groups: the groups with data
    :param has: the models with data
    :param measured: model -> :func:`episode_measures`
    :param boot: the bootstrap's keyword arguments
    :param rows: the section's CSV rows
    """

    def seeds_of(group: str, measure: str) -> list[np.ndarray]:
        values = [measured[m][0].get(measure, []) for m in has if group_of(m) == group]
        return [np.array(v)[None] for v in values if v]

    mean = lambda m: m[..., 0].mean(axis=-1)  # noqa: E731  (per-seed means of one level)
    found = comparisons(study, kind, groups, lambda g: bool(seeds_of(g, "recovery")))
    if not found:
        return []
    lines = [
        "",
        "## Against the reference",
        "",
        "Model minus reference, two-stage bootstrap 95 % interval (unpaired: other models, the same episode seeds); "
        "a verdict only where the interval excludes 0.",
        "",
        "| model | reference | seeds | drop difference | drop | recovery difference | recovery |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, reference, compared in found:
        cells = []
        for measure in ("drop", "recovery"):
            seeds = [s for g in compared for s in seeds_of(g, measure)]
            (difference,) = bootstrap_mean_differences(seeds, seeds_of(reference, measure), [mean], **boot)
            cells.append(f"{fmt(difference, 3)} | {verdict(difference, 'higher', 'lower')}")
            rows.append(
                dict(
                    env=env,
                    evaluation=name,
                    measure=f"{measure}_difference",
                    group=label,
                    reference=reference,
                    seeds=len(seeds),
                    **{k: round(v, 6) for k, v in difference._asdict().items()},
                )
            )
        n_ref = len(seeds_of(reference, "recovery"))
        lines.append(f"| {label} | {reference} | {len(seeds)} vs {n_ref} | " + " | ".join(cells) + " |")
    return lines


def bin_label(b: int, bins: int) -> str:
    """``[-200, -150)``: bin ``b``'s steps relative to the aligned one."""
    return f"[{b * bins}, {(b + 1) * bins})"


def adaptation_section(
    env: str, name: str, evaluation: Evaluation, models: dict, study: Study, kind: dict[str, str], boot: dict
):
    """The adaptation tables of one final evaluation with ``bins``, their rows and their figure.

    :param env: the environment
    :param name: the evaluation's name
    :param evaluation: its declaration (``bins``, ``align``, ``recovery``)
    :param models: model -> :func:`sb3_spikeplastic.study.layout.read_final`
    :param study: the study (its groups' order, its ``report.compare``)
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param boot: the bootstrap's keyword arguments
    :return: Markdown lines, CSV rows (env, evaluation, measure, bin_start, bin_end, group, seeds, episodes,
        left_out: the group's episodes of reference not above ``min_reference``, estimate, low, high) and the
        figure (relative return per bin around the change; recovery per group), or ``None`` for the figure where no
        model has the step rewards and the alignment
    """
    import matplotlib.pyplot as plt

    bins, align, (early, late) = evaluation.bins, evaluation.align, evaluation.recovery
    has = [m for m in sorted(models) if REWARD_KEY in models[m]["steps"] and align in models[m]["align"]]
    groups = [g for g in groups_of(study) if any(group_of(m) == g for m in has)]
    measured = {m: episode_measures(models, m, evaluation) for m in has}
    floor = f"{evaluation.min_reference:g}"
    lines = [
        f"# {env}: evaluation {name!r}, adaptation to the change at {align!r}",
        "",
        f"Per episode, against the same episode before the change (step 0: the first step under the changed "
        f"dynamics, the final step's {align!r}): the reference is the mean step reward over the up to {PRE_BINS} "
        f"whole {bins}-step bins before the change. Mean over seeds of each seed's mean over its episodes; "
        "[95 % interval]: two-stage bootstrap over seeds and episodes. Episodes whose reference is <= "
        f"{floor} (the model did not move forward before the change) are left out, and counted; so are those "
        "without an aligned step or a whole bin before it.",
        "",
        "## Drop and recovery",
        "",
        f"drop: mean step reward over the first {early} steps after the change / reference (1: no loss); "
        f"recovery: (mean over the episode's last {late} steps - mean over the first {early} after the change) / "
        f"reference (positive: it recovers), episodes with at least {early + late} steps after the change.",
        "",
        f"| model | seeds | episodes | left out: reference <= {floor} | left out: no change or bin before it | "
        "reference (reward per step) | drop | recovery |",
        "|---|---|---|---|---|---|---|---|",
    ]
    rows, per_group, recovery = [], {}, {}
    for group in groups:
        mine = [m for m in has if group_of(m) == group]
        values = [measured[m][0] for m in mine]
        not_learned, unaligned = sum(measured[m][1] for m in mine), sum(measured[m][2] for m in mine)
        episodes = sum(len(models[m]["align"][align]) for m in mine)
        cells = []
        for measure in ("reference", "drop", "recovery"):
            found = _interval([v.get(measure, []) for v in values], boot)
            cells.append(fmt(found[0], 3) if found else "-")
            if found:
                rows.append(_row(env, name, measure, None, bins, group, found, not_learned))
                if measure == "recovery":
                    recovery[group] = found
        lines.append(
            f"| {group} | {len(mine)} | {episodes} | {not_learned} | {unaligned} | " + " | ".join(cells) + " |"
        )
        indices = sorted({b for v in values for b in v if isinstance(b, int)})
        per_group[group] = {b: _interval([v.get(b, []) for v in values], boot) for b in indices}
        for b, found in per_group[group].items():
            if found:
                rows.append(_row(env, name, "relative_return", b, bins, group, found, not_learned))
    lines += _differences(env, name, study, kind, groups, has, measured, boot, rows)
    lines += [
        "",
        f"## Relative return per {bins}-step bin",
        "",
        f"The bin's summed reward / ({bins} x the episode's reference): 1 is the return of a bin before the change; "
        "an episode counts in the bins it has whole.",
        "",
        "| steps after the change | " + " | ".join(groups) + " |",
        "|---|" + "---|" * len(groups),
    ]
    indices = sorted({b for points in per_group.values() for b in points})
    for b in indices:
        cells = [fmt(per_group[g][b][0], 3) if per_group[g].get(b) else "-" for g in groups]
        lines.append(f"| {bin_label(b, bins)} | " + " | ".join(cells) + " |")
    if not groups:
        return lines, rows, None
    colours, styles = figure_style(groups)
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw=dict(width_ratios=(2, 1)))
    for group, points in per_group.items():
        x = [b for b in sorted(points) if points[b]]
        if not x:
            continue
        estimate, low, high = (np.array([points[b][0][i] for b in x]) for i in range(3))
        centres = (np.array(x) + 0.5) * bins
        label = f"{group} (n={max(points[b][1] for b in x)})"
        left.plot(centres, estimate, color=colours[group], ls=styles[group], marker="o", ms=3, label=label)
        left.fill_between(centres, low, high, color=colours[group], alpha=0.15, lw=0)
    left.axhline(1.0, color="0.6", ls=":", lw=0.8)
    left.axvline(0, color="0.6", ls=":", lw=0.8)
    left.set(
        title=f"{env}, {name}: return per {bins}-step bin / before the change",
        xlabel=f"steps after the change ({align}; bin centres)",
        ylabel="relative return",
    )
    left.legend(fontsize=7)
    for k, (group, (interval, _, _)) in enumerate(recovery.items()):
        right.errorbar(
            [k],
            [interval.estimate],
            yerr=[[interval.estimate - interval.low], [interval.high - interval.estimate]],
            color=colours[group],
            marker="o",
            capsize=4,
        )
    right.axhline(0.0, color="0.6", ls=":", lw=0.8)
    right.set_xticks(range(len(recovery)), list(recovery), rotation=45, ha="right", fontsize=7)
    right.set_xlim(-0.5, max(len(recovery), 3) - 0.5)
    right.set(title=f"recovery: last {late} - first {early} steps after", ylabel="recovery / reference")
    fig.tight_layout()
    return lines, rows, fig


def _row(
    env: str,
    name: str,
    measure: str,
    b: Optional[int],
    bins: int,
    group: str,
    found: tuple[Interval, int, int],
    left_out: int,
) -> dict:
    """A CSV row of :func:`adaptation_section` (``bin_start``, ``bin_end`` empty for the per-episode measures)."""
    interval, n_seeds, n_episodes = found
    return dict(
        env=env,
        evaluation=name,
        measure=measure,
        bin_start="" if b is None else b * bins,
        bin_end="" if b is None else (b + 1) * bins,
        group=group,
        seeds=n_seeds,
        episodes=n_episodes,
        left_out=left_out,
        **{k: round(v, 6) for k, v in interval._asdict().items()},
    )
