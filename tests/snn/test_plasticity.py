"""Plasticity rules (SPEC §3): one step vs an independent NumPy evaluation of the paper's equations, clipping,
the BCM threshold EMA, the static baseline, gradients through the trace (gradcheck and through spikes), and the
neuromodulation stabiliser (``rule_kwargs=dict(modulation="tanh")``: bounded modulation and finite gradients through
long plastic sequences with the trace at its clip bound)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from sb3_spikeplastic.snn.coding import DiscreteDecoder, RasterInput
from sb3_spikeplastic.snn.layers import PlasticSRMLayer
from sb3_spikeplastic.snn.network import NetworkState, SpikingPlasticNetwork, map_tensors
from sb3_spikeplastic.snn.plasticity import PlasticState, get_rule_class

TRACE_RULES = ["dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"]
ALL_RULES = ["static", *TRACE_RULES]
BCM_RULES = {"dp-bcm", "ndp-bcm"}
NDP_RULES = {"ndp-oja", "ndp-bcm"}
N_IN, N_OUT = 7, 4  # non-square on purpose


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def make_rule(name, n_in=N_IN, n_out=N_OUT, e_max=1.0, seed=0, scale=1.0, dtype=torch.float64, **kw):
    """A rule with random (non-default) parameters, so that every parameter enters the comparison."""
    cls = get_rule_class(name)
    if name in NDP_RULES:
        kw.setdefault("modulation", "linear")  # the paper's form, as numpy_step's default
    rule = cls(n_in, n_out, e_max=e_max, **kw) if cls.has_trace else cls(n_in, n_out)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for pname, p in rule.named_parameters():
            if pname in ("eta_logit", "eta_phi_logit"):
                p.copy_(torch.randn((), generator=g) * scale)
            else:
                p.copy_(torch.randn(p.shape, generator=g) * scale)
    return rule.to(dtype)


def params_np(rule) -> dict:
    return {k: v.detach().numpy().astype(np.float64) for k, v in rule.named_parameters()}


def numpy_step(name, prm, E, phi, r_pre, r_post, e_max, modulation="linear"):
    """The SPEC §3 table evaluated environment by environment with NumPy (returns E', phi')."""
    E_new = np.empty_like(E)
    phi_new = None if phi is None else np.empty_like(phi)
    eta = sigmoid(prm["eta_logit"])
    for b in range(E.shape[0]):
        pre, post, Eb = r_pre[b], r_post[b], E[b]
        if name in NDP_RULES:
            M = prm["w_m"] @ post  # M = W_m r_post
            if modulation == "tanh":
                M = np.tanh(M)
        if name in BCM_RULES:
            eta_phi = sigmoid(prm["eta_phi_logit"])
            r_beta = pre * (pre - (phi[b] + prm["psi"]))  # uses phi BEFORE its update
            phi_new[b] = (1 - eta_phi) * phi[b] + eta_phi * pre
        if name == "dp-linear":
            upd = np.outer(post, pre)
        elif name == "dp-oja":
            upd = np.outer(post - Eb @ pre, pre)
        elif name == "dp-bcm":
            upd = np.outer(post, r_beta)
        elif name == "ndp-oja":
            upd = np.outer(M * post - Eb @ pre, pre)
        elif name == "ndp-bcm":
            upd = np.outer(M * post, r_beta)
        else:
            raise AssertionError(name)
        E_new[b] = np.clip((1 - eta) * Eb + eta * upd, -e_max, e_max)
    return E_new, phi_new


def random_state(rule, B, rng, e_max):
    E = rng.uniform(-0.8 * e_max, 0.8 * e_max, (B, N_OUT, N_IN))
    phi = rng.uniform(0, 1, (B, N_IN)) if rule.name in BCM_RULES else None
    extra = (torch.from_numpy(phi),) if phi is not None else ()
    return E, phi, PlasticState(torch.from_numpy(E), extra)


# ---------------------------------------------------------------------------------------------------------------
# 5. One step == the paper's equation; clipping; EMA; static


@pytest.mark.parametrize("rate_scale,expect_clip", [(0.5, False), (4.0, True)], ids=["small", "clipping"])
@pytest.mark.parametrize("name", TRACE_RULES)
def test_one_step_equals_numpy_equation(name, rate_scale, expect_clip):
    rng = np.random.default_rng(10)
    e_max = 0.5
    rule = make_rule(name, e_max=e_max, seed=1, scale=1.5)
    B = 5
    E, phi, state = random_state(rule, B, rng, e_max)
    r_pre = rng.uniform(0, rate_scale, (B, N_IN))
    r_post = rng.uniform(0, rate_scale, (B, N_OUT))
    new = rule.step(torch.from_numpy(r_pre), torch.from_numpy(r_post), state)
    E_exp, phi_exp = numpy_step(name, params_np(rule), E, phi, r_pre, r_post, e_max)
    np.testing.assert_allclose(new.trace.detach().numpy(), E_exp, rtol=1e-12, atol=1e-12)
    if name in BCM_RULES:
        np.testing.assert_allclose(new.extra[0].detach().numpy(), phi_exp, rtol=1e-12, atol=1e-12)
    else:
        assert new.extra == ()
    at_bound = np.isclose(np.abs(E_exp), e_max, rtol=0, atol=0)
    assert at_bound.any() == expect_clip  # the case exercises (or avoids) the clip as intended


@pytest.mark.parametrize("name", sorted(NDP_RULES))
def test_tanh_modulation_step_equals_numpy_and_is_bounded(name):
    rng = np.random.default_rng(11)
    rule = make_rule(name, seed=2, scale=1.0, modulation="tanh")
    E, phi, state = random_state(rule, 4, rng, 1.0)
    r_pre, r_post = rng.uniform(0, 1, (4, N_IN)), rng.uniform(0, 1, (4, N_OUT))
    new = rule.step(torch.from_numpy(r_pre), torch.from_numpy(r_post), state)
    E_exp, _ = numpy_step(name, params_np(rule), E, phi, r_pre, r_post, 1.0, modulation="tanh")
    np.testing.assert_allclose(new.trace.detach().numpy(), E_exp, rtol=1e-12, atol=1e-12)

    # Bounded: moderate drive stays strictly inside (-1, 1); huge drive never leaves [-1, 1] (float tanh saturates).
    moderate = rule.modulation(torch.from_numpy(rng.uniform(0, 1, (64, N_OUT))))
    assert moderate.abs().max() < 1
    with torch.no_grad():
        rule.w_m.mul_(1e4)
    huge = rule.modulation(torch.from_numpy(rng.uniform(-100, 100, (64, N_OUT))))
    assert torch.isfinite(huge).all() and huge.abs().max() <= 1
    # the linear (paper) form is unbounded
    lin = make_rule(name, seed=2, scale=1.0)
    with torch.no_grad():
        lin.w_m.mul_(100)
    assert lin.modulation(torch.from_numpy(rng.uniform(0, 1, (64, N_OUT)))).abs().max() > 1


@pytest.mark.parametrize("name", TRACE_RULES)
def test_trace_never_leaves_clip_bound_and_phi_follows_ema(name):
    # 500 environments x 20 updates = 10,000 random updates with large rates and parameters.
    rng = np.random.default_rng(12)
    e_max, B, steps = 0.7, 500, 20
    rule = make_rule(name, e_max=e_max, seed=3, scale=3.0, dtype=torch.float32)
    with torch.no_grad():
        rule.eta_logit.fill_(2.0)  # eta = 0.88: aggressive
    state = rule.initial_state(B)
    phi_np = np.zeros((B, N_IN))
    eta_phi = float(torch.sigmoid(rule.eta_phi_logit.detach())) if name in BCM_RULES else None
    ever_clipped = 0
    for _ in range(steps):
        r_pre = rng.uniform(0, 5, (B, N_IN)).astype(np.float32)
        r_post = rng.uniform(0, 5, (B, N_OUT)).astype(np.float32)
        state = rule.step(torch.from_numpy(r_pre), torch.from_numpy(r_post), state)
        E = state.trace.detach()
        assert torch.isfinite(E).all()
        assert E.abs().max() <= e_max
        ever_clipped += int((E.abs() == e_max).sum())
        if name in BCM_RULES:
            phi_np = (1 - eta_phi) * phi_np + eta_phi * r_pre
            np.testing.assert_allclose(state.extra[0].detach().numpy(), phi_np, rtol=1e-5, atol=1e-5)
    assert ever_clipped > 0, "the test did not provoke the clip"


def test_static_rule_has_no_trace():
    rule = get_rule_class("static")(N_IN, N_OUT)
    assert not rule.has_trace
    assert list(rule.parameters()) == []
    state = rule.initial_state(3)
    assert state.trace.numel() == 0 and state.extra == ()
    new = rule.step(torch.rand(3, N_IN), torch.rand(3, N_OUT), state)
    assert new is state
    layer = PlasticSRMLayer(N_IN, N_OUT, rule)
    assert layer.alpha is None and not layer.plastic
    assert torch.equal(layer.efficacy(state.trace), layer.weight)


# ---------------------------------------------------------------------------------------------------------------
# 3. gradcheck of each rule's update (wrt E, r_pre, r_post, phi and the rule's parameters)


class _UpdateFn(nn.Module):
    def __init__(self, rule):
        super().__init__()
        self.rule = rule

    def forward(self, E, r_pre, r_post, *extra):
        new = self.rule.update(r_pre, r_post, PlasticState(E, tuple(extra)))
        return (new.trace, *new.extra)


@pytest.mark.parametrize("name", TRACE_RULES)
def test_rule_update_gradcheck(name):
    rule = make_rule(name, seed=4, scale=0.5)
    fn = _UpdateFn(rule)
    pnames = [f"rule.{n}" for n, _ in rule.named_parameters()]
    g = torch.Generator().manual_seed(5)

    def rnd(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64).requires_grad_()

    E, r_pre, r_post = rnd(3, N_OUT, N_IN), rnd(3, N_IN), rnd(3, N_OUT)
    extra = (rnd(3, N_IN),) if name in BCM_RULES else ()
    params = [p.detach().clone().requires_grad_() for p in rule.parameters()]
    n_state = 3 + len(extra)

    def f(*inputs):
        state_inputs, p = inputs[:n_state], inputs[n_state:]
        return torch.func.functional_call(fn, dict(zip(pnames, p)), state_inputs)

    assert torch.autograd.gradcheck(f, (E, r_pre, r_post, *extra, *params))


# ---------------------------------------------------------------------------------------------------------------
# 6b. Gradients through 3 trace updates equal finite differences


class _Unrolled(nn.Module):
    def __init__(self, rule):
        super().__init__()
        self.rule = rule

    def forward(self, W, alpha, r_pres, r_posts, a, c):
        state = self.rule.initial_state(r_pres.shape[1], torch.float64)
        for k in range(r_pres.shape[0]):
            state = self.rule.step(r_pres[k], r_posts[k], state)
        w_eff = W + alpha * state.trace  # (B, n_out, n_in)
        return (c * (w_eff @ a)).sum()


@pytest.mark.parametrize("name", TRACE_RULES)
def test_gradient_through_three_updates_matches_finite_differences(name):
    rule = make_rule(name, seed=6, scale=0.5)
    fn = _Unrolled(rule)
    pnames = [f"rule.{n}" for n, _ in rule.named_parameters()]
    g = torch.Generator().manual_seed(7)
    B, K = 2, 3
    r_pres = 0.3 * torch.rand(K, B, N_IN, generator=g, dtype=torch.float64)  # small rates: no clipping
    r_posts = 0.3 * torch.rand(K, B, N_OUT, generator=g, dtype=torch.float64)
    a = torch.randn(N_IN, generator=g, dtype=torch.float64)
    c = torch.randn(N_OUT, generator=g, dtype=torch.float64)
    W = torch.randn(N_OUT, N_IN, generator=g, dtype=torch.float64).requires_grad_()
    alpha = (10 + torch.randn(N_OUT, N_IN, generator=g, dtype=torch.float64)).requires_grad_()
    params = [p.detach().clone().requires_grad_() for p in rule.parameters()]

    def f(W, alpha, *p):
        return torch.func.functional_call(fn, dict(zip(pnames, p)), (W, alpha, r_pres, r_posts, a, c))

    # no clipping on this path
    with torch.no_grad():
        st = rule.initial_state(B, torch.float64)
        for k in range(K):
            st = rule.update(r_pres[k], r_posts[k], st)
        assert st.trace.abs().max() < rule.e_max

    assert torch.autograd.gradcheck(f, (W, alpha, *params))
    grads = torch.autograd.grad(f(W, alpha, *params), (W, alpha, *params))
    for pname, gr in zip(["W", "alpha", *pnames], grads):
        assert torch.isfinite(gr).all() and gr.abs().sum() > 0, f"no gradient reaches {pname}"


# ---------------------------------------------------------------------------------------------------------------
# 6a. Gradients reach W, alpha and the rule parameters through the spiking layer over >= 4 intervals


@pytest.mark.parametrize("name", TRACE_RULES)
def test_gradients_reach_all_parameters_through_spiking_layer(name):
    torch.manual_seed(8)
    n_in, n_out, L, n_intervals = 30, 8, 12, 5
    rule = get_rule_class(name)(n_in, n_out)
    layer = PlasticSRMLayer(n_in, n_out, rule, w_init_mean=0.3, w_init_std=1.0, alpha_init_mean=10.0)
    g = torch.Generator().manual_seed(9)
    x = (torch.rand(2, L * n_intervals, n_in, generator=g) < 0.3).float()
    state = layer.initial_state(2)
    for j in range(n_intervals):
        out, state = layer(x[:, j * L : (j + 1) * L], state)
    assert out.spikes.sum() > 0, "output silent: the test would be vacuous"
    weights = torch.randn(out.spikes.shape, generator=g)
    loss = (out.spikes * weights).sum()  # only the last interval's spikes: the rule acts via 4 trace updates
    named = dict(layer.named_parameters())
    expected = {"weight", "alpha", "rule.eta_logit"}
    if name in BCM_RULES:
        expected |= {"rule.eta_phi_logit", "rule.psi"}
    if name in NDP_RULES:
        expected.add("rule.w_m")
    assert expected == set(named)
    grads = torch.autograd.grad(loss, [named[k] for k in sorted(expected)])
    for k, gr in zip(sorted(expected), grads):
        assert torch.isfinite(gr).all(), k
        assert gr.abs().sum() > 0, f"no gradient reaches {k}"


def test_trace_gradient_through_postsynaptic_rate_is_the_surrogate_chain_rule():
    """E depends on W only through r_post (the layer's spikes): with dp-linear from E = 0, one interval of L steps
    gives E = eta r_post (x) r_pre, so for loss = sum(c * E)

        dloss/dW[o, i] = sum_b sum_t (eta / L) (c r_pre_b)[o] rho(u_bo(t)) psp_bi(t),

    with rho the SLAYER surrogate and psp the explicit alpha-kernel convolution of the input (computed here in
    NumPy). Catches a detached or mis-scaled postsynaptic rate, which the checks above would not."""
    torch.manual_seed(12)
    n_in, n_out, L, B = 9, 5, 30, 2
    layer = PlasticSRMLayer(n_in, n_out, get_rule_class("dp-linear")(n_in, n_out), w_init_mean=1.0).double()
    g = torch.Generator().manual_seed(13)
    x = (torch.rand(B, L, n_in, generator=g) < 0.4).double()
    c = torch.randn(n_out, n_in, generator=g, dtype=torch.float64)
    out, state = layer(x, layer.initial_state(B, torch.float64))
    assert out.spikes.sum() > 0
    loss = (c * state.plastic.trace).sum()
    (grad_w,) = torch.autograd.grad(loss, layer.weight)

    p = layer.neuron
    kernel = np.array([(k / p.tau_s) * np.exp(1 - k / p.tau_s) for k in range(L)])
    xs = x.numpy()
    psp = np.zeros_like(xs)
    for t in range(L):
        for k in range(1, t + 1):
            psp[:, t] += kernel[k] * xs[:, t - k]
    u = out.membrane.numpy()
    width = p.tau_rho * p.theta
    rho = (p.scale_rho / width) * np.exp(-np.abs(u - p.theta) / width)
    eta = float(torch.sigmoid(layer.rule.eta_logit.detach()))
    r_pre = xs.mean(1)
    cr = r_pre @ c.numpy().T  # (B, n_out): (c r_pre_b)[o]
    expected = np.einsum("bo,bto,bti->oi", cr, rho, psp) * eta / L
    np.testing.assert_allclose(grad_w.numpy(), expected, rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# The neuromodulation stabiliser: the tanh modulation is the linear one bounded


@pytest.mark.parametrize("rule", ["ndp-oja", "ndp-bcm"])
def test_tanh_modulation_is_bounded_and_linear_is_not(rule):
    torch.manual_seed(0)
    bounded = get_rule_class(rule)(8, 5, modulation="tanh", wm_init_gain=50.0)
    linear = get_rule_class(rule)(8, 5, modulation="linear", wm_init_gain=50.0)
    linear.load_state_dict(bounded.state_dict())
    r_post = torch.rand(4, 5)
    m_bounded, m_linear = bounded.modulation(r_post), linear.modulation(r_post)
    assert m_bounded.abs().max() <= 1.0
    assert m_linear.abs().max() > 1.0
    torch.testing.assert_close(m_bounded, torch.tanh(m_linear))


@pytest.mark.parametrize("rule", ["ndp-oja", "ndp-bcm"])
def test_finite_gradients_over_20_steps_at_the_clip_bound(rule):
    torch.manual_seed(0)
    steps, n_in = 25, 40
    net = SpikingPlasticNetwork(
        RasterInput(steps, n_in),
        DiscreteDecoder(2, 4),
        hidden_sizes=(32,),
        steps=steps,
        rule=rule,
        rule_kwargs=dict(modulation="tanh"),
    )
    state = net.initial_state(4)
    # Start with every trace at ±E_max: the regime where the paper's unbounded rules overflowed.
    layers = tuple(
        s._replace(plastic=PlasticState(torch.randint(0, 2, s.plastic.trace.shape).float() * 2 - 1, s.plastic.extra))
        for s in state.layers
    )
    state = NetworkState(layers, state.noise_key)
    loss = 0.0
    for _ in range(20):
        spikes_in = (torch.rand(4, steps, n_in) < 0.3).float()
        out, state = net(spikes_in, state)
        loss = loss + out.action.pow(2).sum() + sum(r.sum() for r in out.rates)
    loss.backward()
    grads = {name: p.grad for name, p in net.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values()), grads.keys()
    assert sum(g.abs().sum() for g in grads.values()) > 0
    traces = []
    map_tensors(lambda x: traces.append(x) or x, [s.plastic.trace for s in state.layers])
    assert all(t.abs().max() <= 1.0 for t in traces)
