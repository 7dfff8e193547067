"""``sb3-spikeplastic study report FILE``: every table, interval, verdict and figure of a study, derived from its
raw episode files (:mod:`sb3_spikeplastic.study.layout`) and nothing else.

A group is ``<variant>@<budget>`` (its models are the seeds). Intervals are two-stage bootstrap 95 % intervals over
seeds, then episodes (:mod:`sb3_spikeplastic.study.intervals`; seeded, so a report is reproducible). Written into the
study's folder (with one environment; with several, each file name starts with ``<env>_``):

* ``table.md`` — per final evaluation: each group's mean return (and success rate) per seed and with its interval;
  per robustness evaluation (the protocol of :mod:`sb3_spikeplastic.study.protocol`): R0 per seed and per group,
  and per noise type the return at every sigma beside its ratio to R0 and the area under the ratio curve. Models
  with R0 below the learned threshold are listed apart and left out of every ratio and comparison. Last, what is
  missing: cells not trained, evaluations not run.
* ``verdicts.md``, ``verdicts.csv`` — the comparisons the study file declares (``report.compare``), per budget:
  differences (model minus reference) of the AUC, of R0 and of the return at the largest sigma (robustness), or of
  the mean return and success rate (final), with intervals, and a verdict only where the interval excludes 0.
* ``summary.md`` — one row per group of each robustness evaluation: seeds, R0 and the AUC of every noise type.
* ``steps_<evaluation>.md``, ``steps_<evaluation>.csv``, ``steps_<evaluation>_<key>.png`` — per final evaluation
  with ``info_keys``: each key's mean at every step of the episode, and relative to the ``align`` step
  (:mod:`sb3_spikeplastic.study.step_info`); ``table.md`` adds a spiking model's energy per episode.
* ``ablation_<evaluation>.md``, ``ablation_<evaluation>.csv`` — per evaluation with ``ablation`` and a plain
  counterpart: each plastic group's value plain, ablated and the paired difference plain - ablated with its
  interval and verdict (:mod:`sb3_spikeplastic.study.ablation_report`).
* ``adaptation_<evaluation>.md``, ``.csv``, ``.png`` — per final evaluation with ``bins``: the return per bin
  around the aligned change relative to the same episode's before it, the drop and the recovery
  (:mod:`sb3_spikeplastic.study.adaptation`).
* ``points.csv`` (every group x noise x sigma: return and ratio with intervals), ``<evaluation>.png`` (return and
  ratio against sigma: Fig. 4 F-H), ``curves.csv`` and ``training_curves.png`` (Fig. 4 E: the deterministic
  evaluations during training, mean and range over seeds).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path
from typing import Optional

import numpy as np

from .ablation_report import ablation_table
from .adaptation import adaptation_section
from .declaration import Evaluation, Study
from .groups import comparisons, group_of, groups_of, kinds, variant_of
from .intervals import (
    Interval,
    bootstrap_mean_differences,
    bootstrap_mean_intervals,
    fmt,
    robustness_difference_row,
    verdict,
)
from .layout import StudyFolder, read_study
from .matched import matched_rows, matched_table
from .protocol import auc, ratio_to_r0
from .step_info import energy_section, steps_section

# ----------------------------------------------------------------------------------------------------------------
# Statistics of per-seed means (shape (..., seeds, sigmas)), vectorised over bootstrap replicates


def mean_at(j: int) -> Callable[[np.ndarray], np.ndarray]:
    """The mean over seeds of each seed's mean return at sigma index ``j``."""
    return lambda means: means[..., j].mean(axis=-1)


def ratio_at(j: int) -> Callable[[np.ndarray], np.ndarray]:
    """The mean over seeds of each seed's return ratio to R0 at sigma index ``j``."""
    return lambda means: ratio_to_r0(means)[..., j].mean(axis=-1)


def auc_of(sigmas) -> Callable[[np.ndarray], np.ndarray]:
    """The mean over seeds of each seed's area under the ratio curve."""
    return lambda means: auc(ratio_to_r0(means), sigmas).mean(axis=-1)


# ----------------------------------------------------------------------------------------------------------------
# Tables


