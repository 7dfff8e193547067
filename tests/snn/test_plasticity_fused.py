"""The compiled plasticity ops against the eager ones: the fused trace update (``_fast.trace_step``, used by every
built-in rule's ``step``), the plastic layer's product (``plastic_linear``) and the sparse spike products.

For the trace update, forward values and all four gradients (E, post, pre, eta) are compared with the eager
``hebbian_update(...).clamp`` on traces where about half the synapses are at the clip bound, and the op is
gradchecked in float64. The rules themselves are checked against NumPy in ``test_plasticity.py``.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.plasticity import (
    HebbianTerms,
    PlasticState,
    dp_bcm_update,
    dp_linear_update,
    dp_oja_update,
    get_rule_class,
    hebbian_trace_step,
    hebbian_update,
    ndp_bcm_update,
    ndp_oja_update,
)

TOL = {torch.float32: dict(rtol=1e-5, atol=1e-6), torch.float64: dict(rtol=1e-12, atol=1e-12)}


def case(dtype, B=3, n_out=5, n_in=9, seed=0, scale=3.0):
    g = torch.Generator().manual_seed(seed)
    E = (torch.rand(B, n_out, n_in, generator=g, dtype=dtype) * 1.6 - 0.8).requires_grad_()
    post = (scale * torch.rand(B, n_out, generator=g, dtype=dtype) - 1).requires_grad_()
    pre = (scale * torch.rand(B, n_in, generator=g, dtype=dtype)).requires_grad_()
    eta = torch.tensor(0.3, dtype=dtype).requires_grad_()
    upstream = torch.randn(B, n_out, n_in, generator=g, dtype=dtype)
    return E, post, pre, eta, upstream


@pytest.mark.parametrize("oja", [False, True], ids=["hebb", "oja"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_fused_equals_eager_values_and_gradients(compiled_ops, dtype, oja):
    E, post, pre, eta, upstream = case(dtype)
    e_max = 0.5
    out = _fast.trace_step(E, post, pre, eta, e_max, oja)
    ref = hebbian_update(E, eta, HebbianTerms(post, pre, oja)).clamp(-e_max, e_max)
    clipped = (ref.abs() == e_max).float().mean()
    assert 0.2 < clipped < 0.8, "the case must exercise both sides of the clip"
    torch.testing.assert_close(out, ref, **TOL[dtype])
    inputs = (E, post, pre, eta)
    got = torch.autograd.grad((out * upstream).sum(), inputs)
    want = torch.autograd.grad((ref * upstream).sum(), inputs)
    for name, a, b in zip(("E", "post", "pre", "eta"), got, want):
        assert a.shape == b.shape, name
        torch.testing.assert_close(a, b, **TOL[dtype], msg=lambda m, name=name: f"d/d{name}: {m}")


@pytest.mark.parametrize("oja", [False, True], ids=["hebb", "oja"])
def test_fused_gradcheck(compiled_ops, oja):
    E, post, pre, eta, _ = case(torch.float64, scale=0.5)  # keep x off the clip's kinks
    assert torch.autograd.gradcheck(lambda *a: _fast.trace_step(*a, 0.9, oja), (E, post, pre, eta))


@pytest.mark.parametrize("name", ["dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"])
def test_rule_step_fused_equals_eager_update_and_paper_function(compiled_ops, monkeypatch, name):
    """``step`` (fused) == ``update`` + clamp (eager) == the paper's pure function, values and gradients."""
    torch.manual_seed(3)
    rule = get_rule_class(name)(7, 4, e_max=0.3, eta_init=0.5).double()
    g = torch.Generator().manual_seed(4)
    E = (0.6 * torch.rand(2, 4, 7, generator=g, dtype=torch.float64) - 0.3).requires_grad_()
    r_pre = 2 * torch.rand(2, 7, generator=g, dtype=torch.float64)
    r_post = 2 * torch.rand(2, 4, generator=g, dtype=torch.float64)
    extra = (torch.rand(2, 7, generator=g, dtype=torch.float64),) if "bcm" in name else ()
    state = PlasticState(E, extra)

    step = rule.step(r_pre, r_post, state).trace
    eager = rule.update(r_pre, r_post, state).trace
    eta = rule.eta
    if "bcm" in name:
        r_beta = rule.presynaptic(r_pre, state)[0]
    m = rule.modulation(r_post)
    paper = {
        "dp-linear": lambda: dp_linear_update(E, r_pre, r_post, eta),
        "dp-oja": lambda: dp_oja_update(E, r_pre, r_post, eta),
        "dp-bcm": lambda: dp_bcm_update(E, r_beta, r_post, eta),
        "ndp-oja": lambda: ndp_oja_update(E, r_pre, r_post, m, eta),
        "ndp-bcm": lambda: ndp_bcm_update(E, r_beta, r_post, m, eta),
    }[name]()
    torch.testing.assert_close(eager, paper, rtol=1e-14, atol=1e-15)
    torch.testing.assert_close(step, eager.clamp(-0.3, 0.3), rtol=1e-12, atol=1e-12)
    assert (step.abs() == 0.3).any(), "the case must reach the clip"
    params = [E, *rule.parameters()]
    upstream = torch.randn(step.shape, generator=g, dtype=torch.float64)
    # (eta_phi only enters phi', not E')
    got = torch.autograd.grad((step * upstream).sum(), params, allow_unused=True)
    want = torch.autograd.grad((eager.clamp(-0.3, 0.3) * upstream).sum(), params, allow_unused=True)
    for a, b in zip(got, want):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_hebbian_trace_step_falls_back_when_disabled(monkeypatch):
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    E, post, pre, eta, _ = case(torch.float32)
    assert _fast.trace_step(E, post, pre, eta, 0.5, True) is None
    out = hebbian_trace_step(E, eta, HebbianTerms(post, pre, True), 0.5)
    torch.testing.assert_close(
        out, hebbian_update(E, eta, HebbianTerms(post, pre, True)).clamp(-0.5, 0.5), rtol=0, atol=0
    )


