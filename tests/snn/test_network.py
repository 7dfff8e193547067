"""The plastic SNN (SPEC §2–§4): default-initialisation activity and gradients, episode resets, the rule
registry, plasticity intervals, sequences, and every available device against the pure-PyTorch CPU reference."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.coding import ContinuousDecoder, DiscreteDecoder, PopulationEncoder
from sb3_spikeplastic.snn.network import NetworkState, SpikingPlasticNetwork, tensor_leaves
from sb3_spikeplastic.snn.plasticity import (
    RULES,
    PlasticityRule,
    PlasticState,
    available_rules,
    get_rule_class,
    register_rule,
)

BUILTIN_RULES = ["static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"]


def test_builtin_rules_registered():
    assert set(BUILTIN_RULES) <= set(available_rules())


def paper_network(rule: str) -> SpikingPlasticNetwork:
    return SpikingPlasticNetwork(
        PopulationEncoder([-3] * 12, [3] * 12), ContinuousDecoder([-1] * 6, [1] * 6), (64, 64), steps=50, rule=rule
    )


def small_network(rule: str, **kw) -> SpikingPlasticNetwork:
    kw.setdefault("steps", 50)
    return SpikingPlasticNetwork(
        PopulationEncoder([-3] * 4, [3] * 4), ContinuousDecoder([-1] * 2, [1] * 2, pop_size=10), (32,), rule=rule, **kw
    )


# ---------------------------------------------------------------------------------------------------------------
# 4. Default initialisation: useful firing rates, finite nonzero gradients through 16 env steps


@pytest.mark.parametrize("rule", BUILTIN_RULES)
def test_default_init_fires_usefully_and_gradients_are_finite(rule):
    torch.manual_seed(0)
    net = paper_network(rule)
    B, n_steps = 4, 16
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(n_steps, B, 12, generator=g).clamp(-3, 3)  # VecNormalize-like observations
    target = torch.rand(n_steps, B, 6, generator=g) * 2 - 1
    state = net.initial_state(B, seed=2)
    loss, hidden_rates = 0.0, []
    for k in range(n_steps):
        out, state = net(obs[k], state)
        loss = loss + ((out.action - target[k]) ** 2).sum()
        if 2 <= k < 6:  # after the PSP has built up (~10 ms), over 4 env steps
            hidden_rates.append(torch.stack([r.detach().mean() for r in out.rates[:-1]]))
    rates = torch.stack(hidden_rates).mean(0)
    for i, r in enumerate(rates.tolist()):
        assert 0.01 <= r <= 0.5, f"{rule}: hidden layer {i} fires on {r:.3f} of neuron-steps"
    loss.backward()
    for i, layer in enumerate(net.layers):
        grad = layer.weight.grad
        assert grad is not None and torch.isfinite(grad).all(), f"{rule}: layer {i} W grad not finite"
        assert grad.abs().sum() > 0, f"{rule}: layer {i} W grad is zero"
        if layer.alpha is not None:
            assert torch.isfinite(layer.alpha.grad).all() and layer.alpha.grad.abs().sum() > 0
    for name, p in net.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


# ---------------------------------------------------------------------------------------------------------------
# 7. Reset


@pytest.mark.parametrize("rule", ["static", "dp-oja", "ndp-bcm"])
def test_reset_zeros_exactly_the_started_environments(rule):
    torch.manual_seed(3)
    net = small_network(rule)
    B = 4
    g = torch.Generator().manual_seed(4)
    state = net.initial_state(B, seed=5)
    with torch.no_grad():
        for _ in range(3):
            _, state = net(torch.rand(B, 4, generator=g) * 6 - 3, state)
    started = torch.tensor([1.0, 0.0, 1.0, 0.0])
    for episode_start in (started, started.bool()):
        reset = state.reset(episode_start)
        init = net.initial_state(B, seed=5)
        tensors_before, tensors_after, tensors_init = map(tensor_leaves, (state.layers, reset.layers, init.layers))
        assert len(tensors_before) == len(tensors_after) == len(tensors_init)
        n_nonzero_before = 0
        for before, after, zero in zip(tensors_before, tensors_after, tensors_init):
            assert after.shape == before.shape and after.dtype == before.dtype
            for b in (0, 2):
                assert torch.equal(after[b], zero[b]) and not after[b].any()
                n_nonzero_before += int(before[b].any())
            for b in (1, 3):
                assert torch.equal(after[b], before[b])
        assert n_nonzero_before >= 4  # filters (and traces/phi) really were non-zero before
        # the noise key is the random stream, not memory: never reset
        assert torch.equal(reset.noise_key, state.noise_key)
        assert not torch.equal(reset.noise_key, init.noise_key)

    # a reset environment behaves exactly like a fresh one with the same key
    reset = state.reset(started)
    fresh = net.initial_state(B)._replace(noise_key=state.noise_key)
    obs = torch.rand(B, 4, generator=g) * 6 - 3
    with torch.no_grad():
        out_r, st_r = net(obs, reset, record=True)
        out_f, st_f = net(obs, fresh, record=True)
    for b in (0, 2):
        assert torch.equal(out_r.action[b], out_f.action[b])
        for sr, sf in zip(out_r.record.spikes, out_f.record.spikes):
            assert torch.equal(sr[b], sf[b])
        for tr, tf in zip(tensor_leaves(st_r), tensor_leaves(st_f)):
            assert torch.equal(tr[b], tf[b])
    # and differently from the unreset ones (otherwise the comparison above proves nothing)
    assert any(not torch.equal(sr[1], sf[1]) for sr, sf in zip(out_r.record.spikes, out_f.record.spikes))


def test_state_select_cat_stack_roundtrip():
    torch.manual_seed(6)
    net = small_network("ndp-bcm")
    state = net.initial_state(5, seed=1)
    with torch.no_grad():
        _, state = net(torch.rand(5, 4) * 6 - 3, state)
    parts = [state.select(slice(0, 2)), state.select(torch.tensor([2])), state.select(slice(3, 5))]
    joined = NetworkState.cat(parts)
    for a, b in zip(tensor_leaves(joined), tensor_leaves(state)):
        assert torch.equal(a, b)
    stacked = NetworkState.stack([state, state.reset(torch.ones(5))])
    for s, a in zip(tensor_leaves(stacked), tensor_leaves(state)):
        assert s.shape == (2, *a.shape) and torch.equal(s[0], a)


# ---------------------------------------------------------------------------------------------------------------
# 10. Registry


@pytest.fixture
def clean_registry():
    before = dict(RULES)
    yield
    RULES.pop("my-rule", None)
    assert RULES == before


def _define_my_rule(**register_kw):
    @register_rule("my-rule", **register_kw)
    class MyRule(PlasticityRule):
        """Anti-Hebbian toy rule: E' = (1 - eta) E - eta * gain * r_post x r_pre."""

        def __init__(self, n_in, n_out, e_max=1.0, eta_init=0.05, gain=1.0):
            super().__init__(n_in, n_out, e_max, eta_init)
            self.gain = gain

        def update(self, r_pre, r_post, state):
            hebb = r_post.unsqueeze(-1) * r_pre.unsqueeze(-2)
            return PlasticState((1 - self.eta) * state.trace - self.eta * self.gain * hebb)

    return MyRule