def robustness_section(
    env: str,
    name: str,
    evaluation: Evaluation,
    models: dict,
    study: Study,
    kind: dict[str, str],
    boot: dict,
    heading: str,
):
    """The robustness evaluation's tables, points, verdict rows, figure and summary table (one row per group:
    seeds that learned, R0 and the AUC of every noise type)."""
    import matplotlib.pyplot as plt

    noises = [n for n in evaluation.protocol.noises if any(n in d for d in models.values())]
    # R0 (sigma = 0: the same episodes under every noise type) from the first noise a model was evaluated on.
    first = {m: d[next(n for n in noises if n in d)][1] for m, d in models.items()}
    learned = {m for m, d in first.items() if d[0].mean() >= study.learned_threshold}
    groups = [g for g in groups_of(study) if any(group_of(m) == g for m in models)]

    def seeds_of(group: str, noise: str) -> list[np.ndarray]:
        return [
            models[m][noise][1] for m in sorted(models) if group_of(m) == group and noise in models[m] and m in learned
        ]

    episodes = next(iter(first.values())).shape[-1]
    lines = [
        heading,
        "",
        f"R0 and every noise level: {episodes} deterministic episodes per seed, the same episode seeds for every "
        "model and sigma; [95 % interval]: two-stage bootstrap over seeds and episodes; models with R0 < "
        f"{study.learned_threshold:g} are listed apart and excluded below.",
        "",
        "| model | seeds | R0 per seed | R0 [95 % interval] |",
        "|---|---|---|---|",
    ]
    summary = {}
    for group in groups:
        mine = [m for m in sorted(models) if group_of(m) == group and m in first]
        kept = [first[m] for m in mine if m in learned]
        per_seed = " / ".join(f"{first[m][0].mean():.0f}" + ("" if m in learned else " (did not learn)") for m in mine)
        summary[group] = [
            f"{len(kept)} of {len(mine)}",
            fmt(bootstrap_mean_intervals(kept, [mean_at(0)], **boot)[0]) if kept else "-",
        ]
        lines.append(f"| {group} | {summary[group][0]} | {per_seed} | {summary[group][1]} |")
    failed = sorted(m for m in first if m not in learned)
    if failed:
        lines += ["", f"Did not learn (R0 < {study.learned_threshold:g}): " + ", ".join(failed) + "."]

    points, verdicts, matched = [], [], []
    fig, axes = plt.subplots(2, len(noises), figsize=(5 * len(noises) + 3, 8), squeeze=False)
    # A variant keeps its colour at every budget; the larger budgets are dashed.
    variants = list(dict.fromkeys(variant_of(g) for g in groups))
    colours = {g: plt.cm.tab20(variants.index(variant_of(g)) % 20) for g in groups}
    first_budget = groups[0].split("@")[1] if groups else ""
    styles = {g: "-" if g.split("@")[1] == first_budget else "--" for g in groups}
    for col, noise in enumerate(noises):
        sigmas = next(d[noise][0] for d in models.values() if noise in d)
        lines += [
            "",
            f"## {noise} noise",
            "",
            "Absolute return (ratio to R0) at each sigma, and the area under the ratio curve.",
            "",
            "| model | seeds | " + " | ".join(f"sigma {s:g}" for s in sigmas) + " | AUC [95 % interval] |",
            "|---|---|" + "---|" * len(sigmas) + "---|",
        ]
        for group in groups:
            seeds = seeds_of(group, noise)
            if not seeds:
                continue
            n = len(sigmas)
            *intervals, area = bootstrap_mean_intervals(
                seeds, [*map(mean_at, range(n)), *map(ratio_at, range(n)), auc_of(sigmas)], **boot
            )
            returns, ratios = intervals[:n], intervals[n:]
            for sigma, ret, rat in zip(sigmas, returns, ratios):
                points.append(
                    dict(
                        env=env,
                        evaluation=name,
                        group=group,
                        noise=noise,
                        sigma=sigma,
                        seeds=len(seeds),
                        **{f"return_{k}": round(v, 1) for k, v in ret._asdict().items()},
                        **{f"ratio_{k}": round(v, 4) for k, v in rat._asdict().items()},
                    )
                )
            per_sigma = " | ".join(f"{ret.estimate:.0f} ({rat.estimate:.2f})" for ret, rat in zip(returns, ratios))
            lines.append(f"| {group} | {len(seeds)} | {per_sigma} | {fmt(area, 2)} |")
            summary[group].append(fmt(area, 2))
            for row, values in ((0, returns), (1, ratios)):
                axes[row, col].errorbar(
                    sigmas,
                    [v.estimate for v in values],
                    yerr=[[v.estimate - v.low for v in values], [v.high - v.estimate for v in values]],
                    capsize=3,
                    marker="o",
                    ms=3,
                    color=colours[group],
                    ls=styles[group],
                    label=f"{group} (n={len(seeds)})",
                )
        for group in groups:
            if not seeds_of(group, noise):
                summary[group].append("-")
        axes[0, col].set(title=f"{noise} noise", ylabel="return")
        axes[1, col].set(xlabel="sigma", ylabel="return ratio to sigma = 0")
        axes[1, col].axhline(1.0, color="0.6", ls=":", lw=0.8)

        top = len(sigmas) - 1
        statistics = [auc_of(sigmas), mean_at(top), mean_at(0)]
        for label, reference, compared in comparisons(study, kind, groups, lambda g: bool(seeds_of(g, noise))):
            seeds, ref = [s for g in compared for s in seeds_of(g, noise)], seeds_of(reference, noise)
            differences = bootstrap_mean_differences(seeds, ref, statistics, **boot)
            verdicts.append(
                robustness_difference_row(
                    env, name, noise, label, reference, len(seeds), len(ref), sigmas[top], differences
                )
            )
        matched += matched_rows(env, name, noise, sigmas, study, kind, groups, seeds_of, statistics, boot)
    # One legend for the whole figure (a group's label once, with the seeds of its first panel), right of the panels.
    handles = {}
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label.split(" (n=")[0], (handle, label))
    fig.legend([h for h, _ in handles.values()], [lab for _, lab in handles.values()], loc="center right", fontsize=7)
    fig.tight_layout(rect=(0, 0, 1 - 3 / (5 * len(noises) + 3), 1))
    summary_lines = [
        "| model | seeds | R0 [95 % interval] | " + " | ".join(f"AUC {n} noise" for n in noises) + " |",
        "|---|---|---|" + "---|" * len(noises),
    ]
    summary_lines += [f"| {g} | " + " | ".join(cells) + " |" for g, cells in summary.items()]
    return lines, points, verdicts + matched, fig, summary_lines


