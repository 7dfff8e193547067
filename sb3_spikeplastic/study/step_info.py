"""What a final evaluation keeps per episode beyond its return, as the report shows it: the step-info values its
study file names (``info_keys``) averaged at each step position of the episode and, with ``align``, at each step
relative to the aligned one (e.g. the trials around a reversal); and a spiking model's energy per episode.

Every value is the mean over a group's seeds of each seed's mean over its episodes, with the two-stage bootstrap
95 % interval of :mod:`sb3_spikeplastic.study.intervals` (seeds, then episodes). At a step position, an episode
counts where it has that step; in the aligned table, only the episodes whose alignment is not ``None``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .declaration import Evaluation, Study
from .groups import group_of, groups_of, variant_of
from .intervals import Interval, bootstrap_mean_intervals, fmt

#: Steps relative to the aligned one (0: the step the alignment key names) in the aligned tables and figures.
ALIGNED_OFFSETS = tuple(range(-3, 6))
#: The energy per episode of the report: (column of the raw file, what the table calls it, decimals).
ENERGY_TABLE = (("synops", "SynOps", 0), ("plasticity_macs", "trace-update MACs", 0), ("energy_nj", "energy (nJ)", 1))


def _seed_mean(means: np.ndarray) -> np.ndarray:
    """The mean over seeds of the per-seed means (shape ``(..., seeds)``)."""
    return means.mean(axis=-1)


def values_at(episodes: list[np.ndarray], position: int, aligned: Optional[list[Optional[int]]] = None) -> np.ndarray:
    """The values at one step of every episode that has that step.

    :param episodes: one model's episodes, each its values at every step
    :param position: the step (0: the first), or with ``aligned`` the step relative to each episode's aligned step
    :param aligned: each episode's aligned step; an episode whose alignment is ``None`` is left out
    """
    values = []
    for k, episode in enumerate(episodes):
        if aligned is not None and aligned[k] is None:
            continue
        step = position + (aligned[k] if aligned is not None else 0)
        if 0 <= step < len(episode):
            values.append(episode[step])
    return np.array(values, dtype=float)


def position_intervals(
    seeds: list[tuple[list[np.ndarray], Optional[list[Optional[int]]]]], positions, boot: dict
) -> dict[int, tuple[Interval, int, int]]:
    """Position -> (interval of the mean, seeds, episodes) of one group, where at least one seed has the step.

    :param seeds: per seed, its episodes' values and their aligned steps (``None``: the absolute steps)
    :param positions: the steps (absolute, or relative to the aligned one)
    :param boot: the bootstrap's keyword arguments (``n_resamples``)
    """
    out = {}
    for position in positions:
        data = [values_at(episodes, position, aligned) for episodes, aligned in seeds]
        data = [d for d in data if d.size]
        if data:
            (interval,) = bootstrap_mean_intervals(data, [_seed_mean], **boot)
            out[position] = interval, len(data), sum(d.size for d in data)
    return out


def figure_style(groups: list[str]) -> tuple[dict, dict]:
    """A colour per variant (the same at every budget) and a line style per budget (the first solid)."""
    import matplotlib.pyplot as plt

    variants = list(dict.fromkeys(variant_of(g) for g in groups))
    first = groups[0].split("@")[1] if groups else ""
    colours = {g: plt.cm.tab10(variants.index(variant_of(g)) % 10) for g in groups}
    return colours, {g: "-" if g.split("@")[1] == first else "--" for g in groups}


def steps_section(env: str, name: str, evaluation: Evaluation, models: dict, study: Study, boot: dict):
    """The step-info tables of one final evaluation, their rows and a figure per key.

    :param env: the environment
    :param name: the evaluation's name
    :param evaluation: its declaration (``info_keys``, ``align``)
    :param models: model -> :func:`sb3_spikeplastic.study.layout.read_final`
    :param study: the study (its groups' order)
    :param boot: the bootstrap's keyword arguments
    :return: Markdown lines, CSV rows (env, evaluation, key, aligned_on, step, group, seeds, episodes, estimate,
        low, high) and key -> figure (the mean at each step, and beside it the aligned steps when ``align``)
    """
    import matplotlib.pyplot as plt

    align = evaluation.align
    lines = [
        f"# {env}: evaluation {name!r}, step info at each step",
        "",
        "Mean over seeds of each seed's mean over its episodes at each step of the episode (0: the first); "
        "[95 % interval]: two-stage bootstrap over seeds and episodes. An episode counts at the steps it has.",
    ]
    rows, figures = [], {}
    for key in evaluation.info_keys:
        has = [m for m in sorted(models) if key in models[m]["steps"]]
        groups = [g for g in groups_of(study) if any(group_of(m) == g for m in has)]
        if not groups:
            continue
        n_steps = max(len(e) for m in has for e in models[m]["steps"][key])
        tables = [(None, range(n_steps), "step")]
        if align is not None:
            tables.append((align, ALIGNED_OFFSETS, f"step - {align}"))
        fig, axes = plt.subplots(1, len(tables), figsize=(6.5 * len(tables) + 2, 4.5), squeeze=False)
        colours, styles = figure_style(groups)
        for ax, (aligned_on, positions, label) in zip(axes[0], tables):
            per_group = {}
            for group in groups:
                mine = [m for m in has if group_of(m) == group]
                if aligned_on is not None:
                    mine = [m for m in mine if aligned_on in models[m]["align"]]
                seeds = [
                    (models[m]["steps"][key], models[m]["align"][aligned_on] if aligned_on else None) for m in mine
                ]
                per_group[group] = position_intervals(seeds, positions, boot) if seeds else {}
            if aligned_on is None:
                lines += ["", f"## {key} at each step", ""]
            else:
                left_out = sum(a is None for m in has for a in models[m]["align"].get(aligned_on, []))
                lines += [
                    "",
                    f"## {key} at each step relative to the step {aligned_on} names",
                    "",
                    f"0: the step the final step's {aligned_on!r} names; {left_out} episode(s) without it are "
                    "left out.",
                    "",
                ]
            lines += [f"| {label} | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups)]
            for position in positions:
                cells = [fmt(per_group[g][position][0], 3) if position in per_group[g] else "-" for g in groups]
                if any(c != "-" for c in cells):
                    lines.append(f"| {position} | " + " | ".join(cells) + " |")
            for group, points in per_group.items():
                rows += [
                    dict(
                        env=env,
                        evaluation=name,
                        key=key,
                        aligned_on=aligned_on or "",
                        step=position,
                        group=group,
                        seeds=n_seeds,
                        episodes=n_episodes,
                        **{k: round(v, 6) for k, v in interval._asdict().items()},
                    )
                    for position, (interval, n_seeds, n_episodes) in points.items()
                ]
                if points:
                    x = list(points)
                    estimate, low, high = (np.array([points[p][0][i] for p in x]) for i in range(3))
                    n_seeds = max(s for _, s, _ in points.values())
                    label_n = f"{group} (n={n_seeds})"
                    ax.plot(x, estimate, color=colours[group], ls=styles[group], marker="o", ms=3, label=label_n)
                    ax.fill_between(x, low, high, color=colours[group], alpha=0.15, lw=0)
            ax.set(xlabel=label, ylabel=f"mean {key}")
            if aligned_on is not None:
                ax.axvline(0, color="0.6", ls=":", lw=0.8)
        axes[0, 0].set_title(f"{env}: {key} at each step")
        if align is not None:
            axes[0, 1].set_title(f"aligned on {align}")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="center right", fontsize=7)
        fig.tight_layout(rect=(0, 0, 1 - 2 / (6.5 * len(tables) + 2), 1))
        figures[key] = fig
    return lines, rows, figures


def energy_section(models: dict, study: Study, boot: dict, heading: str) -> list[str]:
    """The energy per episode of every group whose models recorded it (spiking policies): SynOps, trace-update
    MACs and their energy estimate (:mod:`sb3_spikeplastic.snn.energy`), mean and interval; no lines when no model
    recorded it.

    :param models: model -> :func:`sb3_spikeplastic.study.layout.read_final`
    :param study: the study (its groups' order)
    :param boot: the bootstrap's keyword arguments
    :param heading: the section's first line
    """
    recorded = [m for m in sorted(models) if models[m]["energy"] is not None]
    if not recorded:
        return []
    lines = [
        heading,
        "",
        "Per episode (the episode's environment steps together): synaptic operations (SynOps), the plasticity's "
        "multiply-accumulates (trace updates) and the energy estimate of both at 45 nm "
        "(`sb3_spikeplastic.snn.energy`); mean over seeds [95 % interval].",
        "",
        "| model | seeds | " + " | ".join(f"{title} [95 % interval]" for _, title, _ in ENERGY_TABLE) + " |",
        "|---|---|" + "---|" * len(ENERGY_TABLE),
    ]
    for group in groups_of(study):
        mine = [m for m in recorded if group_of(m) == group]
        if mine:
            cells = [
                fmt(bootstrap_mean_intervals([models[m]["energy"][c] for m in mine], [_seed_mean], **boot)[0], d)
                for c, _, d in ENERGY_TABLE
            ]
            lines.append(f"| {group} | {len(mine)} | " + " | ".join(cells) + " |")
    return lines + [""]
