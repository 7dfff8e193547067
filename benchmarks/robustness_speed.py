"""Evaluation speed of ``robustness`` on HalfCheetah-v5: deterministic env-steps/s of one process (one torch
thread) against the number of environments stepped side by side, and what the Fig. 4 protocol costs per model.

One (model, noise, sigma) cell of the protocol is 100 episodes of 1000 steps; a model's table is 3 noise types x 5
sigmas (sigma = 0 once per noise type): 1.5M inference steps. Each row evaluates one model with
:func:`sb3_spikeplastic.study.robustness.evaluate_robustness` (action noise, sigma 0.2, ``n_envs`` environments, one
episode each, cut to ``--steps`` steps) in a process of its own and reports env-steps/s, and from it the minutes
per model of the whole protocol on one core. Models: ``entry`` (the CPU entry, ``ppo.yml``), ``mlp``
(``--conf mlp``'s MlpPolicy) and ``ppo_lstm`` (RecurrentPPO, ``--conf ppo_lstm``), untrained: the cost of a step
does not depend on the weights. Rows started while other processes used more than 30 % of the CPU are marked
BUSY.

Usage::

    python benchmarks/robustness_speed.py                 # writes benchmarks/results/robustness_speed.json
    python benchmarks/robustness_speed.py --models entry --n-envs 1 100
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from learn_throughput import BUSY_LOAD_PER_CORE, busy_fraction, load_per_core
from machine import describe_machine, write_result

ENV_ID = "HalfCheetah-v5"
PROTOCOL_STEPS = 3 * 5 * 100 * 1000  # noise types x sigmas x episodes x steps
CONF = {"entry": "ppo", "mlp": "mlp", "ppo_lstm": "ppo_lstm"}


def run_row(key: str, n_envs: int, steps: int) -> dict:
    """One row in this process: build the model, warm up, time one evaluation of ``n_envs`` episodes."""
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from sb3_spikeplastic.study.robustness import evaluate_robustness
    from sb3_spikeplastic.zoo.config import load_hyperparams
    from sb3_spikeplastic.zoo.validation import algorithm_class

    torch.set_num_threads(1)
    h = load_hyperparams(ENV_ID, CONF[key])
    env = make_vec_env(ENV_ID, n_envs=1, seed=0)
    if h.normalize is not None:
        env = VecNormalize(env, **h.normalize)
    model = algorithm_class(h.algo)(h.policy, env, seed=0, device="cpu", **h.model_kwargs)

    def evaluate(n_steps: int) -> None:
        evaluate_robustness(
            {key: model},
            ENV_ID,
            "action",
            [0.2],
            n_episodes=n_envs,
            n_envs=n_envs,
            progress_bar=False,
            env_kwargs={"max_episode_steps": n_steps},
        )

    evaluate(5)  # allocations, lazy compilation
    start = time.perf_counter()
    evaluate(steps)
    seconds = time.perf_counter() - start
    # evaluate_robustness always adds sigma = 0: two cells of n_envs episodes of `steps` steps
    rate = 2 * n_envs * steps / seconds
    return dict(
        model=key, n_envs=n_envs, env_steps_per_s=round(rate), protocol_minutes=round(PROTOCOL_STEPS / rate / 60, 1)
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(CONF), choices=list(CONF))
    parser.add_argument("--n-envs", nargs="+", type=int, default=[1, 10, 100])
    parser.add_argument("--steps", type=int, default=200, help="steps per episode (cut short)")
    parser.add_argument("--row", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "robustness_speed.json")
    args = parser.parse_args(argv)
    if args.row:
        print(json.dumps(run_row(args.row, args.n_envs[0], args.steps)))
        return 0
    rows = []
    print(f"{'model':>9} {'n_envs':>6} {'env-steps/s':>11} {'min/model':>9}  machine")
    for key in args.models:
        for n_envs in args.n_envs:
            load, others = load_per_core(), busy_fraction()
            command = [sys.executable, __file__, "--row", key, "--n-envs", str(n_envs), "--steps", str(args.steps)]
            result = subprocess.run(command, capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"{key} with {n_envs} environments failed:\n{result.stderr[-3000:]}")
            row = dict(
                json.loads(result.stdout.strip().splitlines()[-1]),
                load_per_core=round(load, 2),
                others_busy=round(others, 2),
                busy=others > BUSY_LOAD_PER_CORE,
            )
            rows.append(row)
            print(
                f"{key:>9} {n_envs:>6} {row['env_steps_per_s']:>11} {row['protocol_minutes']:>9}  "
                f"{'BUSY ' if row['busy'] else ''}others {others:.2f}, load/core {load:.2f}",
                flush=True,
            )
    command = " ".join(["python", "benchmarks/robustness_speed.py", *(argv if argv is not None else sys.argv[1:])])
    write_result(dict(command=command, machine=describe_machine(1), steps=args.steps, rows=rows), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