def final_section(
    env: str, name: str, models: dict, study: Study, kind: dict[str, str], boot: dict, heading: str
) -> tuple[list[str], list[dict]]:
    """The final evaluation's table and verdict rows (mean return and success rate)."""
    groups = [g for g in groups_of(study) if any(group_of(m) == g for m in models)]
    has_success = any(np.isfinite(d["success"]).all() for d in models.values())

    def seeds_of(group: str, key: str = "return") -> list[np.ndarray]:
        return [models[m][key][None] for m in sorted(models) if group_of(m) == group]

    episodes = next(iter(models.values()))["return"].size
    mean = lambda m: m[..., 0].mean(axis=-1)  # noqa: E731  (per-seed means of one level)
    head = "| model | seeds | return per seed | return [95 % interval] |"
    lines = [
        heading,
        "",
        f"{episodes} deterministic episodes per seed on held-out episode seeds; [95 % interval]: "
        "two-stage bootstrap over seeds and episodes.",
        "",
    ]
    lines += [
        head + (" success per seed | success [95 % interval] |" if has_success else ""),
        "|---|---|---|---|" + ("---|---|" if has_success else ""),
    ]
    for group in groups:
        mine = [m for m in sorted(models) if group_of(m) == group]
        per_seed = {
            key: " / ".join(f"{models[m][key].mean():{spec}}" for m in mine)
            for key, spec in (("return", ".4g"), ("success", ".3f"))
        }
        row = (
            f"| {group} | {len(mine)} | {per_seed['return']} | "
            f"{fmt(bootstrap_mean_intervals(seeds_of(group), [mean], **boot)[0], 3)} |"
        )
        if has_success:
            row += (
                f" {per_seed['success']} | "
                f"{fmt(bootstrap_mean_intervals(seeds_of(group, 'success'), [mean], **boot)[0], 3)} |"
            )
        lines.append(row)
    verdicts = []
    for label, reference, compared in comparisons(study, kind, groups, lambda g: bool(seeds_of(g))):
        seeds = [s for g in compared for s in seeds_of(g)]
        (d_return,) = bootstrap_mean_differences(seeds, seeds_of(reference), [mean], **boot)
        row = dict(
            env=env,
            evaluation=name,
            noise="",
            model=label,
            reference=reference,
            seeds=len(seeds),
            reference_seeds=len(seeds_of(reference)),
            **{f"return_difference_{k}": round(v, 4) for k, v in d_return._asdict().items()},
            return_verdict=verdict(d_return, "higher", "lower"),
        )
        if has_success:
            success = [s for g in compared for s in seeds_of(g, "success")]
            (d_success,) = bootstrap_mean_differences(success, seeds_of(reference, "success"), [mean], **boot)
            row.update(
                {f"success_difference_{k}": round(v, 4) for k, v in d_success._asdict().items()},
                success_verdict=verdict(d_success, "higher", "lower"),
            )
        verdicts.append(row)
    return lines, verdicts


