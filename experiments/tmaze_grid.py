"""The cue-association experiment (paper §3.1, Fig. 2): every rule on both noise levels over several seeds.

Runs ``sb3-spikeplastic train`` for each (environment, rule, seed) in parallel processes, one torch thread each
(a thread pool that waits on subprocesses: standard tools only), with a deterministic 100-episode evaluation
every ``--eval-freq`` steps, then aggregates the run folders into ``--out``:

* ``success_curves.png`` / ``curves.csv`` — evaluation success rate vs environment steps, mean and min-max band
  over seeds, one panel per noise level (paper Fig. 2 A-B);
* ``firing_rates.png`` — hidden-layer firing rate during training per rule on the high-noise maze (Fig. 2 C-D);
* ``summary.csv`` / ``summary.md`` — per environment and rule: final and best success, environment steps and
  minutes to 0.9 and 0.97 (per seed; "-" where never reached), and the success of the final model and of the
  best evaluated model (``best_model.zip``) on ``--heldout-episodes`` (1000) episodes of seeds no evaluation during
  training saw; ``table.md`` the same, one row per rule.

Usage::

    python experiments/tmaze_grid.py                                   # full grid (hours on 2 cores)
    python experiments/tmaze_grid.py --rules static dp-oja --envs TMazeCue-v0 --seeds 0 -n 50000
    python experiments/tmaze_grid.py --aggregate-only                  # re-aggregate existing run folders
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

#: The neuromodulation stabiliser (bounded modulation, see plasticity.modulatory_signal) with W_m starting at
#: 5 I, so that M = tanh(W_m r_post) ~ 0.6-0.8 at the initial hidden rates (with the paper's W_m ~ I, M ~ r_post
#: ~ 0.2 makes the Hebbian term 5x weaker than the DP rules' at initialisation).
STABILISED = ["policy_kwargs.rule_kwargs.modulation=tanh", "policy_kwargs.rule_kwargs.wm_init_gain=5"]
#: Grid entries: a rule name, or ``<rule>+tanh`` for that rule with the stabiliser's overrides.
VARIANTS = {"static": [], "dp-linear": [], "dp-oja": [], "dp-bcm": [], "ndp-oja": [], "ndp-bcm": [],
            "ndp-oja+tanh": STABILISED, "ndp-bcm+tanh": STABILISED}
RULES = tuple(VARIANTS)
ENVS = ("TMazeCue-v0", "TMazeCueNoisy-v0")
#: First environment seed of the held-out evaluation (EvalCallback's evaluations use the training seed's range).
HELDOUT_SEED = 1_000_000



def run_folder(env: str, variant: str, seed: int, args: argparse.Namespace) -> Path:
    return args.out / "runs" / f"{env}_{variant}_{seed}"


def train_command(env: str, variant: str, seed: int, args: argparse.Namespace) -> list[str]:
    overrides = [*VARIANTS[variant], *args.hyperparams]
    return [cli(), "train", "--env", env, "--rule", variant.split("+")[0], "--seed", str(seed),
            "-n", str(args.n_timesteps), "-f", str(run_folder(env, variant, seed, args)),
            "--eval-freq", str(args.eval_freq), "--eval-episodes", "100", "--torch-threads", "1",
            "--no-progress", "-v", "0", *(["--hyperparams", *overrides] if overrides else [])]


def heldout_command(env: str, variant: str, seed: int, args: argparse.Namespace, best: bool = False) -> list[str]:
    """Evaluate the run's final model (``best``: its ``best_model.zip``) on ``--heldout-episodes`` episodes from
    seeds the training's evaluations never used: 100-episode evaluations have a standard error of ~0.02 near
    0.95, so the best of several of them overstates the selected model's success rate."""
    (run,) = sorted(run_folder(env, variant, seed, args).glob("ppo/*_*"))[-1:]
    return [cli(), "evaluate", "--run", str(run), *(["--best"] if best else []), "--episodes",
            str(args.heldout_episodes), "--n-envs", "10", "--seed", str(HELDOUT_SEED), "--torch-threads", "1",
            "-o", str(run / ("heldout_best.json" if best else "heldout.json"))]



