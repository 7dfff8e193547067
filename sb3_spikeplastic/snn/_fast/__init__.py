"""Compiled kernels of the spiking network's hot loops (C++ sources beside this file), and the one place that
decides whether a compiled op or eager PyTorch runs: :func:`dispatch`.

Each op serves one Python function, which :func:`dispatch` hands either to the op (through its :class:`Kernel`)
or to the eager code that stands in for it, by the operands (dtype, device, shapes), ``SB3_SPIKEPLASTIC_NO_COMPILE``
and whether the build succeeded:

* ``srm_loop`` (``srm_loop.cpp``; :data:`SRM_LOOP`), for :func:`sb3_spikeplastic.snn.neurons.srm_spike_loop`: the SRM
  threshold/refractory recursion, sequential in time and element-wise across neurons, where eager PyTorch spends its
  time launching ~7 tiny kernels per step; one pass, **bit-identical** spikes, membrane and state (the same IEEE
  operations in the same order and dtype, compiled with ``-ffp-contract=off`` and without fast-math).
* ``trace_step_forward`` / ``trace_step_backward`` (``trace_step.cpp``; :data:`TRACE_STEP`), for
  :func:`sb3_spikeplastic.snn.plasticity.hebbian_trace_step`: the trace update and clip of every built-in rule,
  forward and backward, in one pass over the trace each instead of ~20 eager passes; equal to the eager ops to float
  rounding (a dot product is summed in another order).
* ``plastic_linear_forward`` / ``plastic_linear_backward`` (``plastic_linear.cpp``; :data:`PLASTIC_LINEAR`), for
  :func:`sb3_spikeplastic.snn.functional.project`: the synaptic product ``X[b] (W + alpha * E[b])^T`` with the
  efficacy of a few environments at a time in a cache-sized buffer, so that neither the ``(B, n_out, n_in)`` efficacy
  nor its gradient is ever materialised (eager: four extra passes over trace-sized arrays); equal to the eager ops to
  float rounding. Where an environment's ``x`` is binary spikes at most :func:`spike_density_limit` of which fire (the
  input layer's place cells), its forward and gradient products add up the firing inputs' columns instead of
  multiplying through the zeros (``spike_product.h``, AVX2 builds); a one-environment block's float32 input gradient
  runs register tiles of broadcast-FMA (``small_gemm.h``, where the CPU has FMA) instead of BLAS.
* ``srm_interval_forward`` / ``srm_interval_backward`` and their deferred forms ``srm_interval_deferred_*``
  (``srm_interval.cpp``; :data:`sb3_spikeplastic.snn.fused_interval.FUSED_INTERVAL`), for
  :class:`sb3_spikeplastic.snn.layers.PlasticSRMLayer`'s interval (the eager step:
  :func:`sb3_spikeplastic.snn.functional.interval_step`): a whole layer interval (filter, product, spike loop,
  surrogate, rates and, for the built-in rules, the trace update) as one op forward and one backward, built from the
  kernels above; one autograd node per layer and interval where eager autograd records ~15, whose overhead dominated
  the small CPU networks' training step. The deferred forms apply the previous intervals' trace updates in the
  product's pass over the trace. The op filters by the alpha filter's recurrence (``alpha_filter_rows`` and its
  adjoint, ``alpha_filter.cpp``, ~4 operations per value and step) where the eager step multiplies by the filter's
  ``(L + 2, L + 2)`` operator; states and gradients are equal to float rounding. Its tensors travel as named structs
  (:mod:`sb3_spikeplastic.snn._fast.interval`, ``op_fields.h``).
* ``bernoulli_spikes`` (``bernoulli.cpp``; :data:`BERNOULLI_SPIKES`), for
  :meth:`sb3_spikeplastic.snn.coding.CounterBernoulli.sample`: the hash sampler in one pass instead of ~12,
  **bit-identical** (integer hashing, exact comparisons).
* ``cache_cpu_blocks`` / ``uncache_cpu_blocks`` (``block_cache.cpp``), for
  :func:`sb3_spikeplastic.snn.cpu_settings.cache_freed_blocks` and ``release_block_cache``: torch's CPU allocator
  replaced, while a spiking model trains, by one that keeps freed large blocks by exact size for the next
  allocation of that size (a training step allocates the same sizes in every BPTT step), where glibc searches its
  bins.
* Small ops that read or set a kernel's state or describe an interface: ``spike_density_limit`` and
  ``spike_product_counts`` (``plastic_linear.cpp``) for the functions of the same names here,
  ``cpu_block_cache_bytes`` and ``cpu_block_cache_active`` (``block_cache.cpp``) for the allocator's state,
  ``srm_interval_fields`` for the test that holds the interval's NamedTuples to the C++ structs; the alpha
  filter's ``alpha_filter_*`` are registered on
  their own too, for their tests.

On CUDA, ``srm_loop`` runs ``srm_loop_cuda.cu`` instead: one thread per neuron walks the interval's steps, one
launch per layer where eager PyTorch launches ~350 kernels (T = 50), **bit-identical** to the eager loop on the same
GPU. Every other op runs on CPU tensors only; on CUDA :func:`dispatch` runs the eager code, whose few large ops are
already fast there.

The CPU ops are compiled together with :func:`torch.utils.cpp_extension.load` the first time one is needed (never
at import) and cached on disk; the CUDA op likewise, the first time a CUDA tensor needs it (needs ``nvcc``).

* Build directory: ``$SB3_SPIKEPLASTIC_BUILD_DIR`` if set, else
  ``${XDG_CACHE_HOME:-~/.cache}/sb3_spikeplastic/<python>_<torch>_<cpu-flags>_<sources hash>`` (the CUDA op in its
  ``cuda<version>_sm<arch>`` subfolder). It compiles copies of the sources kept in the folder's ``src/``, so every
  checkout or install of the same sources reuses one build. Building needs a C++ compiler and ``ninja``, says one
  line on stderr and takes a while once (measured in ``docs/install.md``, "First use compiles the kernels"); later
  processes only load the cached library. Folders of other source versions are never used again and may be
  deleted.
* ``SB3_SPIKEPLASTIC_NO_COMPILE=1`` disables the compiled path (read at every call), for tests and debugging.
* If a build fails, a single :class:`RuntimeWarning` is issued and the pure-PyTorch code is used instead; it
  gives the same results, only slower.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import sysconfig
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Optional, TypeVar

import torch
from torch import Tensor

from .kernels import (
    BERNOULLI_SPIKES,
    PLASTIC_LINEAR,
    SRM_LOOP,
    TRACE_STEP,
    Kernel,
    SpikeLoopOutputs,
    cpu_float_operands,
)

__all__ = [
    "BERNOULLI_SPIKES",
    "Kernel",
    "NO_COMPILE_ENV",
    "PLASTIC_LINEAR",
    "SRM_LOOP",
    "TRACE_STEP",
    "bernoulli_spikes",
    "build_directory",
    "compiled",
    "compiled_disabled",
    "compiled_ops",
    "cpu_float_operands",
    "dispatch",
    "interval_ops",
    "load_cuda_ops",
    "load_ops",
    "plastic_linear",
    "spike_density_limit",
    "spike_product_counts",
    "srm_loop",
    "trace_step",
]

T = TypeVar("T")

NO_COMPILE_ENV = "SB3_SPIKEPLASTIC_NO_COMPILE"
BUILD_DIR_ENV = "SB3_SPIKEPLASTIC_BUILD_DIR"
#: where the first build's time is measured, as said while compiling
COMPILE_TIME = 'docs/install.md, "First use compiles the kernels"'
_EXTENSION = "sb3_spikeplastic_fast"
_SOURCES = [
    Path(__file__).with_name(name)
    for name in (
        "srm_loop.cpp",
        "trace_step.cpp",
        "plastic_linear.cpp",
        "srm_interval.cpp",
        "alpha_filter.cpp",
        "bernoulli.cpp",
        "block_cache.cpp",
    )
]

_CUDA_EXTENSION = "sb3_spikeplastic_fast_cuda"
_CUDA_SOURCES = [Path(__file__).with_name("srm_loop_cuda.cu")]
_HEADERS = [
    Path(__file__).with_name(name)
    for name in (
        "srm_loop_checks.h",
        "denormal_mode.h",
        "kernels.h",
        "lanes.h",
        "op_fields.h",
        "small_gemm.h",
        "spike_product.h",
    )
]

_lock = threading.Lock()
_tried = False
_ops: Optional[Any] = None
_error: Optional[str] = None
_cuda_tried = False
_cuda_ops: Optional[Any] = None
_cuda_error: Optional[str] = None


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
            _sources_digest(),
        ]
    )
    return cache / "sb3_spikeplastic" / tag


def _sources_digest() -> str:
    """A short hash of the C++/CUDA sources: each version of them builds in a directory of its own, so that two
    installed versions (or checkouts) sharing one cache never rebuild over each other's library."""
    digest = hashlib.sha256()
    for source in [*_SOURCES, *_CUDA_SOURCES, *_HEADERS]:
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    return digest.hexdigest()[:12]


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

    A build takes far less than ``max_age_s`` (``docs/install.md``, "First use compiles the kernels"), so an older
    lock is stale.
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