def sensitivity_section(
    env: str, name: str, evaluation: Evaluation, models: dict, study: Study, heading: str
) -> list[str]:
    """The action sensitivity of every group: the mean over seeds (range) per element or element group, the
    first group's over the second's, and the s.d. of the first group's first element in the models' observation
    statistics (which sets how large the shift is in the units the policy reads)."""
    n = next(iter(models.values()))[0].size
    groups = dict(evaluation.groups or ((str(i), (i,)) for i in range(n)))
    names = list(groups)

    def cell(values, digits: int = 3) -> str:
        return f"{np.mean(values):.{digits}f} ({np.min(values):.{digits}f}-{np.max(values):.{digits}f})"

    ratio = len(names) > 1
    first = groups[names[0]][0]
    lines = [
        heading,
        "",
        f"Mean absolute change of the clipped action when one raw observation element is shifted by "
        f"{evaluation.shift:g}, averaged over the action's dimensions and one noise-free episode (episode seed "
        f"{evaluation.protocol.seed}); mean over seeds (range). A group's column averages its elements.",
        "",
        "| model | seeds | "
        + " | ".join(names)
        + (f" | {names[0]} / {names[1]}" if ratio else "")
        + f" | s.d. of element {first} |",
        "|---|---|" + "---|" * (len(names) + ratio + 1),
    ]
    for group in [g for g in groups_of(study) if any(group_of(m) == g for m in models)]:
        mine = [m for m in sorted(models) if group_of(m) == group]
        per_group = {g: [models[m][0][list(idx)].mean() for m in mine] for g, idx in groups.items()}
        row = f"| {group} | {len(mine)} | " + " | ".join(cell(v) for v in per_group.values())
        if ratio:
            row += f" | {cell([a / b for a, b in zip(per_group[names[0]], per_group[names[1]])], 1)}"
        lines.append(row + f" | {cell([models[m][1][first] for m in mine])} |")
    return lines


def verdict_table(rows: list[dict]) -> list[str]:
    """The verdicts of one evaluation as Markdown, per noise type."""
    lines = []
    for noise in dict.fromkeys(r["noise"] for r in rows):
        mine = [r for r in rows if r["noise"] == noise]

        def ival(r, prefix, digits):
            return fmt(Interval(r[f"{prefix}_estimate"], r[f"{prefix}_low"], r[f"{prefix}_high"]), digits)

        if noise == "":
            has_success = "success_verdict" in mine[0]
            lines += [
                "| model | reference | seeds | return difference | return |"
                + (" success difference | success |" if has_success else ""),
                "|---|---|---|---|---|" + ("---|---|" if has_success else ""),
            ]
            for r in mine:
                lines.append(
                    f"| {r['model']} | {r['reference']} | {r['seeds']} vs {r['reference_seeds']} | "
                    f"{ival(r, 'return_difference', 3)} | {r['return_verdict']} |"
                    + (f" {ival(r, 'success_difference', 3)} | {r['success_verdict']} |" if has_success else "")
                )
            lines.append("")
            continue
        top_key = next(k for k in mine[0] if k.startswith("return_at_sigma_")).split("_difference")[0]
        lines += [
            f"## {noise} noise",
            "",
            f"| model | reference | seeds | AUC difference | relative loss | R0 difference | "
            f"{top_key.replace('_', ' ')} difference | absolute return under noise |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in mine:
            lines.append(
                f"| {r['model']} | {r['reference']} | {r['seeds']} vs {r['reference_seeds']} | "
                f"{ival(r, 'auc_difference', 3)} | {r['auc_verdict']} | {ival(r, 'r0_difference', 0)} | "
                f"{ival(r, top_key + '_difference', 0)} | {r['return_verdict']} |"
            )
        lines.append("")
    return lines


def training_curves(study: Study, env: str, curves: dict, path: Path) -> list[dict]:
    """Fig. 4 E: every variant's deterministic evaluation return against steps (mean and range over seeds)."""
    import matplotlib.pyplot as plt

    rows = []
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for variant in study.variants:
        data = [curves[(variant, s)] for s in study.seeds_of(variant) if (variant, s) in curves]
        if not data:
            continue
        grid = np.unique(np.concatenate([s for s, _ in data]))
        # A seed counts only up to its own last evaluation: the runs of a variant may have different lengths.
        ys = np.stack([np.where(grid <= s[-1], np.interp(grid, s, y), np.nan) for s, y in data])
        n = np.isfinite(ys).sum(0)
        mean, low, high = np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)
        (line,) = ax.plot(grid, mean, label=f"{variant} (n={len(data)})")
        ax.fill_between(grid, low, high, alpha=0.2, color=line.get_color())
        rows += [
            dict(
                env=env,
                variant=variant,
                steps=int(s),
                seeds=int(k),
                mean=round(float(m), 1),
                low=round(float(lo), 1),
                high=round(float(hi), 1),
            )
            for s, k, m, lo, hi in zip(grid, n, mean, low, high)
        ]
    ax.set(
        title=f"{env}: deterministic evaluation return during training",
        xlabel="environment steps",
        ylabel="mean return",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return rows


# ----------------------------------------------------------------------------------------------------------------
# Writing


def _write_csv(path: Path, rows: list[dict]) -> Path:
    from ..zoo.run_folder import atomic_write

    fields = list(dict.fromkeys(k for r in rows for k in r))

    def write(f):
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)

    return atomic_write(path, write, binary=False)