def read_progress(run: Path) -> dict[str, np.ndarray]:
    with open(run / "progress.csv") as f:
        rows = list(csv.DictReader(f))

    def column(name):
        return np.array([float(r[name]) if r.get(name) not in (None, "") else np.nan for r in rows])

    return {k: column(k) for k in ("time/total_timesteps", "time/time_elapsed", "snn/layer0/spike_rate")}


def load_run(folder: Path) -> dict | None:
    runs = sorted(folder.glob("ppo/*_*"))
    if not runs or not (runs[-1] / "evaluations.npz").exists():
        return None
    run = runs[-1]
    env_id = run.name.rsplit("_", 1)[0]
    meta = yaml.safe_load((run / env_id / "args.yml").read_text())
    variant = folder.name[len(env_id) + 1:].rsplit("_", 1)[0]  # folder: <env>_<variant>_<seed>
    evaluations = np.load(run / "evaluations.npz")
    progress = read_progress(run)
    steps = evaluations["timesteps"]
    known = ~np.isnan(progress["time/total_timesteps"]) & ~np.isnan(progress["time/time_elapsed"])
    minutes = np.interp(steps, progress["time/total_timesteps"][known], progress["time/time_elapsed"][known]) / 60
    heldout = {name: json.loads((run / f"{name}.json").read_text()) if (run / f"{name}.json").exists() else {}
               for name in ("heldout", "heldout_best")}
    return dict(env=env_id, rule=variant, seed=meta["seed"], steps=steps, minutes=minutes,
                success=evaluations["successes"].mean(axis=1), progress=progress,
                heldout=heldout["heldout"].get("success_rate", np.nan),
                heldout_best=heldout["heldout_best"].get("success_rate", np.nan),
                heldout_episodes=heldout["heldout"].get("episodes", 0))


def first_reaching(run: dict, level: float) -> tuple[float, float]:
    hit = np.flatnonzero(run["success"] >= level)
    return (float(run["steps"][hit[0]]), float(run["minutes"][hit[0]])) if hit.size else (np.nan, np.nan)


