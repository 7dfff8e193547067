"""Control for the observation-noise result of the HalfCheetah protocol: does a baseline trained with observation
noise keep its return as the spiking networks do?

The spiking networks, trained without noise, keep most of their return under observation noise where every
baseline loses most of its own. A reader will ask whether training the baseline with that noise (domain
randomisation) closes the gap. This script trains the MlpPolicy baselines (``mlp``: the spiking entry's PPO
settings; ``mlp_zoo``: rl-baselines3-zoo's) on ``NoisyHalfCheetah-v5`` with observation noise ``--train-sigmas``
on every element (``train --env NoisyHalfCheetah-v5 --conf <variant> --hyperparams env_kwargs.obs_noise=<sigma>``,
``--budget`` steps, one process per run) and evaluates each with the protocol of ``experiments/halfcheetah_grid.py``
on the noise-free ``HalfCheetah-v5`` under observation noise (100 episodes per point, the same episode seeds).

Writes ``<out>/noise_trained/robustness/<variant>+obs<sigma>@<budget>_s<seed>/`` (per-episode returns, the grid's
format), the models under ``<out>/noise_trained/runs/`` (not kept), the logs under ``<out>/noise_trained/logs/``
and ``<out>/noise_trained/table.md``: R0, the area under the ratio curve and the return at the largest sigma of
each noise-trained group, of the same baseline trained without noise and of the static SNN (from the grid), and
each group's difference from the static SNN (two-stage bootstrap intervals over seeds and episodes).

Usage: ``python experiments/noise_trained_control.py`` (after the grid's observation-noise evaluations of ``mlp``,
``mlp_zoo`` and ``static`` at 300k steps; ~1 hour of one core, most of it ``mlp_zoo``'s training); more seeds of
one training sigma with ``--train-sigmas 0.4 --seeds 3 4 5 6 7 8`` (the table reads every model evaluated so far).
"""

from __future__ import annotations

import argparse
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from fig4_table import LEARNED_THRESHOLD, group_of, r0, read_episodes, summary_cells
from grid_common import cli, run_one
from halfcheetah_grid import ENV, add_control_arguments, budget_label, robustness_command, write_control_table

TRAIN_ENV = "NoisyHalfCheetah-v5"
NOISE = "obs"


def name_of(variant: str, train_sigma: float, seed: int, budget: int) -> str:
    return f"{variant}+obs{train_sigma:g}@{budget_label(budget)}_s{seed}"


def run_dir(name: str, args: argparse.Namespace) -> Path:
    return args.out / "noise_trained" / "runs" / name / "ppo" / f"{TRAIN_ENV}_1"


def train_command(variant: str, train_sigma: float, seed: int, args: argparse.Namespace) -> list[str]:
    name = name_of(variant, train_sigma, seed, args.budget)
    return [cli(), "train", "--env", TRAIN_ENV, "--conf", variant, "--hyperparams",
            f"env_kwargs.obs_noise={train_sigma}", "--seed", str(seed), "-n", str(args.budget), "-f",
            str(args.out / "noise_trained" / "runs" / name), "--eval-freq", "0", "--torch-threads", "1",
            "--no-progress", "-v", "0"]


def job(variant: str, train_sigma: float, seed: int, args: argparse.Namespace) -> int:
    """Train (unless its final model exists) and evaluate one model, the evaluation's log beside the training's."""
    name = name_of(variant, train_sigma, seed, args.budget)
    control = argparse.Namespace(**{**vars(args), "out": args.out / "noise_trained"})
    commands = []
    if not (run_dir(name, args) / f"{TRAIN_ENV}.zip").exists():
        # A run cut short starts over (minutes long): its folder goes, so that the new run is ``run_dir`` again.
        shutil.rmtree(args.out / "noise_trained" / "runs" / name, ignore_errors=True)
        commands.append(lambda: train_command(variant, train_sigma, seed, args))
    if not (control.out / "robustness" / name / f"robustness_{ENV}_{NOISE}_episodes.csv").exists():
        commands.append(lambda: robustness_command(name, run_dir(name, args), NOISE, control))
    return run_one(commands, control.out / "logs" / f"{name}.log")


def table(args: argparse.Namespace) -> str:
    budget = budget_label(args.budget)
    trained = read_episodes(args.out / "noise_trained")
    grid = read_episodes(args.out)

    failed = []

    def seeds(data: dict, group: str) -> tuple[np.ndarray, list[np.ndarray]]:
        """The group's sigmas and the per-seed returns (one row per sigma) of its models that learned."""
        names = [m for m in sorted(data) if group_of(m) == group and NOISE in data[m]]
        failed.extend(f"{m} ({r0(data[m][NOISE][1]):.0f})" for m in names if r0(data[m][NOISE][1]) < LEARNED_THRESHOLD)
        learned = [data[m][NOISE][1] for m in names if r0(data[m][NOISE][1]) >= LEARNED_THRESHOLD]
        return (data[names[0]][NOISE][0] if names else np.array([])), learned

    static = seeds(grid, f"static@{budget}")
    rows = [(f"static@{budget}", static), *((f"{v}@{budget}", seeds(grid, f"{v}@{budget}")) for v in args.variants)]
    rows += [(g, seeds(trained, g)) for g in dict.fromkeys(group_of(m) for m in sorted(trained))]
    lines = [f"# {ENV}: the MlpPolicy baselines trained with observation noise, under observation noise "
             f"({budget} steps)", "",
             "`<variant>+obs<σ>`: trained on NoisyHalfCheetah-v5 with observation noise σ on every element; the "
             f"others from the protocol (trained without noise). {args.episodes} episodes per point, the protocol's "
             "episode seeds; 95 % two-stage bootstrap intervals over seeds and episodes. AUC: area under the "
             f"ratio-to-R0 curve (1 = no loss). Models with R0 < {LEARNED_THRESHOLD:g} did not learn to run: listed "
             "apart, left out of the rows.", "",
             "| model | seeds | R0 | AUC | return at σ max | AUC − static SNN | return at σ max − static SNN |",
             "|---|---|---|---|---|---|---|"]
    for group, (sigmas, data) in rows:
        if not data:
            continue
        comparable = group != rows[0][0] and np.array_equal(sigmas, static[0])
        cells = summary_cells(data, sigmas, static[1] if comparable else None)
        lines.append(f"| {group} | {len(data)} | " + " | ".join(cells) + " |")
    if failed:
        lines += ["", f"Did not learn (R0 < {LEARNED_THRESHOLD:g}): " + ", ".join(failed) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=["mlp", "mlp_zoo"], choices=["mlp", "mlp_zoo"])
    parser.add_argument("--train-sigmas", nargs="+", type=float, default=[0.1, 0.4],
                        help="observation noise during training")
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes")
    parser.add_argument("--robustness-envs", type=int, default=100, help="environments stepped side by side")
    add_control_arguments(parser)
    args = parser.parse_args(argv)
    jobs = [(v, s, seed) for v in args.variants for s in args.train_sigmas for seed in args.seeds]
    with ThreadPoolExecutor(args.jobs) as pool:
        codes = list(pool.map(lambda j: job(*j, args), jobs))
    write_control_table(args.out / "noise_trained", table(args))
    failed = [name_of(*j, args.budget) for j, code in zip(jobs, codes) if code]
    if failed:
        print(f"failed (see {args.out / 'noise_trained' / 'logs'}): {failed}")
    return int(bool(failed))


if __name__ == "__main__":
    raise SystemExit(main())
