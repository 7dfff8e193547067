"""Allocator settings for training: keep freed large blocks for reuse instead of returning them to the OS or to
glibc's bins.

A training step allocates and frees the same few hundred 0.1-10 MB tensors in every BPTT step (trace-sized
arrays, ``(batch, T, n)`` activations and their gradients). Two settings make that cheap:

* :func:`keep_freed_memory` (glibc): by default glibc serves each large block from ``mmap`` and unmaps it on
  free, so the next step page-faults it back in (measured: ~3.7k faults, ~12 ms per call of a ``(64, 50, 600)``
  layer). Raising ``M_MMAP_THRESHOLD`` to its maximum (32 MiB on 64-bit) and ``M_TRIM_THRESHOLD`` keeps them in
  the heap: 10 % faster training steps (``PPO`` chunk step, static and ndp-oja). ``sb3-spikeplastic train``,
  ``optimize`` and ``study`` apply it.
* :func:`cache_freed_blocks` (torch's CPU allocator, ``block_cache.cpp``): glibc still searches, splits and
  coalesces its bins for every large block, ~5 % of the main thread's time on the paper network. A cache of
  freed blocks by exact size hands the same block back in O(1): the paper network's training step at batch 32
  on two threads takes ~6 % less time (median over 8 interleaved pairs of runs, 13.2-15.4 against 13.8-16.0 ms
  per env step) and peaks at 1.13 instead of 1.32-1.38 GB (glibc's bins fragment). Exact sizes suit the spiking
  policies, whose shapes repeat from step to step; a workload of ever-changing shapes would fill the cache with
  blocks it never reuses (sb3-contrib's RecurrentPPO, with its padded sequences of varying length, peaked 0.3 GB
  higher), so ``PPO`` installs it for spiking policies only (``PPO(keep_freed_memory=True)``).

Both are process-wide and keep freed memory in the process (up to the peak it used).
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Blocks of at least this many bytes go to the cache (smaller ones: glibc's thread caches are fast).
CACHE_MIN_BYTES = 64 * 1024
#: At most this many bytes of freed blocks are kept; beyond it a freed block goes back to glibc.
CACHE_MAX_BYTES = 2 * 1024**3


def keep_freed_memory() -> bool:
    """Apply the glibc settings for this process; returns whether they took effect (glibc only)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to tune
        return False


def cache_freed_blocks(min_bytes: int = CACHE_MIN_BYTES, max_cached_bytes: int = CACHE_MAX_BYTES) -> bool:
    """Install the block cache as torch's CPU allocator, once per process; returns whether it is installed (after
    this or an earlier call). Needs the compiled ops (``None`` of them, e.g. with ``SB3_SPIKEPLASTIC_NO_COMPILE``:
    nothing happens). Tensors allocated before keep their allocator."""
    global _cache_installed
    if _cache_installed:
        return True
    from . import _enabled_ops

    ops = _enabled_ops()
    if ops is None:
        return False
    ops.cache_cpu_blocks(int(min_bytes), int(max_cached_bytes))
    _cache_installed = True
    return True


_cache_installed = False
