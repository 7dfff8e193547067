"""The tables of the HalfCheetah experiment (paper Fig. 4 E-H) from the raw per-episode returns of
``experiments/halfcheetah_grid.py``, with two-stage bootstrap intervals (seeds, then episodes:
:mod:`sb3_spikeplastic.intervals`).

Reads ``<out>/robustness/<model>/robustness_HalfCheetah-v5_<noise>_episodes.csv`` (models named
``<variant>@<budget>_s<seed>``; a group is ``<variant>@<budget>``) and the run folders under ``<out>/runs``, and
writes into ``<out>``:

* ``table.md`` — per group: R0 (the sigma = 0 return, 100 episodes per seed: the final evaluation) per seed and
  its mean with a 95 % interval; per noise type the absolute return at every sigma beside its ratio to R0
  (:func:`sb3_spikeplastic.robustness.return_ratio`, averaged over seeds), and the area under the ratio curve
  (trapezoid over sigma divided by the sigma range: 1 = no loss) with its interval. Models whose R0 is below
  ``--learned-threshold`` did not learn to run; they are listed apart and left out of every ratio and comparison
  (a ratio near 1 of a model that never moved says nothing about robustness).
* ``verdicts.md`` — per noise type and budget: each plastic group, and all plastic models pooled, against the
  static SNN of the same budget; each baseline against the static SNN and against ``dp-oja`` (the rule of the
  HalfCheetah entry; a reference fixed in advance, where the best plastic group would be picked on the same
  data): the difference of the AUCs and of the absolute returns at the largest sigma, with intervals, and a
  verdict (resolved only when the interval excludes 0).
* ``fig4.csv`` (every group x noise x sigma: return and ratio with intervals), ``verdicts.csv``, ``runs.csv``
  (per run: steps, minutes, the gradient norm's median over the second half), ``curves.csv``;
* ``robustness.png`` (return and ratio against sigma, per noise type) and ``training_curves.png`` (Fig. 4 E).

Usage: ``python experiments/fig4_table.py --out results/halfcheetah/fig4``.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np
from halfcheetah_grid import BASELINES, ENV, NOISES

from sb3_spikeplastic.intervals import Interval, bootstrap_difference, bootstrap_interval
from sb3_spikeplastic.robustness import return_ratio

STATIC = "static"
#: The plastic rule the baselines are compared with: the rule of the HalfCheetah entry.
PLASTIC_REFERENCE = "dp-oja"
#: R0 below this: the model did not learn to run (a policy standing still scores about 0, a random one about -280).
LEARNED_THRESHOLD = 1000.0


def read_episodes(out: Path) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """model -> noise -> (sigmas, returns of shape (n_sigma, n_episodes))."""
    data: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = defaultdict(dict)
    for path in sorted(out.glob(f"robustness/*/robustness_{ENV}_*_episodes.csv")):
        cells: dict[str, dict[float, list[tuple[int, float]]]] = defaultdict(lambda: defaultdict(list))
        noise = ""
        with open(path) as f:
            for row in csv.DictReader(f):
                noise = row["noise_type"]
                cells[row["model"]][float(row["sigma"])].append((int(row["episode"]), float(row["return"])))
        for model, by_sigma in cells.items():
            sigmas = np.array(sorted(by_sigma))
            returns = np.array([[r for _, r in sorted(by_sigma[s])] for s in sigmas])
            data[model][noise] = (sigmas, returns)
    return data


def group_of(model: str) -> str:
    return model.rsplit("_s", 1)[0]


def variant_of(group: str) -> str:
    return group.split("@")[0]


def budget_of(group: str) -> str:
    return group.split("@")[1] if "@" in group else ""


def r0(seed_data: np.ndarray) -> float:
    return float(seed_data[0].mean())


def mean_return_at(j: int):
    return lambda seeds: float(np.mean([d[j].mean() for d in seeds]))


def ratio_at(j: int):
    return lambda seeds: float(np.mean([return_ratio(d[j].mean(), d[0].mean()) for d in seeds]))


def auc(sigmas: np.ndarray):
    span = sigmas[-1] - sigmas[0]

    def statistic(seeds) -> float:
        values = []
        for d in seeds:
            means = d.mean(axis=-1)
            ratios = np.array([return_ratio(m, means[0]) for m in means])
            values.append(np.trapezoid(ratios, sigmas) / span)
        return float(np.mean(values))

    return statistic


def fmt(interval: Interval, digits: int = 0) -> str:
    return f"{interval.estimate:.{digits}f} [{interval.low:.{digits}f}, {interval.high:.{digits}f}]"


def summary_cells(seeds: list[np.ndarray], sigmas: np.ndarray, reference: list[np.ndarray] | None = None) -> list[str]:
    """A control table's cells for one group: R0, AUC and the return at the largest sigma, then the AUC and return
    differences from ``reference`` (empty without one); intervals as everywhere in the protocol."""
    top = len(sigmas) - 1
    cells = [fmt(bootstrap_interval(seeds, mean_return_at(0))), fmt(bootstrap_interval(seeds, auc(sigmas)), 2),
             fmt(bootstrap_interval(seeds, mean_return_at(top)))]
    if reference is None:
        return cells + ["", ""]
    return cells + [fmt(bootstrap_difference(seeds, reference, auc(sigmas)), 2),
                    fmt(bootstrap_difference(seeds, reference, mean_return_at(top)))]


def read_runs(out: Path) -> list[dict]:
    """Per run folder root (``runs/<variant>_<seed>``): steps, wall-clock minutes, late gradient norm."""
    rows = []
    for root in sorted((out / "runs").glob("*_*")):
        variant, seed = root.name.rsplit("_", 1)
        minutes, steps, norms = 0.0, 0, []
        for folder in sorted(root.glob(f"ppo/{ENV}_*")):  # a run and the runs continuing it
            progress_path = folder / "progress.csv"
            if not progress_path.exists():
                continue
            with open(progress_path) as f:
                progress = list(csv.DictReader(f))
            timed = [r for r in progress if r.get("time/time_elapsed")]
            if timed:
                minutes += float(timed[-1]["time/time_elapsed"]) / 60
                steps = max(steps, int(float(timed[-1]["time/total_timesteps"])))
            norms += [float(r["train/grad_norm"]) for r in progress if r.get("train/grad_norm")]
        late = float(np.median(norms[len(norms) // 2:])) if norms else float("nan")
        rows.append(dict(variant=variant, seed=int(seed), steps=steps, minutes=round(minutes, 1), grad_norm=late))
    return rows


def training_curves(out: Path, runs: list[dict]) -> list[dict]:
    """Fig. 4 E: every variant's deterministic evaluation return against steps (mean and range over seeds)."""
    import matplotlib.pyplot as plt

    curves = []
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for variant in dict.fromkeys(r["variant"] for r in runs):
        data = []
        for run in (r for r in runs if r["variant"] == variant):
            steps, returns = [], []
            for folder in sorted((out / "runs" / f"{variant}_{run['seed']}").glob(f"ppo/{ENV}_*")):
                if (folder / "evaluations.npz").exists():
                    evaluations = np.load(folder / "evaluations.npz")
                    steps.append(evaluations["timesteps"])
                    returns.append(evaluations["results"].mean(axis=1))
            if steps:
                s, y = np.concatenate(steps), np.concatenate(returns)
                order = np.argsort(s, kind="stable")
                data.append((s[order], y[order]))
        if not data:
            continue
        grid = np.unique(np.concatenate([s for s, _ in data]))
        # A seed counts only up to its own last evaluation: the runs of a variant may have different lengths.
        ys = np.stack([np.where(grid <= s[-1], np.interp(grid, s, y), np.nan) for s, y in data])
        n = np.isfinite(ys).sum(0)
        mean, low, high = np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)
        line, = ax.plot(grid, mean, label=f"{variant} (n={len(data)})")
        ax.fill_between(grid, low, high, alpha=0.2, color=line.get_color())
        curves += [dict(variant=variant, steps=int(s), seeds=int(k), mean=round(float(m), 1),
                        low=round(float(lo), 1), high=round(float(hi), 1))
                   for s, k, m, lo, hi in zip(grid, n, mean, low, high)]
    ax.set(title=f"{ENV}: deterministic evaluation return during training", xlabel="environment steps",
           ylabel="mean return")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "training_curves.png", dpi=120)
    plt.close(fig)
    return curves