def test_unsupported_inputs_are_left_to_eager(compiled_ops):
    E, post, pre, eta, _ = case(torch.float32)
    assert _fast.trace_step(E.double(), post, pre, eta, 0.5, True) is None  # mixed dtypes
    assert _fast.trace_step(E.half(), post.half(), pre.half(), eta.half(), 0.5, True) is None
    assert _fast.trace_step(E, post[:1], pre, eta, 0.5, True) is None  # shapes that would broadcast
    assert _fast.trace_step(E, post, pre, eta.expand(2), 0.5, True) is None  # eta not a single value


@pytest.mark.parametrize("x_grad", [True, False], ids=["x-grad", "no-x-grad"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_fused_plastic_linear_equals_eager(compiled_ops, dtype, x_grad):
    """``x[b] (W + alpha * E[b])^T`` and its four gradients against ``addcmul`` + ``matmul``; without a
    gradient for ``x`` (the input layer's spikes) none is computed."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 7, 9, generator=g, dtype=dtype).requires_grad_(x_grad)
    W = torch.randn(5, 9, generator=g, dtype=dtype).requires_grad_()
    alpha = torch.randn(5, 9, generator=g, dtype=dtype).requires_grad_()
    E = torch.randn(3, 5, 9, generator=g, dtype=dtype).requires_grad_()
    upstream = torch.randn(3, 7, 5, generator=g, dtype=dtype)
    out, ref = _fast.plastic_linear(x, W, alpha, E), x @ torch.addcmul(W, alpha, E).transpose(1, 2)
    torch.testing.assert_close(out, ref, **TOL[dtype])
    inputs = (x, W, alpha, E) if x_grad else (W, alpha, E)
    for a, b in zip(
        torch.autograd.grad((out * upstream).sum(), inputs), torch.autograd.grad((ref * upstream).sum(), inputs)
    ):
        torch.testing.assert_close(a, b, **TOL[dtype])
    if dtype is torch.float64 and x_grad:
        assert torch.autograd.gradcheck(_fast.plastic_linear, (x, W, alpha, E))
    assert _fast.plastic_linear(x, W, alpha, E.float() if dtype is torch.float64 else E.double()) is None
    assert _fast.plastic_linear(x[:1], W, alpha, E) is None  # a batch that would broadcast


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_fused_plastic_linear_one_environment_per_block(compiled_ops, dtype):
    """At the paper network's sizes (600 -> 64) a block holds one environment, whose products call BLAS directly
    (where torch's MKL exports it; the input gradient runs small_gemm.h's kernel where the CPU has FMA): the output
    and its four gradients equal the eager ops, for both layouts of the product (64 -> 600 too). The input
    gradient's 600-term float32 sums run in another order than BLAS's (see the next test)."""
    g = torch.Generator().manual_seed(4)
    for n_in, n_out in ((600, 64), (64, 600)):
        x = (torch.rand(3, 11, n_in, generator=g) < 0.2).to(dtype).requires_grad_()
        W, alpha = (0.1 * torch.randn(n_out, n_in, generator=g, dtype=dtype) for _ in range(2))
        W, alpha = W.requires_grad_(), alpha.requires_grad_()
        E = torch.randn(3, n_out, n_in, generator=g, dtype=dtype).requires_grad_()
        upstream = torch.randn(3, 11, n_out, generator=g, dtype=dtype)
        out, ref = _fast.plastic_linear(x, W, alpha, E), x @ torch.addcmul(W, alpha, E).transpose(1, 2)
        torch.testing.assert_close(out, ref, **TOL[dtype])
        grads = zip(
            torch.autograd.grad((out * upstream).sum(), (x, W, alpha, E)),
            torch.autograd.grad((ref * upstream).sum(), (x, W, alpha, E)),
        )
        for k, (a, b) in enumerate(grads):
            tol = dict(TOL[dtype])
            if k == 0 and dtype is torch.float32:
                tol["atol"] = 2e-6 * float(b.abs().max())
            torch.testing.assert_close(a, b, **tol)


@pytest.mark.parametrize("rows", [1, 5, 6, 11, 50])
@pytest.mark.parametrize("n_in", [64, 128, 72], ids=["kernel", "kernel-128", "blas"])
def test_input_gradient_of_one_environment_per_block(compiled_ops, rows, n_in):
    """The input gradient ``dY (W + alpha * E[b])`` of a block of one float32 environment (a 600-output layer):
    small_gemm.h's register tiles (6 rows at a time, then the remaining 1-5; ``n_in`` a multiple of 16) or BLAS
    (other ``n_in``), against the same product in float64. Its error stays within float32 rounding of the
    600-term sums: at most 4 times BLAS's own and 2e-6 of the largest value."""
    g = torch.Generator().manual_seed(rows * 1000 + n_in)
    n_out = 600
    x = (torch.rand(2, rows, n_in, generator=g) < 0.2).float().requires_grad_()
    W, alpha = (0.1 * torch.randn(n_out, n_in, generator=g) for _ in range(2))
    E = torch.randn(2, n_out, n_in, generator=g)
    upstream = torch.randn(2, rows, n_out, generator=g)
    (d_x,) = torch.autograd.grad((_fast.plastic_linear(x, W, alpha, E) * upstream).sum(), (x,))
    eff = torch.addcmul(W, alpha, E)
    exact = upstream.double() @ eff.double()
    blas_error = float((upstream @ eff - exact).abs().max())
    error = float((d_x.double() - exact).abs().max())
    assert error <= max(4 * blas_error, 2e-6 * float(exact.abs().max())), (error, blas_error)
    assert error <= 2e-6 * float(exact.abs().max())


@pytest.mark.parametrize("n_in, n_out", [(9, 5), (600, 64)], ids=["blocks", "one-environment-per-block"])
@pytest.mark.parametrize("rows_grad", [True, False], ids=["rows-grad", "no-rows-grad"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_fused_plastic_linear_with_carried_rows(compiled_ops, dtype, rows_grad, n_in, n_out):
    """Rows carried beside ``x`` (a layer's PSP state), multiplied in the pass that builds the efficacy: the product
    of ``[x; carried]`` and its five gradients against the eager ops on the concatenated rows, with and without
    gradients for the rows; the carried rows' part of the weight gradients is not lost when their products get no
    gradient."""
    g = torch.Generator().manual_seed(5)
    x = (torch.rand(3, 7, n_in, generator=g) < 0.3).to(dtype).requires_grad_(rows_grad)
    carried = torch.randn(3, 2, n_in, generator=g, dtype=dtype).requires_grad_(rows_grad)
    W, alpha = (0.3 * torch.randn(n_out, n_in, generator=g, dtype=dtype) for _ in range(2))
    W, alpha = W.requires_grad_(), alpha.requires_grad_()
    E = torch.randn(3, n_out, n_in, generator=g, dtype=dtype).requires_grad_()
    upstream = torch.randn(3, 9, n_out, generator=g, dtype=dtype)
    out = _fast.plastic_linear(x, W, alpha, E, carried)
    ref = torch.cat([x, carried], 1) @ torch.addcmul(W, alpha, E).transpose(1, 2)

    def assert_close(a, b):  # sums of up to 600 terms in float32: tolerances scaled by the largest value
        tol = TOL[dtype]
        torch.testing.assert_close(a, b, rtol=tol["rtol"], atol=tol["atol"] * max(1.0, float(b.abs().max())))

    assert_close(out, ref)
    inputs = (x, carried, W, alpha, E) if rows_grad else (W, alpha, E)
    for a, b in zip(
        torch.autograd.grad((out * upstream).sum(), inputs), torch.autograd.grad((ref * upstream).sum(), inputs)
    ):
        assert_close(a, b)
    out = _fast.plastic_linear(x, W, alpha, E, carried)
    ref = torch.cat([x, carried], 1) @ torch.addcmul(W, alpha, E).transpose(1, 2)
    spikes_only = (out[:, :7] * upstream[:, :7]).sum()  # the carried rows' products get no gradient
    for a, b in zip(
        torch.autograd.grad(spikes_only, inputs), torch.autograd.grad((ref[:, :7] * upstream[:, :7]).sum(), inputs)
    ):
        assert_close(a, b)
    if dtype is torch.float64 and rows_grad and n_in < 100:
        assert torch.autograd.gradcheck(lambda *t: _fast.plastic_linear(*t), (x, W, alpha, E, carried))


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_plastic_linear_splits_environments_between_threads(compiled_ops, threads):
    """Environments big enough to be split between threads (each thread sums its own dW and dalpha): values and
    gradients equal the eager ops for any thread count, and ``x``'s gradient comes out even though the pool's
    threads start with autograd on."""
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(5, 16, 256, generator=g, dtype=torch.float64) < 0.2).double().requires_grad_()
    W, alpha = (torch.randn(64, 256, generator=g, dtype=torch.float64).requires_grad_() for _ in range(2))
    E = torch.randn(5, 64, 256, generator=g, dtype=torch.float64).requires_grad_()
    upstream = torch.randn(5, 16, 64, generator=g, dtype=torch.float64)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        out = _fast.plastic_linear(x, W, alpha, E)
        grads = torch.autograd.grad((out * upstream).sum(), (x, W, alpha, E))
    finally:
        torch.set_num_threads(before)
    ref = x @ torch.addcmul(W, alpha, E).transpose(1, 2)
    torch.testing.assert_close(out, ref, **TOL[torch.float64])
    for a, b in zip(grads, torch.autograd.grad((ref * upstream).sum(), (x, W, alpha, E))):
        torch.testing.assert_close(a, b, **TOL[torch.float64])


@pytest.mark.parametrize("rule", ["dp-oja", "ndp-bcm"])
def test_network_gradients_with_and_without_compiled_ops(compiled_ops, monkeypatch, rule):
    """A 4-step BPTT sequence through a 2-layer plastic network (float64, so that no spike flips on rounding):
    every parameter's gradient agrees between the compiled path and pure PyTorch."""
    from sb3_spikeplastic.snn.coding import DiscreteDecoder, RasterInput
    from sb3_spikeplastic.snn.network import SpikingPlasticNetwork

    torch.manual_seed(0)
    steps, n_in = 20, 30
    net = SpikingPlasticNetwork(
        RasterInput(steps, n_in),
        DiscreteDecoder(2, 4),
        hidden_sizes=(16,),
        steps=steps,
        rule=rule,
        plastic_layers=(0, 1),
    ).double()
    g = torch.Generator().manual_seed(2)
    raster = (torch.rand(4, 3, steps, n_in, generator=g) < 0.3).double()

    def gradients():
        state = net.initial_state(3, dtype=torch.float64)
        loss = 0.0
        for k in range(4):
            out, state = net(raster[k], state)
            loss = loss + out.action.pow(2).sum() + sum(r.sum() for r in out.rates)
        return torch.autograd.grad(loss, list(net.parameters()), allow_unused=True)

    compiled = gradients()
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    eager = gradients()
    assert sum(float(a.abs().sum()) for a in compiled if a is not None) > 0
    for (name, _), a, b in zip(net.named_parameters(), compiled, eager):
        assert (a is None) == (b is None), name
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12, msg=lambda m, name=name: f"{name}: {m}")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_uses_eager_and_matches_cpu(compiled_ops):
    E, post, pre, eta, _ = case(torch.float32)
    terms = HebbianTerms(post.cuda(), pre.cuda(), True)
    gpu = hebbian_trace_step(E.cuda(), eta.cuda(), terms, 0.5)
    cpu = hebbian_trace_step(E, eta, HebbianTerms(post, pre, True), 0.5)
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-6)


def test_user_rule_with_hebbian_terms_runs_the_fused_update(compiled_ops, monkeypatch):
    from sb3_spikeplastic.snn.plasticity import PlasticityRule

    class Covariance(PlasticityRule):
        def hebbian_terms(self, r_pre, r_post, state):
            return HebbianTerms(r_post - r_post.mean(-1, keepdim=True), r_pre, False)

    rule = Covariance(6, 3, e_max=0.2).double()
    calls = []
    kernel = _fast.TRACE_STEP
    monkeypatch.setattr(_fast, "TRACE_STEP", kernel._replace(run=lambda *a: calls.append(1) or kernel.run(*a)))
    g = torch.Generator().manual_seed(5)
    state = PlasticState(0.4 * torch.rand(2, 3, 6, generator=g, dtype=torch.float64) - 0.2)
    r_pre, r_post = (
        torch.rand(2, 6, generator=g, dtype=torch.float64),
        torch.rand(2, 3, generator=g, dtype=torch.float64),
    )
    stepped = rule.step(r_pre, r_post, state).trace
    assert calls == [1]
    torch.testing.assert_close(
        stepped, rule.update(r_pre, r_post, state).trace.clamp(-0.2, 0.2), rtol=1e-12, atol=1e-12
    )


def test_pool_threads_follow_the_callers_flush_denormal_mode(compiled_ops):
    """Products whose sums are subnormal floats: after ``torch.set_flush_denormal(True)`` every environment's
    result is 0, whichever thread computed it (the pool's threads are started before the mode is set). In a
    subprocess: the mode and the pool are process-wide."""
    code = """
import torch
from sb3_spikeplastic.snn import _fast
torch.set_num_threads(2)
x = torch.full((4, 16, 256), 1e-21)
W, alpha, E = torch.full((64, 256), 1e-21), torch.zeros(64, 256), torch.zeros(4, 64, 256)
kept = bool((_fast.plastic_linear(x, W, alpha, E) > 0).all())  # also starts the pool's threads
torch.set_flush_denormal(True)
print(kept, bool((_fast.plastic_linear(x, W, alpha, E) == 0).all()))
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["True", "True"]


@pytest.fixture
def spike_limit(compiled_ops):
    """Sets the spike products' density limit for one test and restores it."""
    before = _fast.spike_density_limit()
    yield _fast.spike_density_limit
    _fast.spike_density_limit(before)


@pytest.mark.parametrize(
    "n_in, n_out, length", [(600, 64, 50), (603, 72, 3), (2000, 40, 1)], ids=["paper-input-layer", "ragged", "narrow"]
)
@pytest.mark.parametrize("density", [0.0, 0.05, 0.15])
@pytest.mark.parametrize("carry", [False, True], ids=["spikes", "carried-rows"])
def test_spike_products_equal_dense_products(spike_limit, n_in, n_out, length, density, carry):
    """Binary float32 ``x`` taken through the spike products (firing inputs' columns added up; forward and the
    efficacy's gradient): values and all gradients agree with the dense path and with the product in float64, and
    every environment, forward and backward, is counted on the spike path."""
    g = torch.Generator().manual_seed(7)
    B = 3
    x = (torch.rand(B, length, n_in, generator=g) < density).float()
    carried = torch.randn(B, 2, n_in, generator=g) if carry else None
    W, alpha = (0.3 * torch.randn(n_out, n_in, generator=g) for _ in range(2))
    E = torch.randn(B, n_out, n_in, generator=g)
    upstream = torch.randn(B, length + (2 if carry else 0), n_out, generator=g)

    def run(limit):
        spike_limit(limit)
        params = [t.clone().requires_grad_() for t in (W, alpha, E)]
        out = _fast.plastic_linear(x, *params, carried)
        return out, torch.autograd.grad((out * upstream).sum(), params)

    before = _fast.spike_product_counts()
    out, grads = run(1.0)
    after = _fast.spike_product_counts()
    assert (after[0] - before[0], after[1] - before[1]) == (2 * B, 0)
    dense_out, dense_grads = run(0.0)
    assert _fast.spike_product_counts() == after  # limit 0: the spikes are not even looked at
    exact = [t.double().requires_grad_() for t in (W, alpha, E)]
    rows = x.double() if carried is None else torch.cat([x, carried], 1).double()
    ref = rows @ torch.addcmul(exact[0], exact[1], exact[2]).transpose(1, 2)
    ref_grads = torch.autograd.grad((ref * upstream.double()).sum(), exact)
    for a, b, r in zip((out, *grads), (dense_out, *dense_grads), (ref, *ref_grads)):
        scale = max(1.0, float(r.abs().max()))
        torch.testing.assert_close(a.double(), r.detach(), rtol=1e-5, atol=1e-5 * scale)
        torch.testing.assert_close(b.double(), r.detach(), rtol=1e-5, atol=1e-5 * scale)


def test_spike_products_only_for_sparse_binary_float32(spike_limit):
    """The dense product is kept for values other than 0 and 1 (a NaN spreads as it does there), for more spikes
    than the limit allows, for float64 and for blocks of several environments; an out-of-range limit is refused."""
    g = torch.Generator().manual_seed(8)
    W, alpha = torch.randn(64, 600, generator=g), torch.randn(64, 600, generator=g)
    E = torch.randn(2, 64, 600, generator=g)
    sparse = (torch.rand(2, 10, 600, generator=g) < 0.1).float()
    spike_limit(0.2)

    def counted(x, w=W, a=alpha, e=E):
        before = _fast.spike_product_counts()
        out = _fast.plastic_linear(x, w, a, e)
        after = _fast.spike_product_counts()
        return out, (after[0] - before[0], after[1] - before[1])

    assert counted(sparse)[1] == (2, 0)
    half = sparse.clone()
    half[1, 3, 5] = 0.5
    out, counts = counted(half)
    assert counts == (1, 1)
    torch.testing.assert_close(out, half @ torch.addcmul(W, alpha, E).transpose(1, 2), rtol=1e-5, atol=1e-4)
    nan = sparse.clone()
    nan[0, 0, 599] = float("nan")
    out, counts = counted(nan)
    assert counts == (1, 1) and torch.isnan(out[0, 0]).all() and not torch.isnan(out[1]).any()
    dense = (torch.rand(2, 10, 600, generator=g) < 0.5).float()
    assert counted(dense)[1] == (0, 2)
    assert counted(sparse.double(), W.double(), alpha.double(), E.double())[1] == (0, 0)
    small = (torch.rand(2, 10, 16, generator=g) < 0.1).float()  # 16 -> 8: blocks of both environments
    assert counted(small, W[:8, :16], alpha[:8, :16], E[:, :8, :16])[1] == (0, 0)
    with pytest.raises(ValueError, match="limit=1.5"):
        spike_limit(1.5)
