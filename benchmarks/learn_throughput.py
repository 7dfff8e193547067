"""Training throughput of ``learn`` on HalfCheetah-v5: SpikePlasticPolicy vs SB3 MlpPolicy vs sb3-contrib RecurrentPPO.

Two groups of rows, each algorithm at one and at every other requested torch thread count:

* the paper network (``paper.yml``: 12 x 50 inputs, 64-64 hidden, 6 x 100 outputs, T = 50; ``static`` and
  ``ndp-oja``) against ``mlp`` and ``recurrent``, all with the same PPO settings (8 envs, ``n_steps`` 256, 10
  epochs, batch 2048 transitions = 64 chunks of 32), ``chunks_per_pass`` at its default (``"auto"``: each
  minibatch in one pass); ``ndp-oja-two-passes`` runs ndp-oja's minibatches in two passes of 32 chunks
  (``chunks_per_pass=32``: less memory, slower);
* the shipped CPU entry (``entry``: ``ppo.yml``'s HalfCheetah-v5, 17 x 10 inputs, T = 10, its own settings)
  against ``entry-recurrent`` (``ppo_lstm.yml``: RecurrentPPO with the same PPO settings as the entry);
* ``tmaze``: the T-maze entry (``ppo.yml``'s TMazeCue-v0), the small network that ``train --torch-threads auto``
  keeps on one thread;
* ``bare`` and ``bare-mlp``: ``PPO("SpikePlasticPolicy", "HalfCheetah-v5")`` and ``PPO("MlpPolicy",
  "HalfCheetah-v5")`` with every default (one environment);
* ``paper-conf``: the model of ``train --env HalfCheetah-v5 --conf paper`` (``paper.yml``: ndp-oja with the tanh
  modulation, 6 environments x 500 steps, batch 1000, BPTT 10, VecNormalize), against ``recurrent``.

``--n-envs N`` sets the number of environments of the paper rows (keeping 2048 transitions per update) and of
``paper-conf`` (keeping ~3000): the sweep of a GPU's throughput against the batch of environments.
``--concurrent K`` runs K copies of each row at once and reports their summed env-steps/s (several trainings
sharing one GPU).

Every row runs in a process of its own (its thread count set first; its peak RSS its own) and times, after one
warm-up rollout + update, the rollouts + updates that cover one whole episode of every environment (HalfCheetah:
4 rollouts of 256 steps for its 1000-step episodes; ``--rollouts`` sets another number). Whole episodes, because
an update's cost can depend on whether its rollout holds an episode start: sb3-contrib's RecurrentPPO runs its
LSTM one step at a time through every sequence of such an update (``_process_sequence``), ~20 times slower than
in one call, and on HalfCheetah that is one update in 3.9 (the warm-up is always one of them). Timing whole
episodes measures each algorithm at its long-run average. It reports env-steps/s, peak RSS, the machine's state
when the row started (the CPU fraction other processes
used over 2 s: rows started above 0.3 are marked BUSY, and a warning says their ratios are not to be quoted; and
the 1-minute load average per core, which still counts the previous rows' own work) and a roofline line:
the dense multiply-adds of its networks per training env step (rollout forward + ``n_epochs`` x forward and
backward, counting a backward pass as two forwards; for the spiking network ``T`` products per layer), as
GFLOP/s achieved, against the machine's dense float32 matrix-product rate at the same thread count.

Usage (documented in benchmarks/README.md)::

    pip install -e ".[bench]"
    python benchmarks/learn_throughput.py          # prints a table, writes benchmarks/results/learn_throughput.json
    python benchmarks/learn_throughput.py --only entry entry-recurrent --threads 1 2
    python benchmarks/learn_throughput.py --check  # the spiking/RecurrentPPO ratios against the committed result
    python benchmarks/learn_throughput.py --device cuda        # on the GPU (+ ndp-oja without CUDA graphs);
                                                               # writes benchmarks/results/learn_throughput_cuda.json
    python benchmarks/learn_throughput.py --device cuda --only paper-conf recurrent --n-envs 32 \
        --output benchmarks/results/learn_throughput_cuda_32envs.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

RESULTS = Path(__file__).parent / "results" / "learn_throughput.json"
RESULTS_CUDA = RESULTS.with_name("learn_throughput_cuda.json")  # --device cuda
ENV_ID = "HalfCheetah-v5"
COMMON = dict(
    n_steps=256,
    batch_size=2048,
    n_epochs=10,
    learning_rate=5e-4,
    gamma=0.99,
    gae_lambda=0.97,
    max_grad_norm=1.0,
    seed=0,
)
LABELS = {
    "mlp": "SB3 PPO MlpPolicy",
    "recurrent": "sb3-contrib RecurrentPPO",
    "static": "SpikePlastic static, paper network",
    "ndp-oja": "SpikePlastic ndp-oja, paper network",
    "ndp-oja-eager": "SpikePlastic ndp-oja, paper network, no CUDA graphs",
    "ndp-oja-two-passes": "SpikePlastic ndp-oja, paper network, two passes",
    "entry": "SpikePlastic CPU entry (ppo.yml, dp-oja)",
    "entry-recurrent": "RecurrentPPO, the entry's settings (ppo_lstm.yml)",
    "tmaze": "SpikePlastic T-maze entry (ppo.yml, TMazeCue-v0)",
    "bare": 'PPO("SpikePlasticPolicy", "HalfCheetah-v5"), every default',
    "bare-mlp": 'PPO("MlpPolicy", "HalfCheetah-v5"), every default',
    "paper-conf": "SpikePlastic train --conf paper (ndp-oja, tanh)",
}
#: (spiking row, baseline row) pairs whose throughput ratio is reported and checked
RATIOS = {
    "ndp-oja / recurrent": ("ndp-oja", "recurrent"),
    "entry / entry-recurrent": ("entry", "entry-recurrent"),
    "paper-conf / recurrent": ("paper-conf", "recurrent"),
}
#: Rows whose number of environments ``--n-envs`` sets, keeping the transitions per update: the paper rows' 2048
#: (``n_steps = 2048 / n_envs``, a multiple of their BPTT length 32) and ``paper.yml``'s 3000 (``n_steps`` the
#: multiple of its BPTT length nearest to ``3000 / n_envs``).
SCALABLE = ("mlp", "recurrent", "static", "ndp-oja", "ndp-oja-eager", "ndp-oja-two-passes", "paper-conf")


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def dense_macs_per_step(model) -> float:
    """Multiply-adds of one forward pass per environment step: every weight matrix once, a spiking layer's
    ``T`` times (its product runs on every network step)."""
    from sb3_spikeplastic.sb3.policy import SpikePlasticPolicy

    policy = model.policy
    snn_weights = set()
    macs = 0.0
    if isinstance(policy, SpikePlasticPolicy):
        for layer in policy.snn.layers:
            macs += policy.snn.steps * layer.weight.numel()
            snn_weights.update(id(p) for p in layer.parameters())
    for p in policy.parameters():
        if p.dim() >= 2 and id(p) not in snn_weights:
            macs += p.numel()
    return macs


def matmul_gflops(device: str) -> float:
    """The machine's dense float32 matrix-product rate at the current thread count (n = 1024)."""
    import torch

    a = torch.randn(1024, 1024, device=device)
    b = torch.randn(1024, 1024, device=device)
    for _ in range(3):
        a @ b
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start, repeats = time.perf_counter(), 20
    for _ in range(repeats):
        a @ b
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return 2 * 1024**3 * repeats / (time.perf_counter() - start) / 1e9


