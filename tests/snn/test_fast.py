"""The compiled SRM spike loop (sb3_spikeplastic.snn._fast) against the pure-PyTorch reference loop.

The compiled loop must give *bit-identical* spikes, membrane and state (``torch.equal``), not merely close ones:
a membrane value one ulp off can flip a spike at the threshold and change a whole trajectory.
The first test to need the extension builds it (once, cached on disk; ~10-30 s).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from sb3_spikeplastic.snn import _fast, neurons
from sb3_spikeplastic.snn.neurons import (
    AlphaFilterState,
    SRMParameters,
    SRMSpikeRecursion,
    _decay_and_gain,
    _srm_spike_loop_reference,
    slayer_surrogate,
    srm_spike_loop,
)

PARAMS = [
    SRMParameters(),
    # theta, d and kappa not representable in float32: checks that the constants are rounded as torch does
    SRMParameters(theta=0.7, tau_ref=3.0, scale_ref=1.5, dt=0.5),
]
PARAM_IDS = ["paper", "inexact"]
DTYPES = [torch.float32, torch.float64]


@pytest.fixture
def compiled(compiled_ops):
    """The compiled SRM loop (skips where the ops cannot be built)."""
    return compiled_ops.srm_loop


def constants(p: SRMParameters) -> tuple[float, float]:
    d, c = _decay_and_gain(p.tau_ref, p.dt)
    return d, p.scale_ref * p.theta * c


def random_case(batch, length, n, dtype, p, seed=0):
    g = torch.Generator().manual_seed(seed)
    # drive around the threshold so that spikes are frequent and the refractory feedback matters
    syn = p.theta * (0.3 + 1.5 * torch.rand(batch, length, n, generator=g, dtype=dtype))
    state = AlphaFilterState(
        2 * torch.rand(batch, n, generator=g, dtype=dtype), 3 * torch.rand(batch, n, generator=g, dtype=dtype)
    )
    return syn, state


def fast_loop(syn, state, p):
    d, kappa = constants(p)
    out = _fast.srm_loop(syn, state.h1, state.h2, d, kappa, p.theta)
    assert out is not None, "the compiled path did not apply"
    spikes, membrane, h1, h2 = out
    return spikes, membrane, AlphaFilterState(h1, h2)


def assert_identical(a, b):
    names = ["spikes", "membrane", "h1", "h2"]
    for name, x, y in zip(names, [a[0], a[1], *a[2]], [b[0], b[1], *b[2]]):
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert torch.equal(x, y), f"{name} differs: max |diff| = {(x - y).abs().max().item()}"


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("batch", [1, 8])
@pytest.mark.parametrize("n", [1, 64, 600])
@pytest.mark.parametrize("length", [1, 25, 50])
def test_compiled_equals_reference_bitwise(compiled, dtype, batch, n, length):
    p = PARAMS[0]
    syn, state = random_case(batch, length, n, dtype, p, seed=batch * 1000 + n + length)
    fast = fast_loop(syn, state, p)
    assert_identical(fast, _srm_spike_loop_reference(syn, state, p))
    if batch * n * length > 1000:
        assert 0 < fast[0].mean() < 1


@pytest.mark.parametrize("p", PARAMS, ids=PARAM_IDS)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_carried_state_across_two_calls(compiled, p, dtype):
    syn, state = random_case(8, 50, 64, dtype, p, seed=7)
    f1 = fast_loop(syn[:, :20], state, p)  # non-contiguous slices on purpose
    r1 = _srm_spike_loop_reference(syn[:, :20], state, p)
    assert_identical(f1, r1)
    f2 = fast_loop(syn[:, 20:], f1[2], p)
    r2 = _srm_spike_loop_reference(syn[:, 20:], r1[2], p)
    assert_identical(f2, r2)
    # and splitting the interval changes nothing
    whole = fast_loop(syn, state, p)
    assert_identical((torch.cat([f1[0], f2[0]], 1), torch.cat([f1[1], f2[1]], 1), f2[2]), whole)


def threshold_case(p: SRMParameters, dtype, batch=4, length=30, n=50, seed=3):
    """Synaptic input built step by step so that many membrane values land exactly on ``theta`` (as
    PyTorch rounds it) or one ulp either side, with the refractory feedback active."""
    d, kappa = constants(p)
    g = torch.Generator().manual_seed(seed)
    theta = torch.tensor(p.theta, dtype=dtype)
    syn = p.theta * (0.3 + 1.5 * torch.rand(batch, length, n, generator=g, dtype=dtype))
    pick = torch.randint(0, 4, (batch, length, n), generator=g)  # 0: free, 1: at, 2: just below, 3: just above
    state = AlphaFilterState(torch.zeros(batch, n, dtype=dtype), torch.zeros(batch, n, dtype=dtype))
    for t in range(length):
        r = (state.h2 + state.h1) * d * kappa  # what the recursion subtracts at this step
        target = torch.where(
            pick[:, t] == 2,
            torch.nextafter(theta, torch.tensor(-math.inf, dtype=dtype)),
            torch.where(pick[:, t] == 3, torch.nextafter(theta, torch.tensor(math.inf, dtype=dtype)), theta),
        )
        x = target + r
        for _ in range(8):  # nudge x by ulps until x - r rounds to the target
            u = x - r
            x = torch.where(u < target, torch.nextafter(x, torch.full_like(x, math.inf)), x)
            x = torch.where(u > target, torch.nextafter(x, torch.full_like(x, -math.inf)), x)
        syn[:, t] = torch.where(pick[:, t] > 0, x, syn[:, t])
        _, _, state = _srm_spike_loop_reference(syn[:, t : t + 1], state, p)
    return syn


@pytest.mark.parametrize("p", PARAMS, ids=PARAM_IDS)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_inputs_exactly_at_threshold(compiled, p, dtype):
    syn = threshold_case(p, dtype)
    batch, _, n = syn.shape
    zero = AlphaFilterState(torch.zeros(batch, n, dtype=dtype), torch.zeros(batch, n, dtype=dtype))
    ref = _srm_spike_loop_reference(syn, zero, p)
    theta = torch.tensor(p.theta, dtype=dtype)
    membrane = ref[1]
    # the case is meaningful: many values exactly at theta (spike) and one ulp below (no spike)
    assert (membrane == theta).sum() > 50
    below = torch.nextafter(theta, torch.tensor(-math.inf, dtype=dtype))
    assert (membrane == below).sum() > 50
    assert torch.equal(ref[0], (membrane >= theta).to(dtype))
    assert_identical(fast_loop(syn, zero, p), ref)


def test_srm_spike_loop_dispatches_to_compiled(compiled, monkeypatch):
    p = PARAMS[0]
    syn, state = random_case(2, 10, 5, torch.float32, p)
    expected = _srm_spike_loop_reference(syn, state, p)

    def forbidden(*args, **kwargs):
        raise AssertionError("fallback used although the compiled loop is available")

    monkeypatch.setattr(neurons, "_srm_loop_eager", forbidden)
    assert_identical(srm_spike_loop(syn, state, p), expected)


def test_env_var_forces_fallback(monkeypatch):
    p = PARAMS[0]
    syn, state = random_case(2, 10, 5, torch.float32, p)
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")

    def forbidden():
        raise AssertionError("compiled loop requested although disabled")

    monkeypatch.setattr(_fast, "load_ops", forbidden)
    monkeypatch.setattr(_fast, "_tried", False)
    d, kappa = constants(p)
    assert _fast.srm_loop(syn, state.h1, state.h2, d, kappa, p.theta) is None
    assert_identical(srm_spike_loop(syn, state, p), _srm_spike_loop_reference(syn, state, p))
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "0")
    assert not _fast.compiled_disabled()


def _fresh_process(monkeypatch):
    """The module's state as a new process finds it."""
    monkeypatch.setattr(_fast, "_tried", False)
    monkeypatch.setattr(_fast, "_ops", None)
    monkeypatch.setattr(_fast, "_error", None)


