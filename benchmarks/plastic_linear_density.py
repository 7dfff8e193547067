"""The plastic product on spikes against the dense product, by spike density: where the spike products pay.

``_fast.plastic_linear`` at the paper network's input-layer sizes (64 environments, 50 steps, 600 -> 64, the PSP
state carried beside the spikes), forward and forward+backward, once with the spike products allowed
(``spike_density_limit(1.0)``) and once without (``0.0``), on binary inputs firing at each density. The crossover
is where the two columns meet; ``spike_density_limit``'s default sits below it.

    python benchmarks/plastic_linear_density.py            # -> benchmarks/results/plastic_linear_density.json
    python benchmarks/plastic_linear_density.py --threads 2
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from machine import describe_machine, write_result  # benchmarks/machine.py (the script's folder is on sys.path)
from network_forward import median_time

from sb3_spikeplastic.snn import _fast

DENSITIES = (0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5)


def measure(density: float, batch: int, steps: int, n_in: int, n_out: int, repeats: int) -> dict:
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(batch, steps, n_in, generator=g) < density).float()
    carried = torch.randn(batch, 2, n_in, generator=g)
    W, alpha = (0.1 * torch.randn(n_out, n_in, generator=g) for _ in range(2))
    params = [W.requires_grad_(), alpha.requires_grad_(), torch.randn(batch, n_out, n_in, generator=g).requires_grad_()]
    upstream = torch.randn(batch, steps + 2, n_out, generator=g)

    def forward():
        with torch.no_grad():
            _fast.plastic_linear(x, *params, carried)

    def forward_backward():
        out = _fast.plastic_linear(x, *params, carried)
        torch.autograd.grad((out * upstream).sum(), params)

    row = dict(density=density)
    for name, limit in (("spike", 1.0), ("dense", 0.0)):
        _fast.spike_density_limit(limit)
        row[f"{name}_forward_ms"] = 1e3 * median_time(forward, repeats, warmup=1)
        row[f"{name}_forward_backward_ms"] = 1e3 * median_time(forward_backward, repeats, warmup=1)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument(
        "--output", type=Path, default=Path(__file__).resolve().parent / "results" / "plastic_linear_density.json"
    )
    args = parser.parse_args(argv)
    if _fast.load_ops() is None:
        print(f"the compiled ops are unavailable: {_fast.build_error()}")
        return 1
    torch.set_num_threads(args.threads)
    default = _fast.spike_density_limit()
    sizes = dict(batch=64, steps=50, n_in=600, n_out=64)
    rows = []
    print(f"{'density':>8} {'forward ms: spike':>18} {'dense':>7} {'fwd+bwd ms: spike':>18} {'dense':>7}")
    try:
        for density in DENSITIES:
            row = measure(density, repeats=args.repeats, **sizes)
            rows.append(row)
            print(
                f"{density:8.2f} {row['spike_forward_ms']:18.2f} {row['dense_forward_ms']:7.2f} "
                f"{row['spike_forward_backward_ms']:18.2f} {row['dense_forward_backward_ms']:7.2f}"
            )
    finally:
        _fast.spike_density_limit(default)
    write_result(
        dict(machine=describe_machine(args.threads), sizes=sizes, default_limit=default, rows=rows), args.output
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
