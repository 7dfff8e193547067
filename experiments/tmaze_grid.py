"""The cue-association experiment (paper §3.1, Fig. 2): every rule on both noise levels over several seeds.

The grid is ``experiments/tmaze_grid.yml`` (8 variants x 2 mazes x 3 seeds, 200k steps, a deterministic
100-episode evaluation every 5000 steps, the final and best models on 1000 held-out episodes); this script selects
part of it from its flags, runs it with ``sb3-spikeplastic grid``'s workers (``--jobs`` processes, one torch
thread each, sharing an Optuna study in ``--out``: an interrupted grid continues where it stopped, and a killed
worker's cell is run again), then aggregates the run folders into ``--out``:

* ``success_curves.png`` / ``curves.csv`` — evaluation success rate vs environment steps, mean and min-max band
  over seeds, one panel per noise level (paper Fig. 2 A-B);
* ``firing_rates.png`` — hidden-layer firing rate during training per rule on the high-noise maze (Fig. 2 C-D);
* ``summary.csv`` / ``summary.md`` — per environment and rule: final and best success, environment steps and
  minutes to 0.9 and 0.97 (per seed; "-" where never reached), and the success of the final model and of the
  best evaluated model (``best_model.zip``) on ``--heldout-episodes`` (1000) episodes of seeds no evaluation during
  training saw; ``table.md`` the same, one row per rule;
* the grid's own ``grid.csv`` / ``grid.md`` (final held-out return and success per cell).

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
from pathlib import Path

import numpy as np
import yaml

from sb3_spikeplastic import grid as grid_mod

GRID_FILE = Path(__file__).resolve().parent / "tmaze_grid.yml"
#: The grid's variants: a rule name, or ``<rule>+tanh`` for that rule with the NDP stabiliser.
RULES = tuple(grid_mod.load_grid(GRID_FILE).variants)
ENVS = ("TMazeCue-v0", "TMazeCueNoisy-v0")


def selected_grid(args: argparse.Namespace) -> grid_mod.Grid:
    """The part of ``--grid`` that the flags select, with their settings."""
    grid = grid_mod.load_grid(args.grid)
    final = grid.final_eval
    if args.heldout_episodes is not None:
        final = grid_mod.FinalEval(args.heldout_episodes, final.seed, final.n_envs,
                                   final.best_model and args.heldout_episodes > 0)
    return grid.select(envs=args.envs, variants=args.rules, seeds=args.seeds, final_eval=final,
                       hyperparams=[*grid.hyperparams, *args.hyperparams],
                       **({"n_timesteps": args.n_timesteps} if args.n_timesteps else {}),
                       **({"eval_freq": args.eval_freq} if args.eval_freq is not None else {}))


def read_progress(run: Path) -> dict[str, np.ndarray]:
    with open(run / "progress.csv") as f:
        rows = list(csv.DictReader(f))

    def column(name):
        return np.array([float(r[name]) if r.get(name) not in (None, "") else np.nan for r in rows])

    return {k: column(k) for k in ("time/total_timesteps", "time/time_elapsed", "snn/layer0/spike_rate")}


def read_heldout(run: Path, name: str) -> dict:
    """A held-out evaluation of a run: ``final_eval[_best].json`` written by the grid (``heldout[_best].json`` in
    older results folders); ``{}`` if there is none."""
    for file in (run / f"{name.replace('heldout', 'final_eval')}.json", run / f"{name}.json"):
        if file.exists():
            return json.loads(file.read_text())
    return {}


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
    heldout = {name: read_heldout(run, name) for name in ("heldout", "heldout_best")}
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


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grid", type=Path, default=GRID_FILE, help="grid file (default: tmaze_grid.yml)")
    parser.add_argument("--rules", nargs="+", choices=RULES, help="variants (default: the grid's)")
    parser.add_argument("--envs", nargs="+", choices=ENVS, help="default: the grid's")
    parser.add_argument("--seeds", nargs="+", type=int, help="default: the grid's (0 1 2)")
    parser.add_argument("-n", "--n-timesteps", type=int, help="default: the grid's (200000)")
    parser.add_argument("--eval-freq", type=int, help="environment steps between evaluations (default: the grid's, "
                        "5000)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="parallel training processes (workers)")
    parser.add_argument("--hyperparams", nargs="*", default=[], help="overrides passed to every run")
    parser.add_argument("--out", type=Path, default=Path("results/tmaze"), help="the grid's folder; its name is "
                        "the study's")
    parser.add_argument("--storage", help="a study shared with workers elsewhere (default: SQLite in --out)")
    parser.add_argument("--heldout-episodes", type=int, help="episodes of the final and best models' held-out "
                        "evaluations (default: the grid's, 1000; 0: none)")
    parser.add_argument("--aggregate-only", action="store_true")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    status = 0
    if not args.aggregate_only:
        job = grid_mod.prepare(selected_grid(args), args.out, args.out.name, args.storage)
        status = grid_mod.run(job, workers=args.jobs)
        if status:
            print(f"the grid stopped with status {status}: see {args.out / 'grid.md'}", file=sys.stderr)
    aggregate(args.out)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
