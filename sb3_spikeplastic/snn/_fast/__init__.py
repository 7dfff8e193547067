"""Compiled CPU fast paths of the two inner loops that eager PyTorch runs slowest.

* :func:`srm_loop` (``srm_loop.cpp``), for :func:`sb3_spikeplastic.snn.neurons.srm_spike_loop`: the SRM
  threshold/refractory recursion is sequential in time and element-wise across neurons, so eager PyTorch spends
  its time launching ~7 tiny kernels per step; the compiled loop runs it in one pass and gives **bit-identical**
  spikes, membrane and state (the same IEEE operations in the same order and dtype, compiled with
  ``-ffp-contract=off`` and without fast-math).
* :func:`trace_step` (``trace_step.cpp``), for :func:`sb3_spikeplastic.snn.plasticity.hebbian_trace_step`: the
  trace update and clip of every built-in rule, forward and backward, in one pass over the trace each instead of
  ~20 eager passes; equal to the eager ops to float rounding (a dot product is summed in another order).
* :func:`plastic_linear` (``plastic_linear.cpp``), for :meth:`sb3_spikeplastic.snn.layers.PlasticSRMLayer.project`:
  the synaptic product ``X[b] (W + alpha * E[b])^T`` with the efficacy of a few environments at a time in a
  cache-sized buffer, so that neither the ``(B, n_out, n_in)`` efficacy nor its gradient is ever materialised
  (eager: four extra passes over trace-sized arrays); equal to the eager ops to float rounding. Where an
  environment's ``x`` is binary spikes at most :func:`spike_density_limit` of which fire (the input layer's place
  cells), its forward and gradient products add up the firing inputs' columns instead of multiplying through the
  zeros (``spike_product.h``, AVX2 builds); a one-environment block's float32 input gradient runs register tiles of
  broadcast-FMA (``small_gemm.h``, where the CPU has FMA) instead of BLAS.
* :func:`interval_ops` (``srm_interval.cpp``), for :class:`sb3_spikeplastic.snn.layers.PlasticSRMLayer`: a whole
  layer interval (filter, product, spike loop, surrogate, rates and, for the built-in rules, the trace update) as
  one op forward and one backward, built from the kernels above; one autograd node per layer and interval where
  eager autograd records ~15, whose overhead dominated the small CPU networks' training step. It filters by the
  alpha filter's recurrence (``alpha_filter.cpp``, ~4 operations per value and step) where the eager layer
  multiplies by the filter's ``(L + 2, L + 2)`` operator; states and gradients are equal to float rounding.
* :func:`bernoulli_spikes` (``bernoulli.cpp``), for :meth:`sb3_spikeplastic.snn.coding.CounterBernoulli.sample`:
  the hash sampler in one pass instead of ~12, **bit-identical** (integer hashing, exact comparisons).
* ``cache_cpu_blocks`` (``block_cache.cpp``), for :func:`sb3_spikeplastic.snn.cpu_settings.cache_freed_blocks`:
  torch's CPU allocator replaced by one that keeps freed large blocks by exact size for the next allocation of
  that size (a training step allocates the same sizes in every BPTT step), where glibc searches its bins.

On CUDA, :func:`srm_loop` runs ``srm_loop_cuda.cu`` instead: one thread per neuron walks the interval's steps,
one launch per layer where eager PyTorch launches ~350 kernels (T = 50), **bit-identical** to the eager loop on
the same GPU. The other three fall back to eager PyTorch on CUDA, where their few large ops are already fast.

The CPU ops are compiled together with :func:`torch.utils.cpp_extension.load` the first time one is needed (never
at import) and cached on disk; the CUDA op likewise, the first time a CUDA tensor needs it (needs ``nvcc``).

* Build directory: ``$SB3_SPIKEPLASTIC_BUILD_DIR`` if set, else
  ``${XDG_CACHE_HOME:-~/.cache}/sb3_spikeplastic/<python>_<torch>_<cpu-flags>_<sources hash>`` (the CUDA op in its
  ``cuda<version>_sm<arch>`` subfolder). It compiles copies of the sources kept in the folder's ``src/``, so every
  checkout or install of the same sources reuses one build. Building needs a C++ compiler and ``ninja``, says one
  line on stderr and takes a minute or two once on two cores; later processes only load the cached library
  (~0.3 s). Folders of other source versions are never used again and may be deleted.
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
from typing import Any, Optional

import torch
from torch import Tensor

__all__ = ["NO_COMPILE_ENV", "bernoulli_spikes", "build_directory", "compiled_disabled", "cpu_float_operands",
           "interval_ops", "load_cuda_ops", "load_ops", "plastic_linear", "spike_density_limit", "spike_product_counts",
           "srm_loop", "trace_step"]

NO_COMPILE_ENV = "SB3_SPIKEPLASTIC_NO_COMPILE"
BUILD_DIR_ENV = "SB3_SPIKEPLASTIC_BUILD_DIR"
#: the first build's time, as said while compiling (measured: ``benchmarks/README.md``)
COMPILE_TIME = "a minute or two on two cores"
_EXTENSION = "sb3_spikeplastic_fast"
_SOURCES = [Path(__file__).with_name(name)
            for name in ("srm_loop.cpp", "trace_step.cpp", "plastic_linear.cpp", "srm_interval.cpp",
                         "alpha_filter.cpp", "bernoulli.cpp", "block_cache.cpp")]

_CUDA_EXTENSION = "sb3_spikeplastic_fast_cuda"
_CUDA_SOURCES = [Path(__file__).with_name("srm_loop_cuda.cu")]
_HEADERS = [Path(__file__).with_name(name)
            for name in ("srm_loop_checks.h", "denormal_mode.h", "kernels.h", "lanes.h", "small_gemm.h", "spike_product.h")]

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
        print(f"sb3_spikeplastic: compiling {name} once into {directory} (about {COMPILE_TIME}) ...",
              file=sys.stderr, flush=True)
    path = os.environ.get("PATH", "")
    extra = None if shutil.which("ninja") else _ninja_directory()
    if extra:  # torch runs `ninja` from PATH
        os.environ["PATH"] = extra + os.pathsep + path
    try:
        cpp_extension.load(name=name, sources=[str(source) for source in sources], build_directory=str(directory),
                           is_python_module=False, verbose=False, **options)
    finally:
        if extra:
            os.environ["PATH"] = path


def _build() -> Any:
    _compile(_EXTENSION, _SOURCES, build_directory(), extra_cflags=_cflags(), extra_ldflags=["-fopenmp"],
             with_cuda=False)
    return torch.ops.sb3_spikeplastic_fast


def _build_cuda() -> Any:
    major, minor = torch.cuda.get_device_capability()
    # One build per CUDA version and GPU architecture: a cache shared between machines cannot mix them.
    directory = build_directory() / f"cuda{torch.version.cuda}_sm{major}{minor}"
    _compile(_CUDA_EXTENSION, _CUDA_SOURCES, directory, extra_cflags=["-O3"],
             extra_cuda_cflags=["-O3", "-fmad=false"], with_cuda=True)
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
            warnings.warn(f"sb3_spikeplastic: the compiled {what} failed to build on this machine before ({record}; "
                          "delete it to try again); using pure PyTorch, which gives the same results but is slower.",
                          RuntimeWarning, stacklevel=4)
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
        warnings.warn(f"sb3_spikeplastic: could not build the compiled {what} ({error}); using pure PyTorch, "
                      "which gives the same results but is slower.", RuntimeWarning, stacklevel=4)
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
            _ops, _error = _try_build(_build, "inner loops", build_directory() / FAILED_BUILD_RECORD)
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


def cpu_float_operands(first: Tensor, *others: Tensor) -> bool:
    """Whether ``first`` is a CPU float32/float64 tensor and ``others`` are CPU tensors of its dtype (what every
    compiled op needs besides its shapes)."""
    dtype = first.dtype
    if not (first.is_cpu and (dtype is torch.float32 or dtype is torch.float64)):
        return False
    return all(t.dtype is dtype and t.is_cpu for t in others)


def srm_loop(
    synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float
) -> Optional[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Run the compiled recursion, or return ``None`` when it does not apply (then use the PyTorch loop).

    It applies to float32/float64 tensors ``synaptic (batch, L, n)`` and ``h1, h2 (batch, n)`` of one dtype, all
    on the CPU (``srm_loop.cpp``) or all on one CUDA device (``srm_loop_cuda.cu``), unless disabled by
    ``SB3_SPIKEPLASTIC_NO_COMPILE`` or the build failed. Returns ``(spikes, membrane, h1, h2)``, which never carry
    autograd history.
    """
    if not (synaptic.dim() == 3 and h1.shape == h2.shape == (synaptic.shape[0], synaptic.shape[2])):
        return None
    if synaptic.is_cuda:
        usable = (synaptic.dtype in (torch.float32, torch.float64)
                  and all(t.dtype is synaptic.dtype and t.device == synaptic.device for t in (h1, h2)))
        ops = _enabled_cuda_ops() if usable else None
    else:
        ops = _enabled_ops() if cpu_float_operands(synaptic, h1, h2) else None
    if ops is None:
        return None
    with torch.no_grad():
        return ops.srm_loop(synaptic, h1, h2, d, kappa, theta)