def _sources_in(directory: Path, sources: list[Path]) -> list[Path]:
    """Copies of ``sources`` and the headers in ``directory / "src"``, written only where they differ.

    The build records the paths of its sources and rebuilds when they change: compiling copies kept beside the
    build lets every checkout or install of the same sources (the directory is keyed by their digest) reuse it.
    """
    copies = directory / "src"
    copies.mkdir(parents=True, exist_ok=True)
    for source in [*sources, *_HEADERS]:
        target, text = copies / source.name, source.read_bytes()
        if not target.exists() or target.read_bytes() != text:
            partial = target.with_name(f".{target.name}.{os.getpid()}")
            partial.write_bytes(text)
            partial.replace(target)  # atomic: a concurrent build reads the old or the new file, never half of one
    return [copies / source.name for source in sources]


def _compile(name: str, sources: list[Path], directory: Path, **options: Any) -> None:
    """:func:`torch.utils.cpp_extension.load` into ``directory``, with ``ninja`` found where pip puts it; says so
    on stderr when it has to compile (the first use of a version of the sources)."""
    from torch.utils import cpp_extension

    directory.mkdir(parents=True, exist_ok=True)
    _clear_stale_lock(directory)
    sources = _sources_in(directory, sources)
    if not (directory / f"{name}.so").exists():
        print(
            f"sb3_spikeplastic: compiling {name} once into {directory} (build time: {COMPILE_TIME}) ...",
            file=sys.stderr,
            flush=True,
        )
    path = os.environ.get("PATH", "")
    extra = None if shutil.which("ninja") else _ninja_directory()
    if extra:  # torch runs `ninja` from PATH
        os.environ["PATH"] = extra + os.pathsep + path
    try:
        cpp_extension.load(
            name=name,
            sources=[str(source) for source in sources],
            build_directory=str(directory),
            is_python_module=False,
            verbose=False,
            **options,
        )
    finally:
        if extra:
            os.environ["PATH"] = path