def rule_table(summary: list[dict]) -> str:
    """One row per (environment, rule): per-seed best / final success and steps to 0.9 / 0.97 (the tables of
    docs/reproducing-tmaze.md)."""
    def k(v):
        return "-" if v != v else f"{v / 1000:.0f}k"

    lines = ["| env | rule | seeds | best success | final success | seeds reaching 0.97 | steps to 0.9 | steps to 0.97 "
             "| held-out: final model | held-out: best model |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    for row in summary:
        groups.setdefault((row["env"], row["rule"]), []).append(row)
    for (env, rule), rows in groups.items():
        hits = sum(r["best_success"] >= 0.97 for r in rows)
        best = " / ".join(f"{r['best_success']:.2f}" for r in rows)
        final = " / ".join(f"{r['final_success']:.2f}" for r in rows)
        to_90 = " / ".join(k(r["steps_to_0_9"]) for r in rows)
        to_97 = " / ".join(k(r["steps_to_0_97"]) for r in rows)
        heldout, heldout_best = (" / ".join("-" if r[key] != r[key] else f"{r[key]:.2f}" for r in rows)
                                 for key in ("heldout_success", "heldout_best_success"))
        lines.append(f"| {env} | {rule} | {len(rows)} | {best} | {final} | {hits}/{len(rows)} | {to_90} | {to_97} "
                     f"| {heldout} | {heldout_best} |")
    return "\n".join(lines) + "\n"


def aggregate(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for folder in sorted((out / "runs").glob("*")) if (r := load_run(folder)) is not None]
    if not runs:
        print(f"no finished runs under {out / 'runs'}")
        return
    envs = [e for e in ENVS if any(r["env"] == e for r in runs)]
    rules = [k for k in RULES if any(r["rule"] == k for r in runs)]
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4), squeeze=False)
    summary, curves = [], []
    for ax, env in zip(axes[0], envs):
        for rule in rules:
            group = [r for r in runs if r["env"] == env and r["rule"] == rule]
            if not group:
                continue
            grid = np.unique(np.concatenate([r["steps"] for r in group]))
            ys = np.stack([np.interp(grid, r["steps"], r["success"]) for r in group])
            line, = ax.plot(grid, ys.mean(0), label=f"{rule} (n={len(group)})")
            ax.fill_between(grid, ys.min(0), ys.max(0), alpha=0.2, color=line.get_color())
            curves += [dict(env=env, rule=rule, steps=int(s), mean=m, lo=lo, hi=hi)
                       for s, m, lo, hi in zip(grid, ys.mean(0), ys.min(0), ys.max(0))]
            for r in sorted(group, key=lambda r: r["seed"]):
                (s90, m90), (s97, m97) = first_reaching(r, 0.9), first_reaching(r, 0.97)
                summary.append(dict(env=env, rule=rule, seed=r["seed"], final_success=float(r["success"][-1]),
                                    best_success=float(r["success"].max()), steps_to_0_9=s90, minutes_to_0_9=m90,
                                    steps_to_0_97=s97, minutes_to_0_97=m97, total_steps=int(r["steps"][-1]),
                                    total_minutes=float(r["minutes"][-1]), heldout_success=r["heldout"],
                                    heldout_best_success=r["heldout_best"], heldout_episodes=r["heldout_episodes"]))
        ax.axhline(0.97, color="k", ls=":", lw=1)
        ax.set(title=env, xlabel="environment steps", ylabel="success rate (100 deterministic episodes)", ylim=(0, 1.02))
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "success_curves.png", dpi=120)
    noisy = [r for r in runs if r["env"] == "TMazeCueNoisy-v0"] or runs
    fig, ax = plt.subplots(figsize=(6, 4))
    for rule in rules:
        for i, r in enumerate(x for x in noisy if x["rule"] == rule):
            p = r["progress"]
            ax.plot(p["time/total_timesteps"], p["snn/layer0/spike_rate"], color=f"C{rules.index(rule)}",
                    label=rule if i == 0 else None, lw=1)
    ax.set(title=f"hidden-layer firing rate ({noisy[0]['env']})", xlabel="environment steps",
           ylabel="spikes per neuron per ms")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "firing_rates.png", dpi=120)
    for name, rows in (("summary.csv", summary), ("curves.csv", curves)):
        with open(out / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    fmt = lambda v: "-" if v != v else (f"{v:,.0f}" if v >= 100 else f"{v:.2f}")  # noqa: E731  (NaN: never)
    lines = ["| env | rule | seed | final | best | steps to 0.9 | min to 0.9 | steps to 0.97 | min to 0.97 "
             "| held-out final | held-out best |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['env']} | {r['rule']} | {r['seed']} | {r['final_success']:.2f} | {r['best_success']:.2f} | "
              f"{fmt(r['steps_to_0_9'])} | {fmt(r['minutes_to_0_9'])} | {fmt(r['steps_to_0_97'])} | "
              f"{fmt(r['minutes_to_0_97'])} | {fmt(r['heldout_success'])} | {fmt(r['heldout_best_success'])} |"
              for r in summary]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "table.md").write_text(rule_table(summary))
    print("\n".join(lines))
    print(f"wrote {out}/success_curves.png, firing_rates.png, summary.csv, summary.md, curves.csv")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rules", nargs="+", default=list(RULES), choices=RULES)
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=ENVS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("-n", "--n-timesteps", type=int, default=200_000)
    parser.add_argument("--eval-freq", type=int, default=5_000, help="environment steps between evaluations")
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="parallel training processes")
    parser.add_argument("--hyperparams", nargs="*", default=[], help="overrides passed to every run")
    parser.add_argument("--out", type=Path, default=Path("results/tmaze"))
    parser.add_argument("--heldout-episodes", type=int, default=1000,
                        help="episodes of the final model's held-out evaluation (0: none)")
    parser.add_argument("--aggregate-only", action="store_true")
    args = parser.parse_args(argv)
    if not args.aggregate_only:
        # Seed-major order: a grid stopped early still has every rule on both mazes for the first seeds.
        jobs = [(e, r, s) for s in args.seeds for e in args.envs for r in args.rules]
        print(f"{len(jobs)} runs, {args.jobs} at a time; logs under {args.out / 'logs'}")
        def launch(job):
            commands = [lambda: train_command(*job, args)]
            if args.heldout_episodes:
                commands += [lambda: heldout_command(*job, args), lambda: heldout_command(*job, args, best=True)]
            env, rule, seed = job
            return run_one(commands, args.out / "logs" / f"{env}_{rule}_{seed}.log")

        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(launch, jobs))
        failed = [job for job, code in zip(jobs, codes) if code]
        if failed:
            print(f"failed runs (see their logs): {failed}", file=sys.stderr)
    aggregate(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