def test_user_rule_is_usable_by_name(clean_registry):
    MyRule = _define_my_rule()
    assert "my-rule" in available_rules() and get_rule_class("my-rule") is MyRule
    torch.manual_seed(7)
    net = small_network("my-rule", rule_kwargs=dict(gain=2.0, eta_init=0.3))
    assert all(isinstance(layer.rule, MyRule) for layer in net.layers)
    state = net.initial_state(3)
    with torch.no_grad():
        out, state = net(torch.rand(3, 4) * 6 - 3, state, record=True)
    rec = out.record
    pre, post = rec.input_spikes.double().mean(1).numpy(), rec.spikes[0].double().mean(1).numpy()
    assert post.sum() > 0
    expected = np.clip(-0.3 * 2.0 * np.einsum("bi,bj->bij", post, pre), -1, 1)
    np.testing.assert_allclose(state.layers[0].plastic.trace.numpy(), expected, rtol=1e-5, atol=1e-7)


def test_unknown_rule_error_names_value_and_accepted(clean_registry):
    with pytest.raises(ValueError) as e:
        small_network("no-such-rule")
    msg = str(e.value)
    assert "no-such-rule" in msg
    for name in BUILTIN_RULES:
        assert name in msg
    with pytest.raises(ValueError, match="no-such-rule"):
        get_rule_class("no-such-rule")


def test_duplicate_registration_needs_override(clean_registry):
    first = _define_my_rule()
    with pytest.raises(ValueError, match="my-rule"):
        _define_my_rule()
    assert get_rule_class("my-rule") is first
    second = _define_my_rule(override=True)
    assert get_rule_class("my-rule") is second and second is not first
    with pytest.raises(ValueError):
        register_rule("static")(type("Shadow", (PlasticityRule,), {}))
    with pytest.raises(TypeError):
        register_rule("not-a-rule")(object)
    assert "not-a-rule" not in RULES


# ---------------------------------------------------------------------------------------------------------------
# 11. Plasticity interval and sequences


@pytest.mark.parametrize("interval", [7, 0, 51, -10])
def test_plasticity_interval_must_divide_steps(interval):
    with pytest.raises(ValueError, match=str(interval)):
        small_network("dp-oja", plasticity_interval=interval)