def write_csv(path: Path, rows: list[dict]) -> None:
    if rows:
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


def verdict(difference: Interval, better: str, worse: str) -> str:
    if difference.low > 0:
        return better
    if difference.high < 0:
        return worse
    return "not resolved"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("results/halfcheetah/fig4"))
    parser.add_argument("--learned-threshold", type=float, default=LEARNED_THRESHOLD,
                        help="R0 below this: the model did not learn to run (listed apart)")
    parser.add_argument("--resamples", type=int, default=2000)
    args = parser.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = args.out
    runs = read_runs(out)
    write_csv(out / "runs.csv", runs)
    if runs:
        write_csv(out / "curves.csv", training_curves(out, runs))
    data = read_episodes(out)
    if not data:
        print(f"no robustness episodes under {out / 'robustness'}")
        return 0
    noises = [n for n in NOISES if any(n in d for d in data.values())]
    first = {m: d[noises[0]][1] for m, d in data.items() if noises[0] in d}
    learned = {m for m, d in first.items() if r0(d) >= args.learned_threshold}
    groups = list(dict.fromkeys(group_of(m) for m in sorted(data, key=lambda m: (budget_of(group_of(m)), m))))

    def seeds_of(group: str, noise: str, only_learned: bool = True) -> list[np.ndarray]:
        return [data[m][noise][1] for m in sorted(data) if group_of(m) == group and noise in data[m]
                and (m in learned or not only_learned)]

    boot = dict(n_resamples=args.resamples)
    lines = [f"# {ENV}: return under noise, one protocol for every model", "",
             f"R0 and every noise level: {next(iter(first.values())).shape[-1]} deterministic episodes per seed, the "
             "same episode seeds for every model and sigma; [95 % interval]: two-stage bootstrap over seeds and "
             f"episodes; models with R0 < {args.learned_threshold:g} are listed apart and excluded below.", "",
             "| model | seeds | R0 per seed | R0 [95 % interval] |", "|---|---|---|---|"]
    for group in groups:
        members = [m for m in sorted(data) if group_of(m) == group and m in first]
        kept = [first[m] for m in members if m in learned]
        per_seed = " / ".join(f"{r0(first[m]):.0f}" + ("" if m in learned else " (did not learn)") for m in members)
        lines.append(f"| {group} | {len(kept)} of {len(members)} | {per_seed} | "
                     f"{fmt(bootstrap_interval(kept, mean_return_at(0), **boot)) if kept else '-'} |")
    failed = sorted(m for m in first if m not in learned)
    if failed:
        lines += ["", f"Did not learn (R0 < {args.learned_threshold:g}): " + ", ".join(failed) + "."]

    figure_rows, verdict_rows = [], []
    fig, axes = plt.subplots(2, len(noises), figsize=(5 * len(noises), 8), squeeze=False)
    for col, noise in enumerate(noises):
        sigmas = next(d[noise][0] for d in data.values() if noise in d)
        lines += ["", f"## {noise} noise", "",
                  "Absolute return (ratio to R0) at each sigma, and the area under the ratio curve.", "",
                  "| model | seeds | " + " | ".join(f"sigma {s:g}" for s in sigmas) + " | AUC [95 % interval] |",
                  "|---|---|" + "---|" * len(sigmas) + "---|"]
        for group in groups:
            seeds = seeds_of(group, noise)
            if not seeds:
                continue
            cells = []
            returns, ratios = [], []
            for j, sigma in enumerate(sigmas):
                ret = bootstrap_interval(seeds, mean_return_at(j), **boot)
                rat = bootstrap_interval(seeds, ratio_at(j), **boot)
                returns.append(ret)
                ratios.append(rat)
                cells.append(f"{ret.estimate:.0f} ({rat.estimate:.2f})")
                figure_rows.append(dict(group=group, noise=noise, sigma=sigma, seeds=len(seeds),
                                        **{f"return_{k}": round(v, 1) for k, v in ret._asdict().items()},
                                        **{f"ratio_{k}": round(v, 4) for k, v in rat._asdict().items()}))
            area = bootstrap_interval(seeds, auc(sigmas), **boot)
            lines.append(f"| {group} | {len(seeds)} | " + " | ".join(cells) + f" | {fmt(area, 2)} |")
            for row, values in ((0, returns), (1, ratios)):
                axes[row, col].errorbar(sigmas, [v.estimate for v in values],
                                        yerr=[[v.estimate - v.low for v in values], [v.high - v.estimate for v in values]],
                                        capsize=3, marker="o", ms=3, label=f"{group} (n={len(seeds)})")
        axes[0, col].set(title=f"{noise} noise", ylabel="return")
        axes[1, col].set(xlabel="sigma", ylabel="return ratio to sigma = 0")
        axes[1, col].axhline(1.0, color="0.6", ls=":", lw=0.8)
        axes[0, col].legend(fontsize=7)

        # Verdicts: each plastic group and all plastic models pooled against the static SNN of the same budget;
        # each baseline against the static SNN and the entry's plastic rule of that budget.
        top = len(sigmas) - 1
        for budget in dict.fromkeys(budget_of(g) for g in groups):
            at_budget = [g for g in groups if budget_of(g) == budget and seeds_of(g, noise)]
            static = f"{STATIC}@{budget}"
            plastic = [g for g in at_budget if variant_of(g) not in (STATIC, *BASELINES)]
            comparisons = []
            if static in at_budget:
                comparisons += [(g, static, seeds_of(g, noise)) for g in plastic]
                pooled = [s for g in plastic for s in seeds_of(g, noise)]
                if len(plastic) > 1:
                    comparisons.append((f"plastic@{budget} (pooled: {', '.join(variant_of(g) for g in plastic)})",
                                        static, pooled))
            for reference in (static, f"{PLASTIC_REFERENCE}@{budget}"):
                if reference in at_budget:
                    comparisons += [(g, reference, seeds_of(g, noise)) for g in at_budget
                                    if variant_of(g) in BASELINES]
            for name, reference, seeds in comparisons:
                d_auc = bootstrap_difference(seeds, seeds_of(reference, noise), auc(sigmas), **boot)
                d_top = bootstrap_difference(seeds, seeds_of(reference, noise), mean_return_at(top), **boot)
                d_r0 = bootstrap_difference(seeds, seeds_of(reference, noise), mean_return_at(0), **boot)
                verdict_rows.append(dict(
                    noise=noise, model=name, reference=reference, seeds=len(seeds),
                    reference_seeds=len(seeds_of(reference, noise)),
                    **{f"auc_difference_{k}": round(v, 4) for k, v in d_auc._asdict().items()},
                    **{f"return_at_sigma_{sigmas[top]:g}_difference_{k}": round(v, 1)
                       for k, v in d_top._asdict().items()},
                    **{f"r0_difference_{k}": round(v, 1) for k, v in d_r0._asdict().items()},
                    auc_verdict=verdict(d_auc, "loses less", "loses more"),
                    return_verdict=verdict(d_top, "higher", "lower")))
    fig.tight_layout()
    fig.savefig(out / "robustness.png", dpi=120)
    plt.close(fig)

    verdict_lines = [f"# {ENV}: verdicts", "",
                     "Differences (model minus reference) with two-stage bootstrap 95 % intervals; a verdict is "
                     "given only when the interval excludes 0. AUC: area under the ratio-to-R0 curve (relative "
                     f"loss); return at the largest sigma: absolute. Generated by `experiments/fig4_table.py`.", ""]
    for noise in noises:
        rows = [r for r in verdict_rows if r["noise"] == noise]
        if not rows:
            continue
        top_key = next(k for k in rows[0] if k.startswith("return_at_sigma_")).split("_difference")[0]
        verdict_lines += [f"## {noise} noise", "",
                          f"| model | reference | seeds | AUC difference | relative loss | R0 difference | "
                          f"{top_key.replace('_', ' ')} difference | absolute return under noise |",
                          "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            ival = lambda prefix, digits: fmt(Interval(r[f"{prefix}_estimate"], r[f"{prefix}_low"], r[f"{prefix}_high"]),
                                              digits)
            verdict_lines.append(
                f"| {r['model']} | {r['reference']} | {r['seeds']} vs {r['reference_seeds']} | "
                f"{ival('auc_difference', 3)} | {r['auc_verdict']} | {ival('r0_difference', 0)} | "
                f"{ival(top_key + '_difference', 0)} | {r['return_verdict']} |")
        verdict_lines.append("")
    write_csv(out / "fig4.csv", figure_rows)
    write_csv(out / "verdicts.csv", verdict_rows)
    (out / "table.md").write_text("\n".join(lines) + "\n")
    (out / "verdicts.md").write_text("\n".join(verdict_lines) + "\n")
    print("\n".join(lines))
    print()
    print("\n".join(verdict_lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
