"""Dense against sparse-row plastic products (``_fast.plastic_linear``) at the layer sizes of the HalfCheetah
networks, per density of the spike rows: forward and forward+backward per batch, one torch thread.

Usage::

    python benchmarks/plastic_linear_density.py     # table + benchmarks/results/plastic_linear_density.json
"""

from __future__ import annotations

import time

import torch
from machine import describe_machine, write_result  # benchmarks/machine.py

from pathlib import Path

from sb3_spikeplastic import _fast

#: (name, batch, rows, n_in, n_out, needs dX): each layer's product in a training minibatch
LAYERS = [("CPU entry, input 170 -> 64", 16, 12, 170, 64, False), ("CPU entry, hidden 64 -> 64", 16, 10, 64, 64, True),
          ("CPU entry, output 64 -> 120", 16, 10, 64, 120, True), ("paper, input 600 -> 64", 64, 52, 600, 64, False),
          ("paper, output 64 -> 600", 64, 50, 64, 600, True)]
DENSITIES = (0.05, 0.1, 0.2, 0.4)


def timed(x, W, alpha, E, max_density, backward, repeats=20):
    def once():
        y = _fast.plastic_linear(x, W, alpha, E, max_density)
        if backward:
            y.backward(torch.ones_like(y))
    for _ in range(3):
        once()
    start = time.perf_counter()
    for _ in range(repeats):
        once()
    return (time.perf_counter() - start) / repeats * 1e6


def main() -> int:
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    rows = []
    print(f"{'layer':30s} {'density':>7s} {'dense fwd':>9s} {'sparse fwd':>10s} {'dense f+b':>9s} {'sparse f+b':>10s}  (us)")
    for name, B, R, I, O, x_grad in LAYERS:
        for density in DENSITIES:
            x = (torch.rand(B, R, I, generator=g) < density).float()
            x[:, R - 2:] = torch.rand(B, 2, I, generator=g)  # the carried PSP rows are dense
            x.requires_grad_(x_grad)
            W, alpha = (torch.randn(O, I, generator=g).requires_grad_() for _ in range(2))
            E = torch.randn(B, O, I, generator=g).requires_grad_()
            row = dict(layer=name, batch=B, rows=R, n_in=I, n_out=O, density=density,
                       dense_fwd_us=timed(x, W, alpha, E, 0.0, False), sparse_fwd_us=timed(x, W, alpha, E, 1.0, False),
                       dense_fb_us=timed(x, W, alpha, E, 0.0, True), sparse_fb_us=timed(x, W, alpha, E, 1.0, True))
            rows.append(row)
            print(f"{name:30s} {density:7.2f} {row['dense_fwd_us']:9.0f} {row['sparse_fwd_us']:10.0f} "
                  f"{row['dense_fb_us']:9.0f} {row['sparse_fb_us']:10.0f}", flush=True)
    write_result(dict(machine=describe_machine(1), rows=rows),
                 Path(__file__).parent / "results" / "plastic_linear_density.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