def make_model(key: str, device: str, n_envs: Optional[int] = None):
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from sb3_spikeplastic import PPO
    from sb3_spikeplastic.zoo.config import load_hyperparams

    if key == "paper-conf":  # the command's model: its own PPO settings, VecNormalize, linear learning-rate decay
        h = load_hyperparams(ENV_ID, "paper")
        kwargs = dict(h.model_kwargs)
        if n_envs:
            bptt = kwargs["bptt_steps"]
            kwargs["n_steps"] = max(bptt, round(3000 / n_envs / bptt) * bptt)
        env = VecNormalize(make_vec_env(ENV_ID, n_envs=n_envs or h.n_envs, seed=0), **h.normalize)
        return PPO(h.policy, env, seed=0, device=device, **kwargs)

    if key in ("entry", "entry-recurrent", "tmaze"):
        env_id = "TMazeCue-v0" if key == "tmaze" else ENV_ID
        h = load_hyperparams(env_id, "ppo_lstm" if key == "entry-recurrent" else "ppo")
        env = make_vec_env(env_id, n_envs=h.n_envs, seed=0, env_kwargs=h.env_kwargs)
        if h.normalize is not None:
            env = VecNormalize(env, **h.normalize)
        if key != "entry-recurrent":
            return PPO(h.policy, env, seed=0, device=device, **h.model_kwargs)
        from sb3_contrib import RecurrentPPO

        return RecurrentPPO(h.policy, env, seed=0, device=device, **h.model_kwargs)
    if key in ("bare", "bare-mlp"):  # the one-line models, as a new user builds them
        return PPO("SpikePlasticPolicy" if key == "bare" else "MlpPolicy", ENV_ID, seed=0, device=device)
    env = make_vec_env(ENV_ID, n_envs=n_envs or 8, seed=0)
    common = dict(COMMON, device=device, n_steps=2048 // (n_envs or 8))
    if key == "mlp":
        return PPO("MlpPolicy", env, **common)
    if key == "recurrent":
        from sb3_contrib import RecurrentPPO

        return RecurrentPPO("MlpLstmPolicy", env, **common)
    paper = load_hyperparams(ENV_ID, "paper").model_kwargs["policy_kwargs"]
    for name in ("critic", "log_std_init"):  # the same value and critic heads as the baselines
        paper.pop(name, None)
    rule = "static" if key == "static" else "ndp-oja"
    return PPO(
        "SpikePlasticPolicy",
        env,
        bptt_steps=32,
        cuda_graphs=key != "ndp-oja-eager",
        chunks_per_pass=32 if key == "ndp-oja-two-passes" else "auto",
        policy_kwargs=dict(paper, rule=rule),
        **common,
    )


def episode_rollouts(model) -> int:
    """Rollouts that cover one whole episode of every environment (at least 2): ``ceil(max_episode_steps /
    n_steps)``, or 2 for environments without a step limit."""
    limit = model.get_env().get_attr("spec")[0].max_episode_steps
    return 2 if not limit else max(2, math.ceil(limit / model.n_steps))


def run_row(key: str, threads: int, device: str, rollouts: Optional[int], n_envs: Optional[int] = None) -> dict:
    """One row, in this process: build (with ``n_envs`` environments for :data:`SCALABLE` rows), warm up (first
    rollout + update: allocations, lazy compilation), time ``rollouts`` rollouts + updates (default:
    :func:`episode_rollouts`)."""
    import torch

    torch.set_num_threads(threads)
    from sb3_spikeplastic.snn.cpu_settings import keep_freed_memory

    keep_freed_memory()  # as `sb3-spikeplastic train` does
    model = make_model(key, device, n_envs if key in SCALABLE else None)
    rollouts = rollouts or episode_rollouts(model)
    per_rollout = model.n_steps * model.n_envs
    model.learn(per_rollout)
    start = time.perf_counter()
    model.learn(rollouts * per_rollout, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    steps_per_s = rollouts * per_rollout / seconds
    flops = 2 * dense_macs_per_step(model) * (1 + 3 * model.n_epochs)
    row = dict(
        key=key,
        name=LABELS[key],
        threads=threads,
        n_envs=model.n_envs,
        n_steps=model.n_steps,
        timesteps=rollouts * per_rollout,
        seconds=seconds,
        env_steps_per_s=steps_per_s,
        peak_rss_mb=peak_rss_mb(),
        train_flops_per_step=flops,
        achieved_gflops=flops * steps_per_s / 1e9,
        matmul_gflops=matmul_gflops(device),
    )
    if getattr(model, "network_state", None) is not None:
        row["chunks_per_pass"] = model._pass_size() or model.batch_size // model.bptt_steps
        row["state_bytes_per_env"] = model.network_state.nbytes() / model.n_envs
        row["snapshot_bytes_per_rollout"] = model.rollout_buffer.snapshot_nbytes()
    return row


#: a row started while other processes kept more than this fraction of the cores busy is marked busy: they slow
#: the latency-bound baselines (RecurrentPPO's one-step LSTM) more than the spiking network, which skews the ratios
BUSY_LOAD_PER_CORE = 0.3


def load_per_core() -> float:
    return os.getloadavg()[0] / (os.cpu_count() or 1)


def busy_fraction(seconds: float = 2.0) -> float:
    """The fraction of the machine's CPU time spent by other processes over ``seconds`` just before a row, from
    ``/proc/stat`` (no row runs meanwhile). The 1-minute load average is recorded too, but it still counts the
    previous rows' own work for a minute after they end; NaN where ``/proc/stat`` is missing."""

    def times():
        with open("/proc/stat") as f:
            values = [int(x) for x in f.readline().split()[1:]]
        idle = values[3] + (values[4] if len(values) > 4 else 0)
        return sum(values) - idle, sum(values)

    try:
        busy0, total0 = times()
        time.sleep(seconds)
        busy1, total1 = times()
    except OSError:
        return float("nan")
    return (busy1 - busy0) / max(total1 - total0, 1)


def run_in_subprocess(key: str, threads: int, args) -> dict:
    """One row in a process of its own, with the machine's state when it started: the 1-minute load average per
    core, the CPU fraction other processes used (``others_busy``) and ``busy`` when that is above the limit.

    With ``--concurrent K`` the row's process runs K times at once (trainings sharing a GPU, as the grids run
    them): ``env_steps_per_s`` is their sum, each one's in ``env_steps_per_s_each`` (their timed windows overlap
    but are not identical, so the sum is approximate)."""
    command = [sys.executable, __file__, "--row", key, "--threads", str(threads), "--device", args.device]
    if args.rollouts:
        command += ["--rollouts", str(args.rollouts)]
    if args.n_envs:
        command += ["--n-envs", str(args.n_envs)]
    load, others = load_per_core(), busy_fraction()
    processes = [
        subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(args.concurrent)
    ]
    found = []
    for process in processes:
        stdout, stderr = process.communicate()
        if process.returncode != 0:
            raise RuntimeError(f"{key} with {threads} threads failed:\n{stderr[-3000:]}")
        found.append(json.loads(stdout.strip().splitlines()[-1]))
    row = found[0]
    if args.concurrent > 1:
        each = [r["env_steps_per_s"] for r in found]
        row = dict(
            row,
            name=f"{row['name']} x{args.concurrent}",
            env_steps_per_s=sum(each),
            env_steps_per_s_each=each,
            concurrent=args.concurrent,
            achieved_gflops=sum(r["achieved_gflops"] for r in found),
        )
    return dict(row, load_per_core=round(load, 2), others_busy=round(others, 2), busy=others > BUSY_LOAD_PER_CORE)


def ratios(rows: list[dict]) -> dict:
    """Per pair of :data:`RATIOS`, the spiking row's env-steps/s over the baseline's, each at its best thread
    count."""
    best = {}
    for row in rows:
        if row["key"] not in best or row["env_steps_per_s"] > best[row["key"]]["env_steps_per_s"]:
            best[row["key"]] = row
    return {
        name: best[a]["env_steps_per_s"] / best[b]["env_steps_per_s"]
        for name, (a, b) in RATIOS.items()
        if a in best and b in best
    }


def print_row(row: dict) -> None:
    busy = "  BUSY" if row.get("busy") else ""
    print(
        f"{row['name']:52s} {row['threads']:7d} {row['env_steps_per_s']:11.1f} {row['peak_rss_mb']:7.0f} MiB"
        f"{row['achieved_gflops']:8.1f} {row['achieved_gflops'] / row['matmul_gflops']:8.1%} "
        f"{row.get('others_busy', float('nan')):11.2f}{busy}",
        flush=True,
    )


def runs_flat(runs: dict) -> list[dict]:
    return [row for found in runs.values() for row in found]


def median_run(runs: list[dict]) -> dict:
    """The run with the median env-steps/s (the lower middle one of an even count), with every run's env-steps/s
    in ``env_steps_per_s_runs``. Rows drift by ~15 % within minutes on a shared machine, and not all alike: medians
    of interleaved rounds compare rows more reliably than one round."""
    ordered = sorted(runs, key=lambda row: row["env_steps_per_s"])
    return dict(ordered[(len(ordered) - 1) // 2], env_steps_per_s_runs=[row["env_steps_per_s"] for row in runs])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--rollouts", type=int, help="timed rollouts+updates per row (default: one whole episode of every environment)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        nargs="+",
        help="torch thread counts to run every row at (default: 1 and the number of CPUs)",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--n-envs",
        type=int,
        help="environments of the paper rows and paper-conf (the same "
        "transitions per update; default: 8, paper.yml's 6)",
    )
    parser.add_argument("--only", nargs="*", choices=list(LABELS), help="a subset of the rows")
    parser.add_argument("--output", type=Path, help=f"default: {RESULTS} ({RESULTS_CUDA.name} with --device cuda)")
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit 1 if a spiking/RecurrentPPO ratio falls > 30%% below the committed result",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="rounds over all rows, interleaved; each row reports its median round (default 1)",
    )
    parser.add_argument(
        "--concurrent",
        type=int,
        default=1,
        help="run each row's process this many times at once and report the sum (default 1)",
    )
    parser.add_argument("--row", help=argparse.SUPPRESS)  # internal: run one row in this process, print JSON
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be a positive number of rounds")
    if args.concurrent < 1:
        parser.error(f"--concurrent {args.concurrent}: must be a positive number of processes")
    cuda = args.device.startswith("cuda")
    if args.row:
        print(json.dumps(run_row(args.row, args.threads[0], args.device, args.rollouts, args.n_envs)))
        return 0
    from machine import describe_machine, write_result  # benchmarks/machine.py (the script's folder is on sys.path)

    if args.output is None:
        args.output = RESULTS_CUDA if cuda else RESULTS
    threads = args.threads or sorted({1, os.cpu_count() or 1})
    keys = [k for k in LABELS if (not args.only or k in args.only) and (cuda or k != "ndp-oja-eager")]
    try:
        import sb3_contrib  # noqa: F401
    except ImportError:
        print("sb3-contrib not installed (pip install -e '.[bench]'): RecurrentPPO rows skipped", file=sys.stderr)
        keys = [k for k in keys if "recurrent" not in k]
    print(
        f"{'row':52s} {'threads':>7s} {'env-steps/s':>11s} {'peak RSS':>9s} {'GFLOP/s':>8s} {'of matmul':>9s} "
        f"{'others busy':>11s}"
    )
    runs: dict[tuple[str, int], list[dict]] = {}
    for round_ in range(args.repeats):
        if args.repeats > 1:
            print(f"round {round_ + 1} of {args.repeats}")
        for key in keys:
            for n in threads:
                row = run_in_subprocess(key, n, args)
                runs.setdefault((key, n), []).append(row)
                print_row(row)
    rows = [median_run(found) for found in runs.values()]
    if args.repeats > 1:
        print(f"median of {args.repeats} rounds")
        for row in rows:
            print_row(row)
    found = ratios(rows)
    for name, value in found.items():
        print(f"{name} (each at its best thread count): {value:.3f}")
    busy = [row for row in runs_flat(runs) if row["busy"]]
    if busy:
        print(
            f"WARNING: {len(busy)} of {len(runs_flat(runs))} rows started while other processes used more than "
            f"{BUSY_LOAD_PER_CORE:.0%} of the CPU (marked BUSY): they slow the baselines more than the spiking "
            "network; measure again on a quiet machine before quoting a ratio",
            file=sys.stderr,
        )
    result = dict(
        machine=describe_machine(max(threads)),
        settings=dict(vars(args), output=str(args.output), threads=threads),
        rows=rows,
        ratios=found,
    )
    if args.check:
        baseline = json.loads((RESULTS_CUDA if cuda else RESULTS).read_text()).get("ratios", {})
        failed = [name for name, value in found.items() if name in baseline and value < 0.7 * baseline[name]]
        for name in failed:
            print(
                f"REGRESSION: {name} = {found[name]:.3f} vs committed {baseline[name]:.3f} "
                f"(allowed down to {0.7 * baseline[name]:.3f})"
            )
        if not failed:
            print(
                "ok: " + ", ".join(f"{n} {found[n]:.3f} vs committed {baseline[n]:.3f}" for n in found if n in baseline)
            )
        return 1 if failed else 0
    write_result(result, args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