def test_build_failure_warns_once_and_falls_back(monkeypatch, tmp_path):
    monkeypatch.delenv(_fast.NO_COMPILE_ENV, raising=False)
    monkeypatch.setattr(_fast, "build_directory", lambda: tmp_path)  # the record is not written to the real cache
    _fresh_process(monkeypatch)
    attempts = []

    def no_compiler():
        attempts.append(1)
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(_fast, "_build", no_compiler)
    p = PARAMS[0]
    syn, state = random_case(2, 10, 5, torch.float32, p)
    with pytest.warns(RuntimeWarning, match="same results but is slower") as record:
        a = srm_spike_loop(syn, state, p)
        b = srm_spike_loop(syn, state, p)
    assert len([w for w in record if issubclass(w.category, RuntimeWarning)]) == 1
    assert_identical(a, _srm_spike_loop_reference(syn, state, p))
    assert_identical(b, a)

    # The next process on this machine does not try again: one line points to the record.
    _fresh_process(monkeypatch)
    with pytest.warns(RuntimeWarning, match="failed to build on this machine before") as record:
        assert_identical(srm_spike_loop(syn, state, p), a)
    assert len(attempts) == 1 and (tmp_path / _fast.FAILED_BUILD_RECORD).is_file()
    # ...unless a compiler appeared that the record did not see.
    _fresh_process(monkeypatch)
    monkeypatch.setattr(_fast, "_compiler", lambda: "/opt/new/c++")
    with pytest.warns(RuntimeWarning, match="could not build"):
        srm_spike_loop(syn, state, p)
    assert len(attempts) == 2