def _eps(k, tau):
    x = np.asarray(k, dtype=np.float64) / tau
    return x * np.exp(1 - x)


def _causal_conv(x, kernel):
    T = x.shape[-2]
    y = np.zeros_like(x)
    for t in range(T):
        for k in range(1, t + 1):
            y[:, t] += kernel[k] * x[:, t - k]
    return y


def test_five_trace_updates_per_step_in_order():
    """With plasticity_interval = T/5, E is updated 5 times per env step from each interval's rates, and each
    interval runs with the E of the previous update (checked against NumPy: the dp-linear recursion from the
    recorded spikes, and layer 0's membrane recomputed by explicit convolution over two env steps)."""
    torch.manual_seed(8)
    T, L = 50, 10
    net = SpikingPlasticNetwork(
        PopulationEncoder([-1] * 2, [1] * 2, pop_size=10),
        DiscreteDecoder(2, pop_size=4),
        (12,),
        steps=T,
        rule="dp-linear",
        plasticity_interval=L,
        rule_kwargs=dict(eta_init=0.3),
    ).double()
    B = 3
    state = net.initial_state(B, dtype=torch.float64)
    obs = torch.rand(2, B, 2, dtype=torch.float64) * 2 - 1
    recs = []
    with torch.no_grad():
        for k in range(2):
            out, state = net(obs[k], state, record=True)
            recs.append(out.record)
    sizes = net.sizes
    for rec in recs:
        for i, tr in enumerate(rec.traces):
            assert tr.shape == (B, 5, sizes[i + 1], sizes[i])

    eta = [float(torch.sigmoid(layer.rule.eta_logit.detach())) for layer in net.layers]
    layer_in = [torch.cat([r.input_spikes for r in recs], 1).numpy()]
    layer_out = [torch.cat([r.spikes[i] for r in recs], 1).numpy() for i in range(len(net.layers))]
    layer_in += layer_out[:-1]
    assert all(o.mean() > 0.01 for o in layer_out)
    traces = [np.concatenate([r.traces[i].numpy() for r in recs], 1) for i in range(len(net.layers))]
    for i in range(len(net.layers)):
        E = np.zeros((B, sizes[i + 1], sizes[i]))
        for j in range(10):  # 2 env steps x 5 intervals
            pre = layer_in[i][:, j * L : (j + 1) * L].mean(1)
            post = layer_out[i][:, j * L : (j + 1) * L].mean(1)
            E_new = np.clip((1 - eta[i]) * E + eta[i] * np.einsum("bi,bj->bij", post, pre), -1, 1)
            np.testing.assert_allclose(traces[i][:, j], E_new, rtol=1e-9, atol=1e-12)
            if j >= 2:  # once the PSP has built up (the output layer is silent in the first ~10 ms)
                assert not np.array_equal(E_new, E)  # E changes at every interval
            E = E_new

    # layer 0's membrane in interval j uses E after update j-1 (E = 0 in the very first interval)
    layer = net.layers[0]
    W, alpha = layer.weight.detach().numpy(), layer.alpha.detach().numpy()
    p = net.neuron
    psp = _causal_conv(layer_in[0], _eps(np.arange(2 * T), p.tau_s))
    refr = _causal_conv(layer_out[0], -p.scale_ref * p.theta * _eps(np.arange(2 * T), p.tau_ref))
    membrane = np.concatenate([r.membrane[0].numpy() for r in recs], 1)
    E_prev = np.zeros_like(traces[0][:, 0])
    for j in range(10):
        sl = slice(j * L, (j + 1) * L)
        w_eff = W + alpha * E_prev
        u = np.einsum("boi,bti->bto", w_eff, psp[:, sl]) + refr[:, sl]
        np.testing.assert_allclose(membrane[:, sl], u, rtol=1e-9, atol=1e-9)
        E_prev = traces[0][:, j]


def test_forward_sequence_equals_stepwise_forward_with_resets():
    torch.manual_seed(9)
    net = small_network("ndp-oja")
    Lseq, B = 6, 3
    g = torch.Generator().manual_seed(10)
    obs = torch.rand(Lseq, B, 4, generator=g) * 6 - 3
    starts = torch.zeros(Lseq, B)
    starts[0] = 1
    starts[2, 1] = 1
    starts[4, 0] = 1
    state0 = net.initial_state(B, seed=3)
    with torch.no_grad():
        outs, final = net.forward_sequence(obs, starts, state0)
        state = state0
        for k in range(Lseq):
            out, state = net(obs[k], state.reset(starts[k]))
            assert torch.equal(out.action, outs[k].action)
            for a, b in zip(out.rates, outs[k].rates):
                assert torch.equal(a, b)
        for a, b in zip(tensor_leaves(final), tensor_leaves(state)):
            assert torch.equal(a, b)
        # without the resets the outputs differ (so the resets were applied)
        outs_nr, _ = net.forward_sequence(obs, torch.zeros(Lseq, B), state0)
    assert not torch.equal(outs_nr[4].action[0], outs[4].action[0]) or not torch.equal(
        outs_nr[3].action, outs[3].action
    )