class _TraceStep(torch.autograd.Function):
    """``clamp((1-eta) E + (eta p) (x) pre, +-e_max)`` with ``p = post - [E pre]``, fused (see ``trace_step.cpp``).

    Forward: one pass over ``E``. Backward: one pass over ``E`` and the incoming gradient, recomputing the clip
    mask instead of storing the pre-clip trace; returns the gradients of ``E``, ``post``, ``pre`` and ``eta``.
    """

    @staticmethod
    def forward(ctx, E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Tensor:
        eta_value = float(eta)
        new, p = _ops.trace_step_forward(E, post, pre, eta_value, e_max, oja)
        ctx.save_for_backward(E, p, pre)
        ctx.constants = (eta_value, e_max, oja, eta.shape, eta.dtype)
        return new

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        E, p, pre = ctx.saved_tensors
        eta_value, e_max, oja, eta_shape, eta_dtype = ctx.constants
        d_e, d_post, d_pre, d_eta = _ops.trace_step_backward(grad, E, p, pre, eta_value, e_max, oja)
        return d_e, d_post, d_pre, d_eta.to(eta_dtype).reshape(eta_shape), None, None


def trace_step(E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Optional[Tensor]:
    """The fused trace update, or ``None`` when it does not apply (then use the eager ops).

    It applies to CPU float32/float64 ``E (B, n_out, n_in)``, ``post (B, n_out)``, ``pre (B, n_in)`` and a
    one-element ``eta`` of one dtype, unless disabled by ``SB3_SPIKEPLASTIC_NO_COMPILE`` or the build failed.
    Differentiable once (no double backward).
    """
    if not (
        cpu_float_operands(E, post, pre)
        and eta.dtype is E.dtype
        and eta.numel() == 1
        and E.dim() == 3
        and post.shape == E.shape[:2]
        and pre.shape == (E.shape[0], E.shape[2])
    ):
        return None
    if _enabled_ops() is None:
        return None
    return _TraceStep.apply(E, post, pre, eta, float(e_max), bool(oja))


class _PlasticLinear(torch.autograd.Function):
    """``X[b] (W + alpha * E[b])^T`` per environment, and the same product of the rows ``C[b]`` carried beside ``X``
    (when given: a layer's PSP state), the efficacy of a few environments at a time, blocks split between torch's
    threads (see ``plastic_linear.cpp``); the gradients of ``X`` and ``C`` are computed only when needed."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, alpha: Tensor, E: Tensor, carried: Optional[Tensor]):
        ctx.save_for_backward(x, weight, alpha, E, carried)
        ctx.set_materialize_grads(False)  # an unused output's gradient is read as zero, not filled with it
        y, y_carried = _ops.plastic_linear_forward(x, weight, alpha, E, carried)
        if carried is None:
            ctx.mark_non_differentiable(y_carried)
        return y, y_carried

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Optional[Tensor], grad_carried: Optional[Tensor]):
        x, weight, alpha, E, carried = ctx.saved_tensors
        if grad is None:
            grad = x.new_zeros(x.shape[0], x.shape[1], weight.shape[0])
        need_rows = ctx.needs_input_grad[0] or ctx.needs_input_grad[4]
        d_x, d_w, d_alpha, d_e, d_c = _ops.plastic_linear_backward(grad, grad_carried, x, weight, alpha, E, carried,
                                                                   need_rows)
        return (d_x if ctx.needs_input_grad[0] else None, d_w, d_alpha, d_e,
                d_c if ctx.needs_input_grad[4] else None)


def plastic_linear(x: Tensor, weight: Tensor, alpha: Tensor, E: Tensor,
                   carried: Optional[Tensor] = None) -> Optional[Tensor]:
    """The fused ``x[b] @ (W + alpha * E[b]).T`` for CPU float32/float64 ``x (B, L, n_in)``, ``W, alpha
    (n_out, n_in)`` and ``E (B, n_out, n_in)`` of one dtype, or ``None`` when it does not apply (then use the eager
    ops). With ``carried (B, 2, n_in)``, the product of the rows ``[x; carried]`` ``(B, L + 2, n_out)``, without
    copying them into one tensor: the carried rows are multiplied in the pass that builds the efficacy.
    Differentiable once."""
    if not (
        cpu_float_operands(E, x, weight, alpha, *([] if carried is None else [carried]))
        and E.dim() == 3
        and x.dim() == 3
        and weight.shape == alpha.shape == E.shape[1:]
        and x.shape[0] == E.shape[0]
        and x.shape[2] == E.shape[2]
        and (carried is None or carried.shape == (x.shape[0], 2, x.shape[2]))
    ):
        return None
    if _enabled_ops() is None:
        return None
    y, y_carried = _PlasticLinear.apply(x, weight, alpha, E, carried)
    return y if carried is None else torch.cat([y, y_carried], 1)


def spike_density_limit(limit: Optional[float] = None) -> Optional[float]:
    """The largest fraction of an environment's ``x`` values that may be spikes for :func:`plastic_linear` (and the
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
    """The compiled ops' namespace for :class:`sb3_spikeplastic.snn.layers.PlasticSRMLayer`'s fused interval
    (``srm_interval_forward`` / ``srm_interval_backward``, ``srm_interval.cpp``), or ``None`` when disabled or
    unavailable."""
    return _enabled_ops()


def bernoulli_spikes(p: Tensor, keys: Tensor, index_hash: Tensor) -> Optional[Tensor]:
    """The compiled counter-based sampler for CPU float32/float64 ``p (B, n)``, int32 ``keys (B,)`` and
    ``index_hash (T, n)``, or ``None`` when it does not apply (then use the eager hash). No autograd (spikes are
    samples)."""
    if not (
        cpu_float_operands(p)
        and keys.is_cpu
        and p.dim() == 2
        and keys.dtype is torch.int32
        and keys.shape == p.shape[:1]
        and index_hash.shape[1:] == p.shape[1:]
    ):
        return None
    ops = _enabled_ops()
    if ops is None:
        return None
    with torch.no_grad():
        return ops.bernoulli_spikes(p, keys, index_hash)