def _build() -> Any:
    _compile(
        _EXTENSION, _SOURCES, build_directory(), extra_cflags=_cflags(), extra_ldflags=["-fopenmp"], with_cuda=False
    )
    return torch.ops.sb3_spikeplastic_fast


def _build_cuda() -> Any:
    major, minor = torch.cuda.get_device_capability()
    # One build per CUDA version and GPU architecture: a cache shared between machines cannot mix them.
    directory = build_directory() / f"cuda{torch.version.cuda}_sm{major}{minor}"
    _compile(
        _CUDA_EXTENSION,
        _CUDA_SOURCES,
        directory,
        extra_cflags=["-O3"],
        extra_cuda_cflags=["-O3", "-fmad=false"],
        with_cuda=True,
    )
    return torch.ops.sb3_spikeplastic_cuda


#: A failed CPU build is recorded in its build directory, so that later processes of the same machine and version
#: do not try (and warn at length) again; it is tried again where a compiler appears that the record did not see.
FAILED_BUILD_RECORD = "build_failed.txt"


def _compiler() -> str:
    """The C++ compiler torch would use (``$CXX`` or ``c++``), or ``""`` where there is none."""
    return shutil.which(os.environ.get("CXX", "c++")) or ""


def _try_build(build, what: str, record: Optional[Path] = None) -> tuple[Optional[Any], Optional[str]]:
    """``(ops, None)``, or ``(None, error)`` after one warning when the build fails (recorded in ``record``: the
    next process with the same compiler skips the attempt and says so in one line)."""
    if record is not None and record.is_file():
        compiler, _, error = record.read_text().partition("\n")
        if compiler == _compiler():
            warnings.warn(
                f"sb3_spikeplastic: the compiled {what} failed to build on this machine before ({record}; "
                "delete it to try again); using pure PyTorch, which gives the same results but is slower.",
                RuntimeWarning,
                stacklevel=4,
            )
            return None, error.strip()
    try:
        return build(), None
    except Exception as exc:  # no compiler, no ninja/nvcc, failed build, failed load
        message = " ".join(str(exc).split())
        error = f"{type(exc).__name__}: {message[:200]}{'...' if len(message) > 200 else ''}"
        # A failed build's message starts with the compiler's command line; its first "error" line says why.
        reason = next((line.strip() for line in str(exc).splitlines()[1:] if "error" in line.lower()), None)
        if reason:
            error += f" [{reason[:300]}]"
        warnings.warn(
            f"sb3_spikeplastic: could not build the compiled {what} ({error}); using pure PyTorch, "
            "which gives the same results but is slower.",
            RuntimeWarning,
            stacklevel=4,
        )
        if record is not None:
            try:
                record.parent.mkdir(parents=True, exist_ok=True)
                record.write_text(f"{_compiler()}\n{error}\n")
            except OSError:
                pass
        return None, error