@pytest.mark.skipif(_fast.interval_ops() is None, reason="the estimate describes the compiled CPU ops' graph")
@pytest.mark.parametrize("rule,interval", [("ndp-oja", 10), ("static", 5)])
def test_backward_bytes_per_step_estimates_what_backpropagation_keeps(rule, interval):
    """The estimate that ``PPO(chunks_per_pass="auto")`` sizes its passes by, against the tensors autograd
    actually saves (distinct storages, the parameters left out) over a 16-step sequence: within 10 %. (The
    sequence's end keeps one trace more than its share: applying the last two deferred updates stores the one
    between.)"""
    torch.manual_seed(0)
    net = SpikingPlasticNetwork(
        PopulationEncoder([-3] * 6, [3] * 6, pop_size=20),
        ContinuousDecoder([-1] * 2, [1] * 2, pop_size=40),
        (48,),
        steps=10,
        rule=rule,
        plasticity_interval=interval,
    )
    Lseq, B = 16, 6
    parameters = {p.untyped_storage().data_ptr() for p in net.parameters()}
    saved: dict[int, int] = {}

    def pack(t):
        storage = t.untyped_storage()
        if storage.data_ptr() not in parameters:
            saved[storage.data_ptr()] = storage.nbytes()
        return t

    obs = torch.rand(Lseq, B, 6) * 6 - 3
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        outs, _ = net.forward_sequence(obs, torch.zeros(Lseq, B), net.initial_state(B))
    estimate = Lseq * B * net.backward_bytes_per_step()
    assert sum(saved.values()) == pytest.approx(estimate, rel=0.1)


# ---------------------------------------------------------------------------------------------------------------
# Devices: parametrised over ``cpu`` and, where present, ``cuda``. The reference runs on the CPU with the compiled
# ops disabled (``SB3_SPIKEPLASTIC_NO_COMPILE=1``), so on ``cpu`` this compares the compiled CPU path with the
# fallback and on ``cuda`` the CUDA path (its spike-loop kernel and eager PyTorch elsewhere) with the same fallback.
# float64 keeps the two summation orders' differences (~1e-15) far from flipping a spike.


def run_network(net: SpikingPlasticNetwork, device: str):
    """Five environment steps (with a reset) from a fixed state and a loss over all outputs; returns the
    actions, rates, final state and parameter gradients, all on the CPU."""
    g = torch.Generator().manual_seed(1)
    obs = (torch.rand(5, 6, 4, generator=g, dtype=torch.float64) * 6 - 3).to(device)
    starts = torch.zeros(5, 6, dtype=torch.float64, device=device)
    starts[3, 2] = 1
    weights = torch.randn(5, 6, 2, generator=g, dtype=torch.float64).to(device)
    net.zero_grad()
    outputs, final = net.forward_sequence(obs, starts, net.initial_state(6, seed=4, dtype=torch.float64))
    loss = sum((o.action * w).sum() + sum(r.sum() for r in o.rates) for o, w in zip(outputs, weights))
    loss.backward()
    return (
        [o.action.detach().cpu() for o in outputs],
        [r.detach().cpu() for o in outputs for r in o.rates],
        [t.detach().cpu() for t in tensor_leaves(final)],
        {n: p.grad.cpu() for n, p in net.named_parameters()},
    )


@pytest.mark.parametrize("rule", BUILTIN_RULES)
def test_network_on_device_matches_the_cpu_fallback(device, rule, monkeypatch):
    torch.manual_seed(3)
    net = SpikingPlasticNetwork(
        PopulationEncoder([-3] * 4, [3] * 4),
        ContinuousDecoder([-1] * 2, [1] * 2, pop_size=10),
        (32, 24),
        steps=25,
        rule=rule,
    ).double()
    candidate = copy.deepcopy(net).to(device)
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    actions, rates, state, grads = run_network(net, "cpu")
    monkeypatch.delenv(_fast.NO_COMPILE_ENV)
    got_actions, got_rates, got_state, got_grads = run_network(candidate, device)
    assert 0 < torch.cat(rates, 1).mean() < 1  # the network spikes, so the comparison is not of zeros
    for got, want in zip(got_actions + got_rates + got_state, actions + rates + state):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    assert got_grads.keys() == grads.keys()
    for name, want in grads.items():
        assert want.abs().max() > 0, name
        torch.testing.assert_close(got_grads[name], want, rtol=1e-7, atol=1e-10, msg=name)