def _write_text(path: Path, text: str) -> Path:
    from ..zoo.run_folder import atomic_write

    return atomic_write(path, lambda f: f.write(text), binary=False)


def write_report(study: Study, folder: Path, log: Optional[Callable[[str], None]] = print) -> list[Path]:
    """Derive every table, verdict and figure of ``study`` from the raw files in ``folder``; returns the files
    written. ``ValueError`` when the folder holds no raw data of a study."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    if not StudyFolder(folder).has_data():
        raise ValueError(
            f"{str(folder)!r} holds no study (no episodes/ or training/ folder); run "
            "`sb3-spikeplastic study FILE` first, or pass the study's folder with --folder"
        )
    data = read_study(study, folder)
    kind, boot = kinds(study), dict(n_resamples=study.resamples)
    written: list[Path] = []
    for env in study.envs:
        prefix = "" if len(study.envs) == 1 else f"{env}_"
        summary: list[str] = []
        lines, verdict_lines, points, verdict_rows = (
            [],
            [
                f"# {env}: verdicts",
                "",
                "Differences (model minus reference) with two-stage "
                "bootstrap 95 % intervals; a verdict is given only when the "
                "interval excludes 0. AUC: area under the ratio-to-R0 curve "
                "(relative loss); return at the largest sigma: absolute. "
                "Generated by `sb3-spikeplastic study report`.",
                "",
            ],
            [],
            [],
        )
        for name, evaluation in study.evaluations.items():
            if evaluation.kind == "final" and (env, name) in data.final:
                section, rows = final_section(
                    env, name, data.final[(env, name)], study, kind, boot, f"# {env}: evaluation {name!r}"
                )
                lines += section + [""]
                models = data.final[(env, name)]
                lines += energy_section(models, study, boot, f"## {env}: energy per episode, evaluation {name!r}")
                if rows:
                    verdict_lines += [f"## evaluation {name!r}", "", *verdict_table(rows)]
                verdict_rows += rows
                if evaluation.info_keys:
                    step_lines, step_rows, figures = steps_section(env, name, evaluation, models, study, boot)
                    written.append(_write_text(folder / f"{prefix}steps_{name}.md", "\n".join(step_lines) + "\n"))
                    if step_rows:
                        written.append(_write_csv(folder / f"{prefix}steps_{name}.csv", step_rows))
                    for key, fig in figures.items():
                        written.append(folder / f"{prefix}steps_{name}_{key}.png")
                        fig.savefig(written[-1], dpi=120)
                        plt.close(fig)
                if evaluation.bins is not None:
                    adapt_lines, adapt_rows, fig = adaptation_section(env, name, evaluation, models, study, kind, boot)
                    written.append(_write_text(folder / f"{prefix}adaptation_{name}.md", "\n".join(adapt_lines) + "\n"))
                    if adapt_rows:
                        written.append(_write_csv(folder / f"{prefix}adaptation_{name}.csv", adapt_rows))
                    if fig is not None:
                        written.append(folder / f"{prefix}adaptation_{name}.png")
                        fig.savefig(written[-1], dpi=120)
                        plt.close(fig)
            elif evaluation.kind == "sensitivity" and (env, name) in data.sensitivity:
                lines += sensitivity_section(
                    env,
                    name,
                    evaluation,
                    data.sensitivity[(env, name)],
                    study,
                    f"# {env}: evaluation {name!r}, action sensitivity",
                ) + [""]
            elif evaluation.kind == "robustness" and (env, name) in data.robustness:
                heading = (
                    f"# {env}: return under noise, one protocol for every model"
                    if name == "robustness"
                    else f"# {env}: return under noise, evaluation {name!r}"
                )
                section, pts, rows, fig, short = robustness_section(
                    env, name, evaluation, data.robustness[(env, name)], study, kind, boot, heading
                )
                summary += [
                    f"# {env}: evaluation {name!r}",
                    "",
                    f"R0: noise-free return; AUC: area under the ratio-to-R0 curve, sigma "
                    f"{evaluation.protocol.sigmas[0]:g}-{evaluation.protocol.sigmas[-1]:g} (1: no loss); "
                    f"{evaluation.protocol.episodes} episodes per point and seed, 95 % intervals. From "
                    "`sb3-spikeplastic study report`; every noise level and comparison: table.md, "
                    "verdicts.md.",
                    "",
                    *short,
                    "",
                ]
                lines += section + [""]
                points += pts
                if name != "robustness":
                    verdict_lines += [f"# evaluation {name!r}", ""]
                verdict_lines += verdict_table([r for r in rows if not r.get("matched")]) + matched_table(rows)
                verdict_rows += rows
                written.append(folder / f"{prefix}{name}.png")
                fig.savefig(written[-1], dpi=120)
                plt.close(fig)
        for name in study.evaluations:
            if (table := ablation_table(study, data, env, name, kind, boot)) is not None:
                written.append(_write_text(folder / f"{prefix}ablation_{name}.md", table[0]))
                if table[1]:
                    written.append(_write_csv(folder / f"{prefix}ablation_{name}.csv", table[1]))
        if env in data.training:
            written.append(folder / f"{prefix}training_curves.png")
            written.append(
                _write_csv(folder / f"{prefix}curves.csv", training_curves(study, env, data.training[env], written[-1]))
            )
        missing = [m for m in data.missing if m.startswith(f"{env} ")]
        if missing:
            lines += [
                "## Missing",
                "",
                f"{len(missing)} raw file(s) not there yet:",
                "",
                *[f"* {m}" for m in missing],
                "",
            ]
        if lines:
            written.append(_write_text(folder / f"{prefix}table.md", "\n".join(lines).rstrip("\n") + "\n"))
        if points:
            written.append(_write_csv(folder / f"{prefix}points.csv", points))
            written.append(_write_text(folder / f"{prefix}summary.md", "\n".join(summary).rstrip("\n") + "\n"))
        if verdict_rows:
            written.append(_write_csv(folder / f"{prefix}verdicts.csv", verdict_rows))
            written.append(_write_text(folder / f"{prefix}verdicts.md", "\n".join(verdict_lines).rstrip("\n") + "\n"))
        if log is not None:
            log("\n".join(lines).rstrip())
    if log is not None and data.missing:
        log(f"missing: {len(data.missing)} raw file(s) (listed in table.md)")
    return written


def report_command(
    study_file: str, folder: Optional[str] = None, log_folder: str = "logs", name: Optional[str] = None
) -> Callable[[], int]:
    """``sb3-spikeplastic study report FILE``: the study file is checked (``ValueError``); returns the work."""
    from .declaration import load_study_file

    study, path = load_study_file(study_file)
    where = Path(folder) if folder else Path(log_folder) / "study" / (name or path.stem)
    if not StudyFolder(where).has_data():
        raise ValueError(
            f"{str(where)!r} holds no study (no episodes/ or training/ folder); run "
            "`sb3-spikeplastic study FILE` first, or pass the study's folder with --folder"
        )

    def work() -> int:
        paths = write_report(study, where)
        print(f"wrote {', '.join(str(p) for p in paths)}")
        return 0

    return work
