"""The machine description recorded next to every benchmark result."""

from __future__ import annotations

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
    return dict(platform=platform.platform(), cpu=cpu, logical_cpus=os.cpu_count(), python=sys.version.split()[0],
                torch=torch.__version__, sb3_spikeplastic=sb3_spikeplastic.__version__, threads=threads,
                load_average=os.getloadavg() if hasattr(os, "getloadavg") else None,
                cuda=torch.cuda.get_device_name(0) if torch.cuda.is_available() else None)
