"""What the experiment grids share: the console script of this interpreter and a sequential runner with a log."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path


def cli() -> str:
    """The console script of the running interpreter's environment (works without activating it)."""
    return shutil.which("sb3-spikeplastic", path=str(Path(sys.executable).parent)) or "sb3-spikeplastic"


def run_one(commands: list, log: Path) -> int:
    """Run the commands one after another (each built when its turn comes), appending their output to ``log``
    and stopping at the first failure; one torch/OpenMP thread per process."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as out:
        for make in commands:
            out.flush()
            code = subprocess.call(make(), stdout=out, stderr=subprocess.STDOUT,
                                   env={**os.environ, "OMP_NUM_THREADS": "1"})
            if code:
                return code
    return 0