def load_ops() -> Optional[Any]:
    """The compiled CPU ops' namespace, building them on the first call; ``None`` if the build failed (after one
    warning)."""
    global _tried, _ops, _error
    if _tried:
        return _ops
    with _lock:
        if not _tried:
            _ops, _error = _try_build(_build, "CPU kernels", build_directory() / FAILED_BUILD_RECORD)
            _tried = True
    return _ops


def load_cuda_ops() -> Optional[Any]:
    """The CUDA op's namespace, building it on the first call; ``None`` without CUDA or if the build failed (after
    one warning)."""
    global _cuda_tried, _cuda_ops, _cuda_error
    if _cuda_tried:
        return _cuda_ops
    with _lock:
        if not _cuda_tried:
            _cuda_ops, _cuda_error = _try_build(_build_cuda, "CUDA spike loop")
            _cuda_tried = True
    return _cuda_ops


def build_error(cuda: bool = False) -> Optional[str]:
    """Why the compiled CPU ops (``cuda``: the CUDA op) are unavailable: the build's error, or ``None`` when they
    loaded or no build was tried yet."""
    return _cuda_error if cuda else _error


def _enabled_ops() -> Optional[Any]:
    if NO_COMPILE_ENV in os.environ and compiled_disabled():
        return None
    return _ops if _tried else load_ops()


def _enabled_cuda_ops() -> Optional[Any]:
    if NO_COMPILE_ENV in os.environ and compiled_disabled():
        return None
    return _cuda_ops if _cuda_tried else load_cuda_ops()


def compiled_ops(kernel: Kernel, *operands) -> Optional[Any]:
    """The one place that decides between a compiled op and eager PyTorch: the compiled namespace that runs
    ``kernel`` on ``operands``, or ``None`` where the eager code runs them (operands the op does not take, disabled by
    ``SB3_SPIKEPLASTIC_NO_COMPILE``, or the build failed). Builds the library on the first call that needs it."""
    if not kernel.applies(*operands):
        return None
    if kernel.cuda and operands[0].is_cuda:
        return _enabled_cuda_ops()
    return _enabled_ops()


def dispatch(kernel: Kernel, eager: Callable[..., T], *operands) -> T:
    """``kernel``'s compiled op on ``operands`` where :func:`compiled_ops` finds one, else ``eager(*operands)``; the
    two return the same values (bit for bit or to float rounding, as the module docstring says per op)."""
    ops = compiled_ops(kernel, *operands)
    return eager(*operands) if ops is None else kernel.run(ops, *operands)


