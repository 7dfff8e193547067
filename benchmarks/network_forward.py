"""Cost of the plastic SNN per environment step, at the paper's HalfCheetah sizes.

Network: ``PopulationEncoder`` 12 dims x 50 cells = 600 inputs -> hidden (64, 64) -> ``ContinuousDecoder``
6 dims x 100 = 600 output neurons, ``T`` network steps per environment step.

* **forward**: one environment step without autograd (what a rollout costs per step), median over repeats.
* **forward+backward**: a truncated-BPTT chunk of ``--chunk`` environment steps with autograd, a scalar loss on
  the actions, then ``backward()``; reported per environment step (what a PPO update costs per sample).

Every configuration is warmed up first (allocations, cached filter matrices), then timed ``--repeats`` times;
the median is reported. Runs on one intra-op thread by default (``--threads``), as the project runs each
environment process on one core.

Usage::

    python benchmarks/network_forward.py                 # table + benchmarks/results/network_forward.json
    python benchmarks/network_forward.py --threads 2 --batch 8 --steps 50 --rules ndp-oja
    python benchmarks/network_forward.py --profile --device cuda   # where the time goes (torch.profiler table)
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from machine import describe_machine, write_result  # benchmarks/machine.py (the script's folder is on sys.path)

from sb3_spikeplastic.snn.coding import ContinuousDecoder, PopulationEncoder
from sb3_spikeplastic.snn.cpu_settings import keep_freed_memory
from sb3_spikeplastic.snn.network import SpikingPlasticNetwork

RESULTS = Path(__file__).parent / "results" / "network_forward.json"
RESULTS_CUDA = RESULTS.with_name("network_forward_cuda.json")  # --device cuda
OBS_DIMS, ACT_DIMS = 12, 6


def paper_network(rule: str, steps: int) -> SpikingPlasticNetwork:
    return SpikingPlasticNetwork(
        PopulationEncoder([-3.0] * OBS_DIMS, [3.0] * OBS_DIMS, pop_size=50),
        ContinuousDecoder([-1.0] * ACT_DIMS, [1.0] * ACT_DIMS, pop_size=100),
        (64, 64),
        steps=steps,
        rule=rule,
    )


def median_time(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def workload(rule: str, batch: int, steps: int, chunk: int, device: str):
    """``(forward, forward_backward, sync)`` closures over a paper-size network that has run a few steps."""
    torch.manual_seed(0)
    net = paper_network(rule, steps).to(device)
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(chunk, batch, OBS_DIMS, generator=g).clamp(-3, 3).to(device)
    # start from a state that has run a few steps (filters and traces non-zero, as during a rollout)
    state = net.initial_state(batch, seed=2, device=device)
    with torch.no_grad():
        for k in range(4):
            _, state = net(obs[k % chunk], state)
    state = state.detach()

    def forward():
        with torch.no_grad():
            net(obs[0], state)

    def forward_backward():
        s, loss = state, 0.0
        for k in range(chunk):
            out, s = net(obs[k], s)
            loss = loss + out.action.square().sum()
        net.zero_grad(set_to_none=True)
        loss.backward()

    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    return forward, forward_backward, sync


def bench(rule: str, batch: int, steps: int, chunk: int, repeats: int, warmup: int, device: str) -> dict:
    forward, forward_backward, sync = workload(rule, batch, steps, chunk, device)
    fwd = median_time(lambda: (forward(), sync()), repeats, warmup)
    fb = median_time(lambda: (forward_backward(), sync()), max(3, repeats // 4), 1) / chunk
    return dict(
        rule=rule,
        batch=batch,
        steps=steps,
        forward_ms=1e3 * fwd,
        forward_backward_ms=1e3 * fb,
        forward_us_per_env=1e6 * fwd / batch,
        forward_backward_us_per_env=1e6 * fb / batch,
    )


def profile(args: argparse.Namespace) -> int:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    _, forward_backward, sync = workload(args.rules[0], max(args.batch), max(args.steps), args.chunk, args.device)
    for _ in range(2):
        forward_backward()
    sync()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if args.device.startswith("cuda") else [])
    with torch_profile(activities=activities) as prof:
        forward_backward()
        sync()
    sort = "self_cuda_time_total" if args.device.startswith("cuda") else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=sort, row_limit=30))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8, 64], help="environments per call")
    parser.add_argument("--steps", type=int, nargs="+", default=[10, 50], help="network steps T per env step")
    parser.add_argument("--rules", nargs="+", default=["static", "ndp-oja"])
    parser.add_argument("--chunk", type=int, default=8, help="env steps per forward+backward (BPTT chunk)")
    parser.add_argument("--repeats", type=int, default=21, help="timed repeats of the forward (median)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--output", type=Path, help=f"default: {RESULTS} ({RESULTS_CUDA.name} with --device cuda)")
    parser.add_argument(
        "--profile",
        action="store_true",
        help="instead of timing, print torch.profiler's op table for forward+backward of the first "
        "rule at the largest batch and T",
    )
    args = parser.parse_args(argv)
    if args.output is None:
        args.output = RESULTS_CUDA if args.device.startswith("cuda") else RESULTS
    torch.set_num_threads(args.threads)
    keep_freed_memory()  # as `sb3-spikeplastic train` does
    if args.profile:
        return profile(args)

    rows = []
    header = (
        f"{'rule':8s} {'B':>4s} {'T':>4s} | {'fwd ms/step':>11s} {'us/env':>8s} | "
        f"{'fwd+bwd ms/step':>15s} {'us/env':>8s}"
    )
    print(header)
    print("-" * len(header))
    for rule in args.rules:
        for steps in args.steps:
            for batch in args.batch:
                row = bench(rule, batch, steps, args.chunk, args.repeats, args.warmup, args.device)
                rows.append(row)
                print(
                    f"{rule:8s} {batch:4d} {steps:4d} | {row['forward_ms']:11.3f} {row['forward_us_per_env']:8.1f} | "
                    f"{row['forward_backward_ms']:15.3f} {row['forward_backward_us_per_env']:8.1f}",
                    flush=True,
                )
    result = dict(
        machine=describe_machine(args.threads),
        settings=dict(vars(args), output=str(args.output)),
        network=dict(inputs=OBS_DIMS * 50, hidden=[64, 64], outputs=ACT_DIMS * 100),
        rows=rows,
    )
    write_result(result, args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
