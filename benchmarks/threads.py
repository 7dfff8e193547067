"""Torch threads for the Python API's ``learn()``: one thread against all, on a quiet machine and beside a busy one.

The README's Python snippets build the HalfCheetah entry (``load_hyperparams("HalfCheetah-v5")``: 8 environments,
the CPU-sized spiking network) and call ``learn()``; torch uses every core by default. Each row trains that model
in a process of its own at ``--threads`` torch threads, after one warm-up rollout and update, for ``--steps``
environment steps, and reports env-steps/s. The busy rows run beside ``--busy`` processes that keep one core each
spinning (as another training run would). Rounds are interleaved (quiet 1, quiet all, busy 1, busy all, ...), and
each row reports its median round.

Usage: ``python benchmarks/threads.py`` -> ``benchmarks/results/threads.json``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import subprocess
import sys
import time
from pathlib import Path

from machine import describe_machine, write_result

SPIN = "while True: pass"


def one_row(threads: int, steps: int) -> tuple[int, float]:
    """``(env steps, seconds)`` of the HalfCheetah entry's timed ``learn()`` at ``threads`` torch threads."""
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from sb3_spikeplastic import PPO, load_hyperparams

    torch.set_num_threads(threads)
    h = load_hyperparams("HalfCheetah-v5")
    env = make_vec_env("HalfCheetah-v5", n_envs=h.n_envs, seed=0, env_kwargs=h.env_kwargs)
    env = VecNormalize(env, **h.normalize) if h.normalize is not None else env
    model = PPO(h.policy, env, seed=0, **h.model_kwargs)
    rollout = model.n_steps * model.n_envs
    model.learn(rollout)  # warm-up: compiled kernels loaded, buffers allocated
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    return model.num_timesteps - rollout, time.perf_counter() - start


def run_row(threads: int, steps: int) -> float:
    """One row in a fresh process (torch's thread pool is set once per process)."""
    code = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); from threads import one_row; "
        f"n, t = one_row({threads}, {steps}); print(n / t)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=8192, help="timed environment steps per row")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--busy", type=int, default=1, help="spinning processes beside the busy rows")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "threads.json")
    args = parser.parse_args(argv)
    cores = multiprocessing.cpu_count()
    rows = {(load, threads): [] for load in ("quiet", "busy") for threads in sorted({1, cores})}
    machine = describe_machine(threads=cores)
    for _ in range(args.rounds):
        for (load, threads), rates in rows.items():
            spinners = [
                subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(args.busy if load == "busy" else 0)
            ]
            try:
                rates.append(run_row(threads, args.steps))
            finally:
                for spinner in spinners:
                    spinner.kill()
                    spinner.wait()
            print(f"{load:5s} {threads} thread(s): {rates[-1]:.0f} env-steps/s", flush=True)
    result = dict(
        machine=machine,
        steps=args.steps,
        rounds=args.rounds,
        busy_processes=args.busy,
        rows=[
            dict(
                machine_state=load,
                threads=threads,
                env_steps_per_s=round(statistics.median(r), 1),
                rounds=[round(x, 1) for x in r],
            )
            for (load, threads), r in rows.items()
        ],
    )
    for row in result["rows"]:
        print(f"{row['machine_state']:5s} {row['threads']} thread(s): median {row['env_steps_per_s']} env-steps/s")
    write_result(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