def compiled(kernel: Kernel, *operands) -> Optional[Any]:
    """``kernel``'s compiled op alone on ``operands``, or ``None`` where :func:`compiled_ops` finds none (for tests
    and benchmarks that hold it against the eager code; the network goes through :func:`dispatch`)."""
    ops = compiled_ops(kernel, *operands)
    return None if ops is None else kernel.run(ops, *operands)


def srm_loop(
    synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float
) -> Optional[SpikeLoopOutputs]:
    """:data:`SRM_LOOP` alone (see :func:`compiled`): float32/float64 ``synaptic (batch, L, n)`` and ``h1, h2
    (batch, n)`` of one dtype, all on the CPU (``srm_loop.cpp``) or all on one CUDA device (``srm_loop_cuda.cu``).
    Its outputs never carry autograd history."""
    return compiled(SRM_LOOP, synaptic, h1, h2, d, kappa, theta)


def trace_step(E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Optional[Tensor]:
    """:data:`TRACE_STEP` alone (see :func:`compiled`): CPU float32/float64 ``E (B, n_out, n_in)``, ``post
    (B, n_out)``, ``pre (B, n_in)`` and a one-element ``eta`` of one dtype. Differentiable once (no double
    backward)."""
    return compiled(TRACE_STEP, E, post, pre, eta, e_max, oja)


def plastic_linear(
    x: Tensor, weight: Tensor, alpha: Tensor, E: Tensor, carried: Optional[Tensor] = None
) -> Optional[Tensor]:
    """:data:`PLASTIC_LINEAR` alone (see :func:`compiled`): ``x[b] @ (W + alpha * E[b]).T`` for CPU float32/float64
    ``x (B, L, n_in)``, ``W, alpha (n_out, n_in)`` and ``E (B, n_out, n_in)`` of one dtype. With ``carried
    (B, 2, n_in)``, the product of the rows ``[x; carried]`` ``(B, L + 2, n_out)``, without copying them into one
    tensor: the carried rows are multiplied in the pass that builds the efficacy. Differentiable once."""
    return compiled(PLASTIC_LINEAR, x, weight, alpha, E, carried)


def bernoulli_spikes(p: Tensor, keys: Tensor, index_hash: Tensor) -> Optional[Tensor]:
    """:data:`BERNOULLI_SPIKES` alone (see :func:`compiled`): CPU float32/float64 ``p (B, n)``, int32 ``keys (B,)``
    and ``index_hash (T, n)``. No autograd (spikes are samples)."""
    return compiled(BERNOULLI_SPIKES, p, keys, index_hash)


def spike_density_limit(limit: Optional[float] = None) -> Optional[float]:
    """The largest fraction of an environment's ``x`` values that may be spikes for :data:`PLASTIC_LINEAR` (and the
    fused interval) to take the spike products (default 0.3; 0 turns them off); sets it when ``limit`` is given and
    returns the previous one. ``None`` without the compiled ops."""
    ops = _enabled_ops()
    if ops is None:
        return None
    if limit is not None and not 0.0 <= float(limit) <= 1.0:
        raise ValueError(f"spike_density_limit: limit={limit!r} is not a fraction in [0, 1]")
    return ops.spike_density_limit(-1.0 if limit is None else float(limit))


def spike_product_counts() -> Optional[tuple[int, int]]:
    """How many environments' products took the spike path and how many were checked and kept the dense one (their
    input not binary, e.g. a layer's filtered PSPs, or too many spikes) since the compiled ops were loaded
    (``(spike, dense)``), or ``None`` without them."""
    ops = _enabled_ops()
    if ops is None:
        return None
    spike, dense = ops.spike_product_counts()
    return int(spike), int(dense)


def interval_ops() -> Optional[Any]:
    """The compiled CPU namespace where it is enabled and built (the fused interval's ops among it), else ``None``:
    whether the layers' intervals can run compiled at all (:func:`compiled_ops` decides per call)."""
    return _enabled_ops()
