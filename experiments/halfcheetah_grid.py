"""The locomotion experiment (paper §3.2, Fig. 4 E-H) under one protocol for every model: every rule and the
baselines on HalfCheetah-v5 over several seeds, then each model's return under joint-friction, action and
observation noise.

1. **Training** (``sb3-spikeplastic train`` per (variant, seed), ``--jobs`` processes of one torch thread each):
   the variant's entry, ``-n`` steps, a checkpoint every ``--save-freq`` steps (all kept) and a deterministic
   evaluation every ``--eval-freq`` steps (the training curve). The entry's learning rate is constant, so a run's
   checkpoint at 300k steps is the model a 300k-step run of the same seed ends with: one 1M-step run gives both
   budgets.
2. **Robustness** (``sb3-spikeplastic robustness``, one process per (model, noise)): every model at every budget of
   ``--budgets`` it reached, named ``<variant>@<budget>_s<seed>`` (e.g. ``dp-oja@300k_s0``), on ``--episodes``
   deterministic episodes per noise level (100, as the paper) for sigma in ``--sigmas`` (0 included): all
   environments seeded from ``HELDOUT_SEED``, so every model and every sigma sees the same episode seeds, and the
   sigma = 0 cell is the model's final evaluation (R0). The ``--robustness-envs`` environments of a cell are
   stepped side by side (one batched forward pass); raw per-episode returns land in
   ``<out>/robustness/<model>/robustness_HalfCheetah-v5_<noise>_episodes.csv``.
3. **Aggregation** (``experiments/fig4_table.py``): tables with bootstrap intervals and the verdicts.

Variants: the rules (``static``, ``dp-oja``...), ``<rule>+tanh`` (the bounded-modulation stabiliser; the plain NDP
variants are the paper's unbounded form), and the baselines twice: with the spiking entry's PPO settings (``mlp``,
``ppo_lstm``: ``--conf mlp`` / ``ppo_lstm``) and with rl-baselines3-zoo's tuned HalfCheetah settings
(``mlp_zoo``, ``ppo_lstm_zoo``).

Running a command again resumes it: finished runs and robustness cells are skipped, a run cut short continues
from its latest checkpoint (``train --trained-agent``), and a finished run shorter than ``-n`` continues from its
final model to ``-n`` steps (300k-step runs become 1M-step runs with their checkpoints every ``--save-freq``).

Usage::

    # every rule 300k steps, 3 seeds; static, the best plastic rule and the baselines 1M steps (5 / 5 / 3 seeds)
    python experiments/halfcheetah_grid.py --variants dp-linear dp-bcm ndp-bcm ndp-oja+tanh --seeds 0 1 2 \
        -n 300000 --skip-robustness
    python experiments/halfcheetah_grid.py --variants static dp-oja --seeds 0 1 2 3 4 -n 1000000 --skip-robustness
    python experiments/halfcheetah_grid.py --variants mlp mlp_zoo ppo_lstm ppo_lstm_zoo -n 1000000 --skip-robustness
    python experiments/halfcheetah_grid.py --skip-training        # robustness of every model, then the tables
    python experiments/halfcheetah_grid.py --aggregate-only
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from grid_common import cli, run_one

ENV = "HalfCheetah-v5"
STABILISED = ["policy_kwargs.rule_kwargs.modulation=tanh", "policy_kwargs.rule_kwargs.wm_init_gain=5"]
#: The plain NDP variants are the rules as the paper writes them (their default modulation is the bounded one).
PAPER_FORM = ["policy_kwargs.rule_kwargs.modulation=linear"]
RULES = ("static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm")
BASELINES = ("mlp", "mlp_zoo", "ppo_lstm", "ppo_lstm_zoo")
VARIANTS = (*RULES, "ndp-oja+tanh", "ndp-bcm+tanh", *BASELINES)
NOISES = ("friction", "action", "obs")
#: First environment seed of the robustness evaluations (training's evaluations use the seed's range).
HELDOUT_SEED = 1_000_000


def add_control_arguments(parser: argparse.ArgumentParser) -> None:
    """The protocol's evaluation options of the controls that re-evaluate or add models beside the grid's."""
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--budget", type=int, default=300_000, help="training steps of the models")
    parser.add_argument("--sigmas", nargs="+", type=float, default=[0.0, 0.1, 0.2, 0.3, 0.4])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--n-envs", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path("results/halfcheetah/fig4"))


def run_root(variant: str, seed: int, args: argparse.Namespace) -> Path:
    return args.out / "runs" / f"{variant}_{seed}"


def run_folders(variant: str, seed: int, args: argparse.Namespace) -> list[Path]:
    """The run folders of (variant, seed), oldest first (later ones continue earlier ones)."""
    return sorted(run_root(variant, seed, args).glob(f"ppo/{ENV}_*"), key=lambda p: int(p.name.rsplit("_", 1)[1]))


def train_command(variant: str, seed: int, args: argparse.Namespace) -> list[str]:
    """The run's ``train`` command; a run cut short before (killed, or stopped with the machine) continues from
    its latest checkpoint, and a finished shorter run from its final model (``--trained-agent``, a new run folder
    beside it), instead of starting over."""
    common = ["--seed", str(seed), "-n", str(args.n_timesteps), "-f", str(run_root(variant, seed, args)),
              "--eval-freq", str(args.eval_freq), "--eval-episodes", str(args.eval_episodes), "--save-freq",
              str(args.save_freq), "--keep-checkpoints", "0", "--torch-threads", "1", "--no-progress", "-v", "0"]
    previous = run_folders(variant, seed, args)
    # An interrupted run saved its model on the way out (INTERRUPTED.txt): that model is its latest point.
    if previous and (any(previous[-1].glob("rl_model_*_steps.zip")) or (previous[-1] / f"{ENV}.zip").exists()):
        return [cli(), "train", "--env", ENV, "--trained-agent", str(previous[-1]), *common]
    if variant in BASELINES:
        selection = ["--conf", variant]
    else:
        selection = ["--rule", variant.split("+")[0]]
        form = STABILISED if variant.endswith("+tanh") else PAPER_FORM if variant.startswith("ndp-") else []
        overrides = [*form, *args.hyperparams]
        selection += ["--hyperparams", *overrides] if overrides else []
    return [cli(), "train", "--env", ENV, *selection, *common]


def finished(variant: str, seed: int, args: argparse.Namespace) -> bool:
    """Whether the latest run of (variant, seed) reached its end (an interrupted run also leaves a final model)."""
    folders = run_folders(variant, seed, args)
    return bool(folders) and (folders[-1] / f"{ENV}.zip").exists() and not (folders[-1] / "INTERRUPTED.txt").exists()


def trained_steps(variant: str, seed: int, args: argparse.Namespace) -> int:
    """The length of the finished run of (variant, seed), 0 if there is none: a run shorter than ``-n`` is
    continued from its final model to ``-n`` steps (``train --trained-agent``, step counter kept)."""
    import yaml

    if not finished(variant, seed, args):
        return 0
    meta = yaml.safe_load((run_folders(variant, seed, args)[-1] / ENV / "args.yml").read_text())
    return int(meta["n_timesteps"])


def budget_label(steps: int) -> str:
    return f"{steps // 1_000_000}M" if steps % 1_000_000 == 0 else f"{steps // 1000}k"


def model_at(variant: str, seed: int, budget: int, args: argparse.Namespace) -> Path | None:
    """The model of (variant, seed) after ``budget`` steps: the checkpoint saved there or, for a run of exactly
    that length, its final model (None if the run did not reach it)."""
    folders = run_folders(variant, seed, args)
    for folder in reversed(folders):
        checkpoint = folder / f"rl_model_{budget}_steps.zip"
        if checkpoint.exists():
            return checkpoint
    return folders[-1] if trained_steps(variant, seed, args) == budget else None


def models(args: argparse.Namespace) -> dict[str, Path]:
    """``<variant>@<budget>_s<seed>`` -> model, for every finished run and every budget it reached."""
    found = {}
    for folder in sorted((args.out / "runs").glob("*_*")):
        variant, seed = folder.name.rsplit("_", 1)
        if variant not in VARIANTS or not finished(variant, int(seed), args):
            continue
        for budget in args.budgets:
            model = model_at(variant, int(seed), budget, args)
            if model is not None:
                found[f"{variant}@{budget_label(budget)}_s{seed}"] = model
    return found


def control_models(args: argparse.Namespace) -> Iterator[tuple[str, Path]]:
    """``(<variant>@<budget>_s<seed>, model)`` for the controls' ``--variants`` and ``--seeds`` (options of
    :func:`add_control_arguments`) whose runs reached ``--budget``."""
    for variant in args.variants:
        for seed in args.seeds:
            model = model_at(variant, seed, args.budget, args)
            if model is not None:
                yield f"{variant}@{budget_label(args.budget)}_s{seed}", model


def write_control_table(folder: Path, text: str) -> None:
    """Write and print a control's ``table.md`` (the folder is made even when no model reached the budget)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "table.md").write_text(text)
    print(text)


