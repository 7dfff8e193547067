"""Training throughput of ``learn`` on HalfCheetah-v5: SpikePlasticPolicy vs SB3 MlpPolicy vs sb3-contrib RecurrentPPO.

All algorithms run in this one process, one after another, with the same PPO settings (8 envs, ``n_steps``
256, 10 epochs, batch 2048 transitions = 64 chunks of 32), so their env-steps/s are comparable. Also reports
the per-environment network state and chunk-snapshot memory of the paper-size plastic network, and the
process's peak RSS after each run.

Usage (documented in benchmarks/README.md)::

    pip install -e ".[bench]"
    python benchmarks/learn_throughput.py                      # prints a table, writes benchmarks/results/learn_throughput.json
    python benchmarks/learn_throughput.py --check              # compare the spiking/RecurrentPPO ratio with the committed result
    python benchmarks/learn_throughput.py --device cuda        # all of them on the GPU (+ ndp-oja without CUDA graphs);
                                                               # writes benchmarks/results/learn_throughput_cuda.json
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import torch
from machine import describe_machine, write_result  # benchmarks/machine.py (the script's folder is on sys.path)
from sb3_spikeplastic._fast.allocator import keep_freed_memory
from stable_baselines3.common.env_util import make_vec_env

import sb3_spikeplastic  # noqa: F401  (registers the environments)
from sb3_spikeplastic import PPO

RESULTS = Path(__file__).parent / "results" / "learn_throughput.json"
RESULTS_CUDA = RESULTS.with_name("learn_throughput_cuda.json")  # --device cuda
PAPER_NET = dict(hidden_sizes=[64, 64], steps=50, encoder_pop_size=50, action_pop_size=100)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(name: str, make_model, timesteps: int, warmup: int) -> dict:
    model = make_model()
    model.learn(warmup)  # first rollout + update: allocations, lazy compilation
    start = time.perf_counter()
    model.learn(timesteps, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    row = dict(name=name, timesteps=timesteps, seconds=seconds, env_steps_per_s=timesteps / seconds,
               peak_rss_mb=peak_rss_mb())
    if getattr(model, "network_state", None) is not None:
        n_envs = model.n_envs
        row["state_bytes_per_env"] = model.network_state.nbytes() / n_envs
        row["snapshot_bytes_per_rollout"] = model.rollout_buffer.snapshot_nbytes()
    print(f"{name:36s} {row['env_steps_per_s']:8.1f} env-steps/s  ({seconds:.1f} s)  peak RSS {row['peak_rss_mb']:.0f} MB",
          flush=True)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rollouts", type=int, default=2, help="timed rollouts+updates per algorithm")
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--n-steps", type=int, default=256)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--only", nargs="*", help="subset of: mlp recurrent static ndp-oja ndp-oja-eager (CUDA only)")
    parser.add_argument("--output", type=Path, help=f"default: {RESULTS} ({RESULTS_CUDA.name} with --device cuda)")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if the spiking/RecurrentPPO ratio falls > 30%% below the committed baseline")
    args = parser.parse_args(argv)
    if args.output is None:
        args.output = RESULTS_CUDA if args.device.startswith("cuda") else RESULTS
    torch.set_num_threads(args.threads)
    keep_freed_memory()  # as `sb3-spikeplastic train` does
    per_rollout = args.n_envs * args.n_steps
    common = dict(n_steps=args.n_steps, batch_size=2048, n_epochs=10, learning_rate=5e-4, gamma=0.99,
                  gae_lambda=0.97, max_grad_norm=1.0, seed=0, device=args.device)

    def env():
        return make_vec_env("HalfCheetah-v5", n_envs=args.n_envs, seed=0)

    candidates = {
        "mlp": lambda: PPO("MlpPolicy", env(), **common),
        "static": lambda: PPO("SpikePlasticPolicy", env(), bptt_steps=32, policy_kwargs=dict(rule="static", **PAPER_NET), **common),
        "ndp-oja": lambda: PPO("SpikePlasticPolicy", env(), bptt_steps=32, policy_kwargs=dict(rule="ndp-oja", **PAPER_NET), **common),
    }
    if args.device.startswith("cuda"):  # what the CUDA graphs (sb3_spikeplastic.cuda_graphs) buy
        candidates["ndp-oja-eager"] = lambda: PPO("SpikePlasticPolicy", env(), bptt_steps=32, cuda_graphs=False,
                                                  policy_kwargs=dict(rule="ndp-oja", **PAPER_NET), **common)
    try:
        from sb3_contrib import RecurrentPPO

        candidates["recurrent"] = lambda: RecurrentPPO("MlpLstmPolicy", env(), **common)
    except ImportError:
        print("sb3-contrib not installed (pip install -e '.[bench]'): RecurrentPPO skipped", file=sys.stderr)
    labels = {"mlp": "SB3 PPO MlpPolicy", "recurrent": "sb3-contrib RecurrentPPO", "static": "SpikePlastic static",
              "ndp-oja": "SpikePlastic ndp-oja", "ndp-oja-eager": "SpikePlastic ndp-oja, no CUDA graphs"}
    rows = [run(labels[k], candidates[k], args.rollouts * per_rollout, per_rollout)
            for k in labels if k in candidates and (not args.only or k in args.only)]
    by_name = {r["name"]: r for r in rows}
    ratio = None
    if labels["recurrent"] in by_name and labels["ndp-oja"] in by_name:
        ratio = by_name[labels["ndp-oja"]]["env_steps_per_s"] / by_name[labels["recurrent"]]["env_steps_per_s"]
        print(f"ndp-oja / RecurrentPPO throughput ratio: {ratio:.2f}")
    result = dict(machine=describe_machine(args.threads), settings=dict(vars(args), output=str(args.output)), rows=rows,
                  ratio_ndp_oja_vs_recurrent=ratio)
    if args.check:
        baseline_file = RESULTS_CUDA if args.device.startswith("cuda") else RESULTS
        baseline = json.loads(baseline_file.read_text())["ratio_ndp_oja_vs_recurrent"]
        if ratio is None or ratio < 0.7 * baseline:
            print(f"REGRESSION: ratio {ratio} vs committed baseline {baseline:.2f} (allowed down to {0.7 * baseline:.2f})")
            return 1
        print(f"ok: ratio {ratio:.2f} vs committed baseline {baseline:.2f}")
        return 0
    write_result(result, args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
