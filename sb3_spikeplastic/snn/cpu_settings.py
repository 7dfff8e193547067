"""CPU settings under which spiking plastic networks train fast, applied only while they train or evaluate.

* **Flush-to-zero** (``torch.set_flush_denormal(True)``): the PSP filters of silent neurons, the traces and their
  gradients decay through the subnormal floats (below ~1e-38 in float32), where CPU arithmetic is up to ~100x
  slower; flushed to zero they change no spike, and the HalfCheetah entry trains ~1.3x faster
  (``benchmarks/README.md``).
* **The block cache** (torch's CPU allocator, ``_fast/block_cache.cpp``): a training step allocates and frees the
  same few hundred 0.1-10 MB tensors in every BPTT step, and glibc searches, splits and coalesces its bins for
  every one. A cache of freed blocks by exact size hands the same block back in O(1): the paper network's training
  step at batch 32 on two threads takes ~6 % less time and peaks at 1.13 instead of 1.32-1.38 GB. Exact sizes suit
  the spiking policies, whose shapes repeat from step to step; a workload of ever-changing shapes would fill the
  cache with blocks it never reuses (sb3-contrib's RecurrentPPO peaked 0.3 GB higher), so only spiking models use it.

:func:`spiking_cpu_settings` applies both and puts back what was there before on exit: ``sb3_spikeplastic.PPO``
enters it in ``learn()``, and the command line's evaluations enter it around a spiking model's episodes. Building
a model changes nothing. Around your own evaluation loop::

    with spiking_cpu_settings(cache_blocks=False):
        evaluate_policy(model, env)

* **glibc's thresholds** (:func:`keep_freed_memory`, process-wide and for good: glibc cannot say what they were):
  by default glibc serves each large block from ``mmap`` and unmaps it on free, so the next step page-faults it back
  in (~3.7k faults, ~12 ms per call of a ``(64, 50, 600)`` layer); raising ``M_MMAP_THRESHOLD`` to its maximum
  (32 MiB on 64-bit) and ``M_TRIM_THRESHOLD`` keeps them in the heap: 10 % faster training steps. The commands
  ``train``, ``optimize`` and ``study`` call it once for their process; call it yourself in a training script.
  Under those thresholds the heap keeps what a training freed, resident, and the next ``learn()`` of the same
  process peaked higher, its blocks not all placed in the freed ones. So :func:`spiking_cpu_settings` hands the
  freed heap back (:func:`return_freed_memory`) when it takes the block cache down: the paper network's row of
  ``benchmarks/learn_throughput.py`` (a warm-up ``learn()``, then the timed one) peaked at 1560-1620 MiB without
  it and at 1470 MiB with it, at the same speed.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
from collections.abc import Iterator
from typing import Optional

import torch

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Blocks of at least this many bytes go to the cache (smaller ones: glibc's thread caches are fast).
CACHE_MIN_BYTES = 64 * 1024
#: At most this many bytes of freed blocks are kept; beyond it a freed block goes back to glibc.
CACHE_MAX_BYTES = 2 * 1024**3


@functools.cache
def _libc() -> Optional[ctypes.CDLL]:
    """The C library, looked up once (``find_library`` runs ``ldconfig``: ~2 ms, and every ``learn()`` ends here)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


def keep_freed_memory() -> bool:
    """Apply the glibc thresholds for this process; returns whether they took effect (glibc only)."""
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):  # not glibc (musl, macOS): nothing to tune
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def return_freed_memory() -> bool:
    """Give the pages of the heap's free chunks back to the system (glibc's ``malloc_trim(0)``); returns whether it
    ran (glibc only)."""
    libc = _libc()
    if libc is None or not hasattr(libc, "malloc_trim"):
        return False
    libc.malloc_trim(0)
    return True


def flush_denormal_enabled() -> bool:
    """Whether this thread flushes subnormal floats to zero (torch offers no getter: a subnormal times one is
    zero exactly when it does)."""
    return (torch.tensor(1e-40, dtype=torch.float32) * 1.0).item() == 0.0


def _ops():
    from ._fast import _enabled_ops

    return _enabled_ops()


def block_cache_active() -> bool:
    """Whether the block cache is torch's CPU allocator now."""
    ops = _ops()
    return ops is not None and bool(ops.cpu_block_cache_active())


def cache_freed_blocks(min_bytes: int = CACHE_MIN_BYTES, max_cached_bytes: int = CACHE_MAX_BYTES) -> bool:
    """Make the block cache torch's CPU allocator; returns whether this call installed it (``False``: it already
    was, or the compiled ops are off, e.g. with ``SB3_SPIKEPLASTIC_NO_COMPILE``). Tensors allocated before keep
    their allocator."""
    ops = _ops()
    return ops is not None and bool(ops.cache_cpu_blocks(int(min_bytes), int(max_cached_bytes)))


def release_block_cache() -> bool:
    """Put back the CPU allocator that :func:`cache_freed_blocks` replaced and free the cached blocks; returns
    whether the cache was installed."""
    ops = _ops()
    return ops is not None and bool(ops.uncache_cpu_blocks())


@contextlib.contextmanager
def spiking_cpu_settings(flush_denormal: bool = True, cache_blocks: bool = True) -> Iterator[None]:
    """Flush-to-zero and the block cache while the block runs, each put back as it was on exit (so nested uses
    and a user's own settings are kept); taking the cache down also returns the freed heap to the system."""
    flushing = flush_denormal_enabled() if flush_denormal else True
    installed = cache_blocks and cache_freed_blocks()
    if not flushing:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if not flushing:
            torch.set_flush_denormal(False)
        if installed:
            release_block_cache()
            return_freed_memory()
