"""Compiled CPU fast path for :func:`sb3_spikeplastic.neurons.srm_spike_loop`.

The SRM threshold/refractory recursion is sequential in time and element-wise across neurons, so eager PyTorch
spends its time launching ~7 tiny kernels per step. ``srm_loop.cpp`` runs the same recursion in one pass; it is
compiled with :func:`torch.utils.cpp_extension.load` the first time it is needed (never at import), cached on
disk, and gives **bit-identical** spikes, membrane and state: it performs the same IEEE operations in the same
order and dtype as the eager loop, and is compiled with ``-ffp-contract=off`` and without fast-math.

* Build directory: ``$SB3_SPIKEPLASTIC_BUILD_DIR`` if set, else
  ``${XDG_CACHE_HOME:-~/.cache}/sb3_spikeplastic/<python>_<torch>_<cpu-flags>``. Building needs a C++ compiler
  and ``ninja`` and takes ~10-30 s once; later processes only load the cached library (~0.3 s).
* ``SB3_SPIKEPLASTIC_NO_COMPILE=1`` disables the compiled path (read at every call), for tests and debugging.
* If the build fails, a single :class:`RuntimeWarning` is issued and the pure-PyTorch loop is used instead; it
  gives the same results, only slower.
"""

from __future__ import annotations

import os
import shutil
import sys
import sysconfig
import threading
import time
import warnings
from pathlib import Path
from typing import Callable, Optional

import torch
from torch import Tensor

__all__ = ["NO_COMPILE_ENV", "build_directory", "compiled_disabled", "load_srm_loop", "srm_loop"]

NO_COMPILE_ENV = "SB3_SPIKEPLASTIC_NO_COMPILE"
BUILD_DIR_ENV = "SB3_SPIKEPLASTIC_BUILD_DIR"
_EXTENSION = "sb3_spikeplastic_fast"
_SOURCE = Path(__file__).with_name("srm_loop.cpp")

_lock = threading.Lock()
_tried = False
_op: Optional[Callable] = None
_error: Optional[str] = None


def compiled_disabled() -> bool:
    """True when ``SB3_SPIKEPLASTIC_NO_COMPILE`` is set to anything but ``""``/``0``/``false``/``no``."""
    return os.environ.get(NO_COMPILE_ENV, "").strip().lower() not in ("", "0", "false", "no")


def _vector_flags() -> list[str]:
    # Wider vectors for the inner (neuron) loop where the CPU has them; the results do not depend on the width.
    # The flag is part of the build directory's name, so a cache shared between machines cannot mix them.
    try:
        capability = torch.backends.cpu.get_cpu_capability()
    except Exception:  # pragma: no cover - very old torch
        capability = "DEFAULT"
    return ["-mavx2"] if capability in ("AVX2", "AVX512") else []


def _cflags() -> list[str]:
    return ["-O3", "-fno-fast-math", "-ffp-contract=off", "-fopenmp", *_vector_flags()]


def build_directory() -> Path:
    """Where the extension is built and cached (see the module docstring)."""
    explicit = os.environ.get(BUILD_DIR_ENV)
    if explicit:
        return Path(explicit).expanduser()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    tag = "_".join(
        [
            f"py{sys.version_info.major}{sys.version_info.minor}",
            "torch" + torch.__version__.replace("+", "-"),
            "avx2" if _vector_flags() else "generic",
        ]
    )
    return cache / "sb3_spikeplastic" / tag


def _ninja_directory() -> Optional[str]:
    """A directory holding ``ninja`` when it is not on ``PATH``: the ``ninja`` wheel's, or this environment's
    scripts directory (a virtual environment used without being activated)."""
    candidates = []
    try:
        import ninja  # the PyPI wheel

        candidates.append(ninja.BIN_DIR)
    except Exception:
        pass
    candidates.append(sysconfig.get_path("scripts"))
    for directory in candidates:
        if directory and shutil.which("ninja", path=directory):
            return directory
    return None


def _clear_stale_lock(directory: Path, max_age_s: float = 600.0) -> None:
    """Remove a build lock left by a process killed while compiling (torch would wait on it forever).

    A build takes well under a minute, so a lock older than ``max_age_s`` is stale.
    """
    lock = directory / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except OSError:
        return
    if age > max_age_s:
        warnings.warn(f"sb3_spikeplastic: removing stale build lock {lock} ({age:.0f} s old)", RuntimeWarning)
        try:
            lock.unlink()
        except OSError:
            pass


def _build() -> Callable:
    from torch.utils import cpp_extension

    directory = build_directory()
    directory.mkdir(parents=True, exist_ok=True)
    _clear_stale_lock(directory)
    path = os.environ.get("PATH", "")
    extra = None if shutil.which("ninja") else _ninja_directory()
    if extra:  # torch runs `ninja` from PATH
        os.environ["PATH"] = extra + os.pathsep + path
    try:
        cpp_extension.load(
            name=_EXTENSION,
            sources=[str(_SOURCE)],
            extra_cflags=_cflags(),
            extra_ldflags=["-fopenmp"],
            build_directory=str(directory),
            with_cuda=False,
            is_python_module=False,
            verbose=False,
        )
    finally:
        if extra:
            os.environ["PATH"] = path
    return torch.ops.sb3_spikeplastic_fast.srm_loop


def load_srm_loop() -> Optional[Callable]:
    """The compiled op, building it on the first call; ``None`` if the build failed (after one warning)."""
    global _tried, _op, _error
    if _tried:
        return _op
    with _lock:
        if not _tried:
            try:
                _op = _build()
            except Exception as exc:  # no compiler, no ninja, failed build, failed load
                message = " ".join(str(exc).split())
                _error = f"{type(exc).__name__}: {message[:200]}{'...' if len(message) > 200 else ''}"
                warnings.warn(
                    "sb3_spikeplastic: could not build the compiled SRM spike loop "
                    f"({_error}); using the pure-PyTorch loop, which gives identical results but is slower.",
                    RuntimeWarning,
                    stacklevel=3,
                )
            _tried = True
    return _op


def srm_loop(
    synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float
) -> Optional[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Run the compiled recursion, or return ``None`` when it does not apply (then use the PyTorch loop).

    It applies to CPU float32/float64 tensors ``synaptic (batch, L, n)`` and ``h1, h2 (batch, n)`` of one dtype,
    unless disabled by ``SB3_SPIKEPLASTIC_NO_COMPILE`` or the build failed. Returns
    ``(spikes, membrane, h1, h2)``, which never carry autograd history.
    """
    # Cheap checks first: this is called a few hundred times per environment step.
    dtype = synaptic.dtype
    if not (
        synaptic.is_cpu
        and (dtype is torch.float32 or dtype is torch.float64)
        and h1.dtype is dtype
        and h2.dtype is dtype
        and h1.is_cpu
        and h2.is_cpu
        and synaptic.dim() == 3
        and h1.shape == h2.shape == (synaptic.shape[0], synaptic.shape[2])
    ):
        return None
    if NO_COMPILE_ENV in os.environ and compiled_disabled():
        return None
    op = _op if _tried else load_srm_loop()
    if op is None:
        return None
    if torch.is_grad_enabled() and (synaptic.requires_grad or h1.requires_grad or h2.requires_grad):
        with torch.no_grad():
            return op(synaptic, h1, h2, d, kappa, theta)
    return op(synaptic, h1, h2, d, kappa, theta)