def robustness_command(name: str, model: Path, noise: str, args: argparse.Namespace) -> list[str]:
    return [cli(), "robustness", "--env", ENV, "--models", f"{name}={model}", "--noise", noise, "--sigmas",
            *map(str, args.sigmas), "--episodes", str(args.episodes), "--n-envs", str(args.robustness_envs),
            "--seed", str(HELDOUT_SEED), "--torch-threads", "1", "-o", str(args.out / "robustness" / name),
            "--no-progress"]


def robustness_done(name: str, noise: str, args: argparse.Namespace) -> bool:
    return (args.out / "robustness" / name / f"robustness_{ENV}_{noise}_episodes.csv").exists()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("-n", "--n-timesteps", type=int, default=300_000)
    parser.add_argument("--eval-freq", type=int, default=50_000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--save-freq", type=int, default=50_000, help="must divide every budget")
    parser.add_argument("--budgets", nargs="+", type=int, default=[300_000, 1_000_000],
                        help="training steps at which every model is evaluated")
    parser.add_argument("--noises", nargs="+", default=list(NOISES), choices=NOISES)
    parser.add_argument("--sigmas", nargs="+", type=float, default=[0.0, 0.1, 0.2, 0.3, 0.4])
    parser.add_argument("--episodes", type=int, default=100, help="episodes per (model, noise, sigma)")
    parser.add_argument("--robustness-envs", type=int, default=100, help="environments stepped side by side")
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="parallel processes")
    parser.add_argument("--hyperparams", nargs="*", default=[], help="overrides passed to every spiking run")
    parser.add_argument("--out", type=Path, default=Path("results/halfcheetah/fig4"))
    parser.add_argument("--skip-training", action="store_true")
    parser.add_argument("--skip-robustness", action="store_true")
    parser.add_argument("--aggregate-only", action="store_true")
    args = parser.parse_args(argv)
    for budget in args.budgets:
        if budget % args.save_freq:
            parser.error(f"--save-freq {args.save_freq} does not divide the budget {budget}: no checkpoint there")
    logs = args.out / "logs"
    failed = []
    if not (args.aggregate_only or args.skip_training):
        jobs = [(v, s) for s in args.seeds for v in args.variants  # seed-major
                if trained_steps(v, s, args) < args.n_timesteps]
        print(f"{len(jobs)} runs to train, {args.jobs} at a time; logs under {logs}")
        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(lambda job: run_one([lambda: train_command(*job, args)],
                                                      logs / f"{job[0]}_{job[1]}.log"), jobs))
        failed += [f"train {v} seed {s}" for (v, s), code in zip(jobs, codes) if code]
    if not (args.aggregate_only or args.skip_robustness):
        cells = [(name, model, noise) for name, model in models(args).items() for noise in args.noises
                 if not robustness_done(name, noise, args)]
        print(f"{len(cells)} robustness evaluations to run, {args.jobs} at a time")
        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(lambda c: run_one([lambda: robustness_command(*c, args)],
                                                    logs / f"robustness_{c[0]}_{c[2]}.log"), cells))
        failed += [f"robustness {name} {noise}" for (name, _, noise), code in zip(cells, codes) if code]
    if failed:
        print(f"failed (see their logs under {logs}): {failed}", file=sys.stderr)
    table = [sys.executable, str(Path(__file__).with_name("fig4_table.py")), "--out", str(args.out)]
    return subprocess.call(table) or int(bool(failed))


if __name__ == "__main__":
    raise SystemExit(main())
