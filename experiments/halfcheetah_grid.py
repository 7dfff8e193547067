"""The locomotion experiment (paper §3.2, Fig. 4 E-H): every rule and the two baselines on HalfCheetah-v5 over
several seeds, then their robustness to joint-friction, action and observation noise.

Runs ``sb3-spikeplastic train`` for each (variant, seed) in parallel processes (one torch thread each), with
``--save-freq`` checkpoints and a deterministic
evaluation every ``--eval-freq`` steps; then evaluates each final model on ``--final-episodes`` deterministic
episodes, runs ``sb3-spikeplastic robustness`` on all final models side by side (the same noise draws for every
model), and aggregates into ``--out``:

* ``training_curves.png`` / ``curves.csv`` — evaluation return vs environment steps, mean and min-max band over
  seeds (Fig. 4 E);
* ``robustness.png`` — per noise type, the return ratio to sigma = 0 against sigma, mean and standard deviation
  over seeds (Fig. 4 F-H);
* ``table.md`` / ``summary.csv`` / ``robustness_summary.csv`` — per variant: final deterministic return per seed,
  steps, the gradient norm's median over the second half of training, skipped updates and wall-clock minutes per
  run; per group of models and noise type, the area under the ratio curve (trapezoid over
  sigma, divided by the sigma range: 1 = no loss) and the worst ratio, mean ± standard deviation over the models.

Variants: the rules of ``ppo.yml``'s HalfCheetah entry (``static``, ``dp-oja``...), ``<rule>+tanh`` (the
bounded-modulation stabiliser), and the baselines ``mlp`` (``--conf mlp``) and ``ppo_lstm`` (``--conf ppo_lstm``).

Running the same command again resumes the grid: finished runs are skipped, and a run cut short (killed, or
stopped with its machine) continues from its latest checkpoint with ``train --trained-agent``.

Usage::

    python experiments/halfcheetah_grid.py --variants static dp-oja ndp-oja mlp --seeds 0 1 2
    python experiments/halfcheetah_grid.py --aggregate-only
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml
from grid_common import cli, run_one

ENV = "HalfCheetah-v5"
STABILISED = ["policy_kwargs.rule_kwargs.modulation=tanh", "policy_kwargs.rule_kwargs.wm_init_gain=5"]
#: The plain NDP variants are the rules as the paper writes them (their default modulation is the bounded one).
PAPER_FORM = ["policy_kwargs.rule_kwargs.modulation=linear"]
RULES = ("static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm")
VARIANTS = (*RULES, "ndp-oja+tanh", "ndp-bcm+tanh", "mlp", "ppo_lstm")
NOISES = ("friction", "action", "obs")
#: First environment seed of the final and robustness evaluations (training's evaluations use the seed's range).
HELDOUT_SEED = 1_000_000



def run_root(variant: str, seed: int, args: argparse.Namespace) -> Path:
    return args.out / "runs" / f"{variant}_{seed}"


def latest_run(variant: str, seed: int, args: argparse.Namespace) -> Path | None:
    runs = sorted(run_root(variant, seed, args).glob(f"ppo/{ENV}_*"), key=lambda p: int(p.name.rsplit("_", 1)[1]))
    return runs[-1] if runs else None


def train_command(variant: str, seed: int, args: argparse.Namespace) -> list[str]:
    """The run's ``train`` command; a run cut short before (killed, or stopped with the machine) continues from
    its latest checkpoint (``--trained-agent``, a new run folder beside it) instead of starting over."""
    previous = latest_run(variant, seed, args)
    if previous is not None and any(previous.glob("rl_model_*_steps.zip")):
        return [cli(), "train", "--env", ENV, "--trained-agent", str(previous), "--seed", str(seed), "-n",
                str(args.n_timesteps), "-f", str(run_root(variant, seed, args)), "--eval-freq", str(args.eval_freq),
                "--eval-episodes", str(args.eval_episodes), "--save-freq", str(args.save_freq), "--torch-threads",
                "1", "--no-progress", "-v", "0"]
    if variant in ("mlp", "ppo_lstm"):
        selection = ["--conf", variant]
    else:
        selection = ["--rule", variant.split("+")[0]]
        form = STABILISED if variant.endswith("+tanh") else PAPER_FORM if variant.startswith("ndp-") else []
        overrides = [*form, *args.hyperparams]
        selection += ["--hyperparams", *overrides] if overrides else []
    return [cli(), "train", "--env", ENV, *selection, "--seed", str(seed), "-n", str(args.n_timesteps),
            "-f", str(run_root(variant, seed, args)), "--eval-freq", str(args.eval_freq), "--eval-episodes",
            str(args.eval_episodes), "--save-freq", str(args.save_freq), "--torch-threads", "1", "--no-progress",
            "-v", "0"]


def final_command(variant: str, seed: int, args: argparse.Namespace) -> list[str]:
    run = latest_run(variant, seed, args)
    return [cli(), "evaluate", "--run", str(run), "--episodes", str(args.final_episodes), "--seed",
            str(HELDOUT_SEED), "--torch-threads", "1", "-o", str(run / "final_eval.json")]



def finished_runs(args: argparse.Namespace) -> dict[str, Path]:
    """``<variant>_s<seed>`` -> run folder, for every run with a final model."""
    found = {}
    for folder in sorted((args.out / "runs").glob("*_*")):
        variant, seed = folder.name.rsplit("_", 1)
        run = latest_run(variant, int(seed), args)
        if run is not None and (run / f"{ENV}.zip").exists():
            found[f"{variant}_s{seed}"] = run
    return found


def robustness_commands(args: argparse.Namespace) -> list[list[str]]:
    runs = finished_runs(args)
    models = [f"{name}={run}" for name, run in runs.items()]
    return [[cli(), "robustness", "--models", *models, "--noise", noise, "--sigmas", *map(str, args.sigmas),
             "--episodes", str(args.robustness_episodes), "--n-envs", "5", "--seed", str(HELDOUT_SEED),
             "--torch-threads", "1", "-o", str(args.out / "robustness"), "--no-progress"] for noise in args.noises]


def read_evaluations(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """Evaluation steps and mean returns of a run and of the runs it continued (``--trained-agent``: the other
    run folders of the same variant and seed)."""
    steps, returns = [], []
    for folder in sorted(run.parent.glob(f"{ENV}_*")):
        if (folder / "evaluations.npz").exists():
            evaluations = np.load(folder / "evaluations.npz")
            steps.append(evaluations["timesteps"])
            returns.append(evaluations["results"].mean(axis=1))
    steps, returns = np.concatenate(steps), np.concatenate(returns)
    order = np.argsort(steps, kind="stable")
    return steps[order], returns[order]


def robustness_rows(args: argparse.Namespace, noise: str) -> list[dict]:
    """The rows of every ``robustness*/robustness_<env>_<noise>.csv`` under ``--out`` (models evaluated in several
    ``robustness`` runs with the same seed and sigmas see the same noise draws)."""
    rows = []
    for path in sorted(args.out.glob(f"robustness*/robustness_{ENV}_{noise}.csv")):
        with open(path) as f:
            rows += list(csv.DictReader(f))
    return rows


def variant_of(name: str) -> str:
    return name.rsplit("_s", 1)[0]


def aggregate(args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = finished_runs(args)
    if not runs:
        print(f"no finished runs under {args.out / 'runs'}")
        return
    variants = [v for v in VARIANTS if any(variant_of(n) == v for n in runs)]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    curves, summary = [], []
    for variant in variants:
        group = {n: r for n, r in runs.items() if variant_of(n) == variant and (r / "evaluations.npz").exists()}
        if not group:
            continue
        data = [read_evaluations(r) for r in group.values()]
        grid = np.unique(np.concatenate([s for s, _ in data]))
        ys = np.stack([np.interp(grid, s, y) for s, y in data])
        line, = ax.plot(grid, ys.mean(0), label=f"{variant} (n={len(group)})")
        ax.fill_between(grid, ys.min(0), ys.max(0), alpha=0.2, color=line.get_color())
        curves += [dict(variant=variant, steps=int(s), mean=m, lo=lo, hi=hi)
                   for s, m, lo, hi in zip(grid, ys.mean(0), ys.min(0), ys.max(0))]
    ax.axhline(1500, color="k", ls=":", lw=1)
    ax.set(title=f"{ENV}: deterministic evaluation return", xlabel="environment steps", ylabel="mean return")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "training_curves.png", dpi=120)

    # Robustness: per model, its ratio curve; grouped by the model name's variant (``<variant>_s<seed>``; a
    # robustness run may name checkpoints, e.g. ``dp-oja@300k_s0``).
    curves_of: dict[tuple[str, str], dict[str, list[tuple[float, float]]]] = {}
    for noise in NOISES:
        for row in robustness_rows(args, noise):
            models = curves_of.setdefault((variant_of(row["model"]), noise), {})
            models.setdefault(row["model"], []).append((float(row["sigma"]), float(row["ratio"])))
    noises = [n for n in NOISES if any(k[1] == n for k in curves_of)]
    groups = list(dict.fromkeys(k[0] for k in curves_of))
    robustness_summary = []
    if noises:
        fig, axes = plt.subplots(1, len(noises), figsize=(5 * len(noises), 4), squeeze=False)
        for ax, noise in zip(axes[0], noises):
            for group in groups:
                models = curves_of.get((group, noise))
                if not models:
                    continue
                sigmas = sorted({s for curve in models.values() for s, _ in curve})
                table = np.array([[dict(curve).get(s, np.nan) for s in sigmas] for curve in models.values()])
                ax.errorbar(sigmas, np.nanmean(table, 0), yerr=np.nanstd(table, 0), capsize=3, marker="o", ms=3,
                            label=f"{group} (n={len(models)})")
                span = sigmas[-1] - sigmas[0]
                auc = [np.trapezoid(row, sigmas) / span for row in table] if span > 0 else [np.nan]
                robustness_summary.append(dict(variant=group, noise=noise, models=len(models),
                                               auc_mean=float(np.mean(auc)), auc_std=float(np.std(auc)),
                                               worst_mean=float(np.mean(table.min(1))),
                                               worst_std=float(np.std(table.min(1)))))
            ax.axhline(1.0, color="0.6", ls=":", lw=0.8)
            ax.set(title=f"{noise} noise", xlabel="sigma", ylabel="return ratio to sigma = 0")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out / "robustness.png", dpi=120)

    for name, run in runs.items():
        final = run / "final_eval.json"
        meta = yaml.safe_load((run / ENV / "args.yml").read_text())
        minutes, steps, grad_norms, skipped = 0.0, 0, [], 0
        for folder in sorted(run.parent.glob(f"{ENV}_*")):  # the run and the runs it continued
            with open(folder / "progress.csv") as f:
                progress = list(csv.DictReader(f))
            rows = [r for r in progress if r.get("time/time_elapsed")]
            if rows:
                minutes += float(rows[-1]["time/time_elapsed"]) / 60
                steps = max(steps, int(float(rows[-1]["time/total_timesteps"])))
            grad_norms += [float(r["train/grad_norm"]) for r in progress if r.get("train/grad_norm")]
            skipped += sum(int(float(r["train/skipped_steps"])) for r in progress if r.get("train/skipped_steps"))
        # The gradient norm's scale over the second half of training: where a rule's loop makes it explode.
        late_norm = float(np.median(grad_norms[len(grad_norms) // 2:])) if grad_norms else np.nan
        summary.append(dict(variant=variant_of(name), seed=meta["seed"], steps=steps, minutes=minutes,
                            grad_norm=late_norm, skipped_steps=skipped,
                            final_return=json.loads(final.read_text())["mean_return"] if final.exists() else np.nan))
    for name, rows in (("summary.csv", summary), ("robustness_summary.csv", robustness_summary), ("curves.csv", curves)):
        if rows:
            with open(args.out / name, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)

    def cell(values, fmt):
        values = [v for v in values if v == v]
        return " / ".join(fmt.format(v) for v in values) or "-"

    lines = ["| variant | seeds | deterministic return, 10 episodes (per seed) | steps | gradient norm, median of the "
             "second half | skipped updates | wall-clock minutes (shared machine) |", "|---|---|---|---|---|---|---|"]
    for variant in variants:
        rows = sorted((r for r in summary if r["variant"] == variant), key=lambda r: r["seed"])
        lines.append(f"| {variant} | {len(rows)} | {cell([r['final_return'] for r in rows], '{:.0f}')} | "
                     f"{cell([r['steps'] for r in rows], '{:,}')} | {cell([r['grad_norm'] for r in rows], '{:.3g}')} "
                     f"| {cell([r['skipped_steps'] for r in rows], '{}')} | "
                     f"{cell([r['minutes'] for r in rows], '{:.0f}')} |")
    if robustness_summary:
        lines += ["", "| models | n | " + " | ".join(f"{n}: AUC | {n}: worst" for n in noises) + " |",
                  "|---|---|" + "---|---|" * len(noises)]
        for group in groups:
            found = {r["noise"]: r for r in robustness_summary if r["variant"] == group}
            n = max(r["models"] for r in found.values())
            cells = []
            for noise in noises:
                r = found.get(noise)
                cells += ([f"{r['auc_mean']:.2f} ± {r['auc_std']:.2f}", f"{r['worst_mean']:.2f} ± {r['worst_std']:.2f}"]
                          if r else ["-", "-"])
            lines.append(f"| {group} | {n} | " + " | ".join(cells) + " |")
    (args.out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=["static", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm", "mlp",
                                                          "ppo_lstm"], choices=VARIANTS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("-n", "--n-timesteps", type=int, default=1_000_000)
    parser.add_argument("--eval-freq", type=int, default=50_000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--save-freq", type=int, default=100_000)
    parser.add_argument("--final-episodes", type=int, default=10)
    parser.add_argument("--noises", nargs="+", default=list(NOISES), choices=NOISES)
    parser.add_argument("--sigmas", nargs="+", type=float, default=[0.0, 0.1, 0.2, 0.3, 0.5])
    parser.add_argument("--robustness-episodes", type=int, default=20)
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="parallel training processes")
    parser.add_argument("--hyperparams", nargs="*", default=[], help="overrides passed to every spiking run")
    parser.add_argument("--out", type=Path, default=Path("results/halfcheetah"))
    parser.add_argument("--aggregate-only", action="store_true")
    parser.add_argument("--skip-robustness", action="store_true")
    args = parser.parse_args(argv)
    if not args.aggregate_only:
        jobs = [(v, s) for s in args.seeds for v in args.variants]  # seed-major: a cut grid has every variant
        print(f"{len(jobs)} runs, {args.jobs} at a time; logs under {args.out / 'logs'}")

        def launch(job):
            run = latest_run(*job, args)
            if run is not None and (run / f"{ENV}.zip").exists():
                # finished before: the grid resumes where it stopped (with the final evaluation, if it is missing)
                if (run / "final_eval.json").exists():
                    return 0
                return run_one([lambda: final_command(*job, args)], args.out / "logs" / f"{job[0]}_{job[1]}.log")
            commands = [lambda: train_command(*job, args), lambda: final_command(*job, args)]
            return run_one(commands, args.out / "logs" / f"{job[0]}_{job[1]}.log")

        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(launch, jobs))
        failed = [job for job, code in zip(jobs, codes) if code]
        if failed:
            print(f"failed runs (see their logs): {failed}", file=sys.stderr)
        if not args.skip_robustness:
            with ThreadPoolExecutor(args.jobs) as pool:
                list(pool.map(lambda cmd: run_one([lambda: cmd], args.out / "logs" / "robustness.log"),
                              robustness_commands(args)))
    aggregate(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