def test_fallback_for_unsupported_inputs(compiled):
    p = PARAMS[0]
    d, kappa = constants(p)
    syn, state = random_case(2, 10, 5, torch.float32, p)
    # mixed dtypes, half precision and broadcast state are left to the PyTorch loop
    assert _fast.srm_loop(syn, state.h1.double(), state.h2, d, kappa, p.theta) is None
    assert _fast.srm_loop(syn.half(), state.h1.half(), state.h2.half(), d, kappa, p.theta) is None
    assert _fast.srm_loop(syn, state.h1[:1], state.h2[:1], d, kappa, p.theta) is None


def test_outputs_carry_no_autograd(compiled):
    p = PARAMS[0]
    syn, state = random_case(2, 10, 5, torch.float64, p)
    syn.requires_grad_()
    spikes, membrane, new = srm_spike_loop(syn, state, p)
    assert not (spikes.requires_grad or membrane.requires_grad or new.h1.requires_grad or new.h2.requires_grad)
    # the autograd wrapper is unaffected: element-wise surrogate gradient
    spikes, membrane, _, _ = SRMSpikeRecursion.apply(syn, state.h1, state.h2, p)
    upstream = torch.randn_like(spikes)
    (spikes * upstream).sum().backward()
    assert torch.allclose(syn.grad, upstream * slayer_surrogate(membrane.detach(), p), rtol=1e-12, atol=0)


def test_no_compile_at_import():
    code = (
        "import sb3_spikeplastic, sb3_spikeplastic.snn.neurons, sb3_spikeplastic.snn.layers\n"
        "from sb3_spikeplastic.snn import _fast\n"
        "assert not _fast._tried, 'compiled at import'\n"
    )
    env = dict(os.environ)
    env.pop(_fast.NO_COMPILE_ENV, None)
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


@pytest.fixture
def compiled_cuda(compiled_cuda_ops):
    """The CUDA SRM loop (skips without a CUDA device or where it cannot be built)."""
    return compiled_cuda_ops.srm_loop


def to_cuda(syn, state):
    return syn.cuda(), AlphaFilterState(state.h1.cuda(), state.h2.cuda())


def to_cpu(result):
    spikes, membrane, state = result
    return spikes.cpu(), membrane.cpu(), AlphaFilterState(state.h1.cpu(), state.h2.cpu())


@pytest.mark.parametrize("p", PARAMS, ids=PARAM_IDS)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 50, 129), (64, 50, 600), (2, 7, 1000)])
def test_cuda_kernel_is_bit_identical_to_eager_cuda(compiled_cuda, p, dtype, shape):
    """The CUDA kernel against the eager loop on the same GPU (odd sizes: partial blocks, one neuron)."""
    syn, state = to_cuda(*random_case(*shape, dtype, p, seed=sum(shape)))
    d, kappa = constants(p)
    out = compiled_cuda(syn, state.h1, state.h2, d, kappa, p.theta)
    spikes, membrane, ref_state = _srm_spike_loop_reference(syn, state, p)
    assert out[0].is_cuda
    if out[0].numel() > 100:
        assert 0 < out[0].mean() < 1  # spikes and silence both occur
    assert_identical((out[0], out[1], AlphaFilterState(out[2], out[3])), (spikes, membrane, ref_state))


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_cuda_matches_cpu(compiled_cuda, dtype):
    """CUDA kernel, CPU compiled loop and CPU eager loop all agree bit for bit (no contracted multiply-adds)."""
    p = PARAMS[1]
    syn, state = random_case(8, 50, 64, dtype, p, seed=11)
    cpu = srm_spike_loop(syn, state, p)
    gpu = srm_spike_loop(*to_cuda(syn, state), p)
    assert gpu[0].device.type == "cuda"
    assert_identical(to_cpu(gpu), cpu)


