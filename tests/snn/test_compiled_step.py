"""One network step without autograd as one loop of compiled ops (:mod:`sb3_spikeplastic.snn.compiled_step`) against
the same step through the layers' modules: bit-identical outputs and states, and the cases where it stands aside."""

from __future__ import annotations

import pytest
import torch
from test_compiled_sequence import BUILTIN_RULES, raster_network, sequence_inputs, vector_network

import sb3_spikeplastic.snn.network as network_module
from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.compiled_step import compiled_step
from sb3_spikeplastic.snn.network import tensor_leaves

pytestmark = pytest.mark.skipif(_fast.interval_ops() is None, reason="needs the compiled CPU ops")


def run_steps(net, obs, starts, state, monkeypatch, compiled: bool, hold_plastic: bool = False):
    """Every step's output and state of ``net`` over ``obs`` with resets at ``starts``, without gradients, through
    :func:`compiled_step` or (with it switched off) through the layers' modules."""
    with monkeypatch.context() as m:
        if not compiled:
            m.setattr(network_module, "compiled_step", lambda *args, **kwargs: None)
        calls = []
        m.setattr(
            network_module,
            "compiled_step",
            lambda *args, _inner=network_module.compiled_step, **kwargs: calls.append(1) or _inner(*args, **kwargs),
        )
        results = []
        with torch.no_grad():
            for k in range(obs.shape[0]):
                out, state = net(obs[k], state.reset(starts[k]), hold_plastic=hold_plastic)
                results.append((out, state))
    assert len(calls) == obs.shape[0]
    return results


def assert_same_steps(net, obs, starts, state, monkeypatch, hold_plastic: bool = False):
    want = run_steps(net, obs, starts, state, monkeypatch, compiled=False, hold_plastic=hold_plastic)
    got = run_steps(net, obs, starts, state, monkeypatch, compiled=True, hold_plastic=hold_plastic)
    for (out_a, state_a), (out_b, state_b) in zip(want, got):
        assert torch.equal(out_a.action, out_b.action)
        assert torch.equal(out_a.input_rate, out_b.input_rate)
        assert len(out_a.rates) == len(out_b.rates)
        for ra, rb in zip(out_a.rates, out_b.rates):
            assert torch.equal(ra, rb)
        leaves_a, leaves_b = tensor_leaves(state_a), tensor_leaves(state_b)
        assert len(leaves_a) == len(leaves_b)
        for a, b in zip(leaves_a, leaves_b):
            assert torch.equal(a, b)
    # The steps did something: the last step's rates are not all zero.
    assert any(bool(r.any()) for r in got[-1][0].rates)


@pytest.mark.parametrize("rule", BUILTIN_RULES)
def test_the_compiled_step_gives_the_modules_outputs_and_states_bit_for_bit(rule, monkeypatch):
    net = vector_network(rule)
    assert_same_steps(net, *sequence_inputs(net), monkeypatch)


@pytest.mark.parametrize("rule", ["ndp-bcm", "dp-oja"])
def test_bit_for_bit_in_float64_with_static_and_plastic_layers_mixed(rule, monkeypatch):
    net = vector_network(rule, dtype=torch.float64, plastic_layers=[0, 2])
    assert_same_steps(net, *sequence_inputs(net, dtype=torch.float64), monkeypatch)


@pytest.mark.parametrize("rule", ["ndp-oja", "static"])
def test_bit_for_bit_on_spike_rasters_and_discrete_outputs(rule, monkeypatch):
    net = raster_network(rule)
    assert_same_steps(net, *sequence_inputs(net, length=9, batch=4), monkeypatch)


@pytest.mark.parametrize("rule", ["dp-oja", "ndp-bcm"])
def test_held_plastic_state_bit_for_bit(rule, monkeypatch):
    """The ``frozen`` ablation's step: every layer keeps the plastic state it came in with."""
    net = vector_network(rule)
    obs, starts, state = sequence_inputs(net)
    assert_same_steps(net, obs, starts, state, monkeypatch, hold_plastic=True)
    got = run_steps(net, obs, starts, state, monkeypatch, compiled=True, hold_plastic=True)
    for _, new_state in got:  # every trace stays at its initial value
        for before, after in zip(state.layers, new_state.layers):
            assert torch.equal(after.plastic.trace, before.plastic.trace)


def test_it_stands_aside_where_it_does_not_apply():
    net = vector_network("dp-oja")
    obs, _, state = sequence_inputs(net)
    spikes = net.encoder(obs[0], state.noise_key, net.steps)
    with torch.no_grad():
        assert compiled_step(net, spikes, state.layers) is not None
        # pending updates (inside a training sequence) need the deferred op
        _, pending_state = net(obs[0], state, defer_updates=True)
        assert any(layer.plastic.pending is not None for layer in pending_state.layers)
        assert compiled_step(net, spikes, pending_state.layers) is None
        # other dtypes than the parameters', and intervals shorter than the step
        assert compiled_step(net, spikes.double(), state.layers) is None
        short = vector_network("dp-oja", steps=10, plasticity_interval=5)
        assert compiled_step(short, spikes, short.initial_state(3).layers) is None
    # training: the layers' autograd nodes (or the sequence node) run
    assert compiled_step(net, spikes, state.layers) is None


def test_it_stands_aside_for_a_rule_of_ones_own():
    """A rule that the compiled op does not evaluate (an external modulator) runs its step in Python."""
    net = vector_network("ndp-oja", rule_kwargs={"modulation_source": "reward"})
    obs, _, state = sequence_inputs(net)
    with torch.no_grad():
        assert compiled_step(net, net.encoder(obs[0], state.noise_key, net.steps), state.layers) is None
