"""Learning curve of a run of the paper's HalfCheetah network (``--conf paper``): whether it trains, update by update.

Reads a run folder of ``sb3-spikeplastic train`` (and the runs it continued with ``--trained-agent``) and writes,
to ``--out``:

* ``curve.csv`` — per PPO update: environment steps, the training episodes' mean return, the gradient norm
  (median over the update's minibatches), skipped updates, the action std, approx. KL, and the deterministic
  evaluation's mean return where one ran;
* ``curve.png`` — the returns, the gradient norm and the action std against environment steps.

Usage::

    python experiments/paper_network_curve.py results/halfcheetah/runs/paper_1/ppo/HalfCheetah-v5_1 \\
        --out results/halfcheetah/paper_network
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

COLUMNS = {"steps": "time/total_timesteps", "train_return": "rollout/ep_rew_mean", "grad_norm": "train/grad_norm",
           "skipped_updates": "train/skipped_steps", "action_std": "train/std", "approx_kl": "train/approx_kl",
           "eval_return": "eval/mean_reward"}


def read_rows(run: Path) -> list[dict]:
    """The run's ``progress.csv`` rows with the columns of :data:`COLUMNS` (``nan`` where a row lacks one)."""
    with open(run / "progress.csv") as f:
        rows = list(csv.DictReader(f))

    def number(text):
        try:
            return float(text)
        except (TypeError, ValueError):
            return math.nan

    out = [{name: number(row.get(key)) for name, key in COLUMNS.items()} for row in rows]
    return [row for row in out if not math.isnan(row["steps"])]


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["steps"] for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(steps, [r["train_return"] for r in rows], label="training episodes (mean)")
    evaluated = [r for r in rows if not math.isnan(r["eval_return"])]
    axes[0].plot([r["steps"] for r in evaluated], [r["eval_return"] for r in evaluated], "o-",
                 label="deterministic evaluation")
    axes[0].set_ylabel("return")
    axes[0].legend(fontsize=8)
    axes[1].semilogy(steps, [r["grad_norm"] for r in rows])
    axes[1].set_ylabel("gradient norm (before clipping)")
    axes[2].plot(steps, [r["action_std"] for r in rows])
    axes[2].set_ylabel("action std")
    for ax in axes:
        ax.set_xlabel("environment steps")
    fig.suptitle("The paper's network on HalfCheetah-v5 (--conf paper)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders, in training order (a continued run last)")
    parser.add_argument("--out", type=Path, default=Path("results/halfcheetah/paper_network"))
    args = parser.parse_args(argv)
    rows = [row for run in args.runs for row in read_rows(run)]
    # SB3 logs an evaluation as a row of its own, at the same step count as the update around it: merge them.
    merged: dict[float, dict] = {}
    for row in rows:
        into = merged.setdefault(row["steps"], dict(row))
        for key, value in row.items():
            if math.isnan(into[key]) and not math.isnan(value):
                into[key] = value
    rows = [merged[s] for s in sorted(merged)]
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(COLUMNS))
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, args.out / "curve.png")
    print(f"{len(rows)} rows, up to {rows[-1]['steps']:,.0f} steps -> {args.out}/curve.csv, curve.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
