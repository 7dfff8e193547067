"""What each compiled CPU path gains end to end: ``learn()`` with the path switched off against all on.

Each (network, switch) runs in a process of its own, in interleaved rounds, and times the rollouts + updates
that cover one episode of every environment after a warm-up (as ``learn_throughput.py``). The gain of a path is
``t(without) / t(all on) - 1`` of the round medians; a compiled path stays if it gains at least 5 % on a network
it is meant for. Measure on a quiet machine (the load per core is recorded with every run).

Switches (``--switches``):

* ``all`` — every compiled path on (the reference);
* ``no-spike-products`` — the input layer's products dense (``_fast.spike_density_limit(0)``);
* ``no-block-cache`` — glibc's allocator (``PPO(keep_freed_memory=False)``);
* ``no-carried-rows`` — the carried PSP state copied beside the spikes (``layers.CARRY_MIN_ROW_VALUES`` huge);
* ``no-compile`` — every compiled CPU op off (``SB3_SPIKEPLASTIC_NO_COMPILE=1``): the fused layer interval, the
  trace update, the product and the sampler together.

Networks (``--networks``): ``entry`` (the shipped CPU entry) and ``ndp-oja`` (the paper network), as in
``learn_throughput.py``.

    python benchmarks/kernel_shares.py --rounds 3              # -> benchmarks/results/kernel_shares.json / .md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results" / "kernel_shares.json"
SWITCHES = ("all", "no-spike-products", "no-block-cache", "no-carried-rows", "no-compile")
NETWORKS = ("entry", "ndp-oja")


def run_one(network: str, switch: str, threads: int) -> dict:
    """One timed run in this process (the switch is set before anything is built)."""
    import torch

    torch.set_num_threads(threads)
    from learn_throughput import episode_rollouts, make_model  # benchmarks/ is on sys.path

    from sb3_spikeplastic.snn import _fast, cpu_settings, layers

    cpu_settings.keep_freed_memory()  # glibc's settings, as `train` applies them, in every variant
    if switch == "no-carried-rows":
        layers.CARRY_MIN_ROW_VALUES = 2**62
    if switch == "no-spike-products":
        _fast.spike_density_limit(0.0)
    if switch == "no-block-cache":  # PPO installs the cache while it learns
        cpu_settings.cache_freed_blocks = lambda *args, **kwargs: False
    model = make_model(network, "cpu")
    per_rollout = model.n_steps * model.n_envs
    model.learn(per_rollout)  # warm-up
    rollouts = episode_rollouts(model)
    start = time.perf_counter()
    model.learn(rollouts * per_rollout, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    return dict(
        network=network,
        switch=switch,
        threads=threads,
        seconds=seconds,
        env_steps_per_s=rollouts * per_rollout / seconds,
    )


def in_subprocess(network: str, switch: str, threads: int) -> dict:
    env = dict(os.environ)
    env.pop("SB3_SPIKEPLASTIC_NO_COMPILE", None)
    if switch == "no-compile":
        env["SB3_SPIKEPLASTIC_NO_COMPILE"] = "1"
    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    result = subprocess.run(
        [sys.executable, __file__, "--one", network, switch, "--threads", str(threads)],
        capture_output=True,
        text=True,
        env=env,
    )
    if result.returncode != 0:
        raise RuntimeError(f"{network} / {switch} failed:\n{result.stderr[-3000:]}")
    return dict(json.loads(result.stdout.strip().splitlines()[-1]), load_per_core=round(load, 2))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--networks", nargs="+", choices=NETWORKS, default=list(NETWORKS))
    parser.add_argument("--switches", nargs="+", choices=SWITCHES, default=list(SWITCHES))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--one", nargs=2, metavar=("NETWORK", "SWITCH"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(*args.one, args.threads)))
        return 0
    switches = ["all", *[s for s in args.switches if s != "all"]]
    runs: dict[tuple[str, str], list[dict]] = {}
    for round_ in range(args.rounds):
        for network in args.networks:
            for switch in switches:
                row = in_subprocess(network, switch, args.threads)
                runs.setdefault((network, switch), []).append(row)
                print(
                    f"round {round_ + 1}: {network:8s} {switch:18s} {row['seconds']:8.1f} s "
                    f"{row['env_steps_per_s']:8.1f} env-steps/s  load/core {row['load_per_core']:.2f}",
                    flush=True,
                )
    lines = [
        "| network | switched off | median s | gain of the path (t off / t on - 1) | rounds (s) |",
        "|---|---|---|---|---|",
    ]
    table = []
    for network in args.networks:
        reference = sorted(r["seconds"] for r in runs[(network, "all")])[(args.rounds - 1) // 2]
        for switch in switches:
            seconds = sorted(r["seconds"] for r in runs[(network, switch)])
            median = seconds[(args.rounds - 1) // 2]
            gain = median / reference - 1
            table.append(
                dict(
                    network=network,
                    switch=switch,
                    median_seconds=median,
                    gain=gain,
                    rounds=[r["seconds"] for r in runs[(network, switch)]],
                )
            )
            lines.append(
                f"| {network} | {switch} | {median:.1f} | {'' if switch == 'all' else f'{gain:+.1%}'} | "
                + ", ".join(f"{r['seconds']:.1f}" for r in runs[(network, switch)])
                + " |"
            )
    loads = [r["load_per_core"] for found in runs.values() for r in found]
    note = (
        f"\n\n{args.threads} torch threads; load per core when the runs started: {min(loads):.2f}-{max(loads):.2f}.\n"
    )
    print("\n".join(lines) + note)
    from machine import describe_machine, write_result

    write_result(dict(machine=describe_machine(args.threads), rounds=args.rounds, rows=table), args.output)
    args.output.with_suffix(".md").write_text("\n".join(lines) + note)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
