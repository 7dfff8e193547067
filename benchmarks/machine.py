"""The machine description recorded next to every benchmark result, and writing the result."""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path

import torch

import sb3_spikeplastic


def describe_machine(threads: int) -> dict:
    """CPU model, core count, versions, torch threads, load average (results taken on a busy machine say so)
    and the GPU if any."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    cpu = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), platform.processor())
    return dict(
        platform=platform.platform(),
        cpu=cpu,
        logical_cpus=os.cpu_count(),
        python=sys.version.split()[0],
        torch=torch.__version__,
        sb3_spikeplastic=sb3_spikeplastic.__version__,
        threads=threads,
        load_average=os.getloadavg() if hasattr(os, "getloadavg") else None,
        cuda=torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    )


def write_result(result: dict, path: Path) -> None:
    """Write a benchmark's result (with its machine description) as JSON and say where."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))
    print(f"wrote {path}")