def test_cuda_env_var_and_build_failure_fall_back(monkeypatch):
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    p = PARAMS[0]
    syn, state = to_cuda(*random_case(4, 20, 33, torch.float32, p, seed=5))
    reference = _srm_spike_loop_reference(syn, state, p)
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    d, kappa = constants(p)
    assert _fast.srm_loop(syn, state.h1, state.h2, d, kappa, p.theta) is None
    monkeypatch.delenv(_fast.NO_COMPILE_ENV)
    monkeypatch.setattr(_fast, "_cuda_tried", False)
    monkeypatch.setattr(_fast, "_cuda_ops", None)

    def no_nvcc():
        raise RuntimeError("nvcc not found")

    monkeypatch.setattr(_fast, "_build_cuda", no_nvcc)
    with pytest.warns(RuntimeWarning, match="CUDA spike loop.*same results but is slower") as record:
        a = srm_spike_loop(syn, state, p)
        b = srm_spike_loop(syn, state, p)
    assert len([w for w in record if issubclass(w.category, RuntimeWarning)]) == 1
    assert_identical(a, reference)
    assert_identical(b, reference)


def test_numpy_oracle_float32():
    """Independent of both implementations: the recursion in numpy float32, one rounding per operation."""
    p = PARAMS[1]
    syn, state = random_case(3, 40, 17, torch.float32, p, seed=5)
    d, kappa = (np.float32(x) for x in constants(p))
    theta = np.float32(p.theta)
    x, h1, h2 = syn.numpy(), state.h1.numpy().copy(), state.h2.numpy().copy()
    spikes, membrane = np.empty_like(x), np.empty_like(x)
    for t in range(x.shape[1]):
        h2 = (h2 + h1) * d
        u = x[:, t] - h2 * kappa
        s = (u >= theta).astype(np.float32)
        h1 = h1 * d + s
        spikes[:, t], membrane[:, t] = s, u
    # srm_spike_loop runs the compiled loop where available: both implementations must match the oracle
    for out in (srm_spike_loop(syn, state, p), _srm_spike_loop_reference(syn, state, p)):
        np.testing.assert_array_equal(out[0].numpy(), spikes)
        np.testing.assert_array_equal(out[1].numpy(), membrane)
        np.testing.assert_array_equal(out[2].h1.numpy(), h1)
        np.testing.assert_array_equal(out[2].h2.numpy(), h2)


def test_stale_build_lock_is_removed(tmp_path):
    lock = tmp_path / "lock"
    lock.touch()
    _fast._clear_stale_lock(tmp_path)  # fresh: another process may be compiling
    assert lock.exists()
    old = lock.stat().st_mtime - 3600
    os.utime(lock, (old, old))
    with pytest.warns(RuntimeWarning, match="stale build lock"):
        _fast._clear_stale_lock(tmp_path)
    assert not lock.exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_allocator_settings_take_effect_on_glibc():
    import platform

    from sb3_spikeplastic.snn.cpu_settings import keep_freed_memory

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_freed_memory() is True


_BLOCK_CACHE_CHECK = """
import torch
from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.cpu_settings import block_cache_active, cache_freed_blocks, release_block_cache
ops = _fast.load_ops()
assert ops is not None, _fast.build_error()
assert ops.cpu_block_cache_bytes() == 0 and not block_cache_active()
early = torch.empty(2**18)  # allocated before: freed through the allocator it came from
assert cache_freed_blocks(min_bytes=2**16, max_cached_bytes=3 * 2**20) and not cache_freed_blocks()
assert block_cache_active()
a = torch.ones(2**18)  # 1 MiB
address = a.data_ptr()
del a, early
assert ops.cpu_block_cache_bytes() == 2**20
b = torch.empty(2**18)  # the same size: the same block, taken out of the cache
assert b.data_ptr() == address and ops.cpu_block_cache_bytes() == 0
c, d = torch.empty(2**19), torch.empty(2**19)  # 2 MiB each: the second one freed would pass the 3 MiB cap
del b, c, d
assert ops.cpu_block_cache_bytes() == 3 * 2**20, ops.cpu_block_cache_bytes()
small = torch.empty(100)  # under min_bytes: not cached
del small
assert ops.cpu_block_cache_bytes() == 3 * 2**20
kept = torch.empty(2**18)  # allocated through the cache, freed after it is released
assert release_block_cache() and not block_cache_active() and not release_block_cache()
assert ops.cpu_block_cache_bytes() == 0  # the cached blocks went back
del kept
assert ops.cpu_block_cache_bytes() == 0  # and so do the cache's blocks freed later
e = torch.empty(2**18)
del e
assert ops.cpu_block_cache_bytes() == 0  # torch's own allocator again
assert cache_freed_blocks(min_bytes=2**16, max_cached_bytes=3 * 2**20)  # installed again
f = torch.empty(2**18)
del f
assert ops.cpu_block_cache_bytes() == 2**20
"""

_BLOCK_CACHE_TRAINING = """
import hashlib, sys, torch
from stable_baselines3.common.callbacks import BaseCallback
from sb3_spikeplastic import PPO
from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.cpu_settings import block_cache_active
torch.set_num_threads(1)
cache = sys.argv[1] == "cache"
model = PPO("SpikePlasticPolicy", "TMazeCue-v0", n_steps=64, batch_size=64, bptt_steps=16, n_epochs=2, seed=3,
            policy_kwargs=dict(rule="ndp-oja", hidden_sizes=(128, 128)),  # traces of 64 KB per environment
            keep_freed_memory=cache, device="cpu")  # the block cache is the CPU allocator's


class Seen(BaseCallback):
    active = []

    def _on_step(self):
        return True

    def _on_rollout_end(self):
        self.active.append(block_cache_active())


model.learn(128, callback=Seen())
digest = hashlib.sha256()
for tensor in model.policy.state_dict().values():
    digest.update(tensor.numpy().tobytes())
assert Seen.active == [cache, cache] and not block_cache_active(), Seen.active
print(digest.hexdigest())
"""


def _run_python(code: str, *args: str) -> str:
    env = dict(os.environ)
    env.pop(_fast.NO_COMPILE_ENV, None)
    result = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout.strip().splitlines()[-1] if result.stdout.strip() else ""


def test_block_cache_hands_a_freed_block_back_by_its_size(compiled):
    """In a process of its own (the allocator is process-wide): a freed block of at least ``min_bytes`` is kept,
    the next allocation of its size gets it back, and the cap and the minimum size hold."""
    _run_python(_BLOCK_CACHE_CHECK)


def test_training_with_the_block_cache_is_bit_identical(compiled):
    """A reused block holds the values of its last tensor where a fresh one may not: training must read no
    memory before writing it. Two short ndp-oja runs, with and without the cache, end with the same parameters."""
    assert _run_python(_BLOCK_CACHE_TRAINING, "cache") == _run_python(_BLOCK_CACHE_TRAINING, "plain")


def test_build_directory_depends_on_the_sources(monkeypatch, tmp_path):
    """Each version of the C++/CUDA sources builds in its own cache directory (two installed versions sharing a
    cache must not rebuild over each other's library)."""
    monkeypatch.delenv(_fast.BUILD_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    source = tmp_path / "srm_loop.cpp"
    source.write_text("// version 1\n")
    monkeypatch.setattr(_fast, "_SOURCES", [source])
    first = _fast.build_directory()
    assert first == _fast.build_directory() and first.parent == tmp_path / "sb3_spikeplastic"
    source.write_text("// version 2\n")
    assert _fast.build_directory() != first
    monkeypatch.setenv(_fast.BUILD_DIR_ENV, str(tmp_path / "explicit"))
    assert _fast.build_directory() == tmp_path / "explicit"


def test_checkouts_of_the_same_sources_share_one_build(monkeypatch, tmp_path):
    """The build compiles copies of the sources kept in its folder: two checkouts of one version hand the build
    the same paths (a changed path would make ninja rebuild), and an unchanged copy is not rewritten."""
    monkeypatch.setattr(_fast, "_HEADERS", [])
    build = tmp_path / "build"
    checkouts = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        checkouts.append(tmp_path / name / "srm_loop.cpp")
        checkouts[-1].write_text("// one version\n")
    first = _fast._sources_in(build, [checkouts[0]])
    stamp = first[0].stat().st_mtime_ns
    second = _fast._sources_in(build, [checkouts[1]])
    assert first == second == [build / "src" / "srm_loop.cpp"]
    assert second[0].stat().st_mtime_ns == stamp
    checkouts[1].write_text("// edited\n")
    assert _fast._sources_in(build, [checkouts[1]])[0].read_text() == "// edited\n"


def test_compiling_says_so_once_on_stderr(monkeypatch, tmp_path, capsys):
    from torch.utils import cpp_extension

    monkeypatch.setattr(_fast, "_HEADERS", [])
    monkeypatch.setattr(cpp_extension, "load", lambda **kwargs: None)
    source = tmp_path / "srm_loop.cpp"
    source.write_text("// a version\n")
    _fast._compile("ext", [source], tmp_path / "build")
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sb3_spikeplastic: compiling ext once into")
    (tmp_path / "build" / "ext.so").write_bytes(b"")  # built: later processes load it quietly
    _fast._compile("ext", [source], tmp_path / "build")
    assert capsys.readouterr().err == ""
