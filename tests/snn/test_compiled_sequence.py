"""The training sequence as one autograd node (:mod:`sb3_spikeplastic.snn.compiled_sequence`) against the same
sequence through the layers' own nodes: bit-identical outputs and gradients, and the cases where it stands aside."""

from __future__ import annotations

import pytest
import torch

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.coding import ContinuousDecoder, DiscreteDecoder, PopulationEncoder, RasterInput
from sb3_spikeplastic.snn.compiled_sequence import compiled_sequence_rates
from sb3_spikeplastic.snn.network import SpikingPlasticNetwork

BUILTIN_RULES = ["static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"]

pytestmark = pytest.mark.skipif(_fast.interval_ops() is None, reason="needs the compiled CPU ops")


def vector_network(rule: str, dtype=torch.float32, **kw) -> SpikingPlasticNetwork:
    torch.manual_seed(3)
    kw.setdefault("steps", 10)
    kw.setdefault("w_init_gain", 8.0)
    net = SpikingPlasticNetwork(
        PopulationEncoder([-3] * 5, [3] * 5, pop_size=10),
        ContinuousDecoder([-1] * 2, [1] * 2, pop_size=12),
        (24, 16),
        rule=rule,
        **kw,
    )
    return net.to(dtype)


def raster_network(rule: str) -> SpikingPlasticNetwork:
    torch.manual_seed(4)
    return SpikingPlasticNetwork(
        RasterInput(8, 12), DiscreteDecoder(3, pop_size=4), (20,), steps=8, rule=rule, w_init_gain=8.0
    )


def sequence_inputs(net, length=7, batch=3, dtype=torch.float32):
    g = torch.Generator().manual_seed(11)
    if isinstance(net.encoder, RasterInput):
        obs = (torch.rand(length, batch, net.steps, net.encoder.n_neurons, generator=g) < 0.3).to(dtype)
    else:
        obs = (torch.rand(length, batch, 5, generator=g) * 6 - 3).to(dtype)
    starts = torch.zeros(length, batch)
    starts[0, 1] = 1
    starts[3, 0] = 1
    starts[4, :] = 1
    return obs, starts, net.initial_state(batch, seed=5, dtype=dtype)


def outputs_and_gradients(net, obs, starts, state, compiled: bool):
    """The sequence's outputs and every parameter's gradient of a loss on the actions and all layers' rates."""
    net.zero_grad(set_to_none=True)
    outputs, final = net.forward_sequence(obs, starts, state, final_state=not compiled)
    assert (final is None) == compiled
    g = torch.Generator().manual_seed(12)
    loss = 0.0
    for out in outputs:
        loss = loss + (out.action * torch.randn(out.action.shape, generator=g, dtype=out.action.dtype)).sum()
        for r in out.rates:
            loss = loss + (r * torch.randn(r.shape, generator=g, dtype=r.dtype)).sum()
    loss.backward()
    grads = {name: p.grad.clone() for name, p in net.named_parameters() if p.grad is not None}
    return outputs, grads


def assert_same(net, obs, starts, state):
    want, want_grads = outputs_and_gradients(net, obs, starts, state, compiled=False)
    got, got_grads = outputs_and_gradients(net, obs, starts, state, compiled=True)
    for a, b in zip(want, got):
        assert torch.equal(a.action, b.action)
        assert torch.equal(a.input_rate, b.input_rate)
        for ra, rb in zip(a.rates, b.rates):
            assert torch.equal(ra, rb)
    assert want_grads.keys() == got_grads.keys() and want_grads
    for name in want_grads:
        assert torch.equal(want_grads[name], got_grads[name]), name


@pytest.mark.parametrize("rule", BUILTIN_RULES)
def test_sequence_node_gives_the_layers_outputs_and_gradients_bit_for_bit(rule):
    net = vector_network(rule)
    assert_same(net, *sequence_inputs(net))


@pytest.mark.parametrize("rule", ["ndp-bcm", "dp-oja"])
def test_bit_for_bit_in_float64_with_static_and_plastic_layers_mixed(rule):
    net = vector_network(rule, dtype=torch.float64, plastic_layers=[0, 2])
    assert_same(net, *sequence_inputs(net, dtype=torch.float64))


@pytest.mark.parametrize("rule", ["ndp-oja", "static"])
def test_bit_for_bit_on_spike_rasters_and_discrete_outputs(rule):
    net = raster_network(rule)
    assert_same(net, *sequence_inputs(net, length=9, batch=4))


def test_the_sequence_is_one_node_and_the_resets_reach_it():
    """One node for the whole sequence (not one per layer and step), and the resets change what it computes."""
    net = vector_network("ndp-oja")
    obs, starts, state = sequence_inputs(net)
    outputs, _ = net.forward_sequence(obs, starts, state, final_state=False)
    nodes = {r.grad_fn for out in outputs for r in out.rates}
    assert len(nodes) == 1 and type(next(iter(nodes))).__name__ == "_CompiledSequenceBackward"
    unreset, _ = net.forward_sequence(obs, torch.zeros_like(starts), state, final_state=False)
    assert not all(torch.equal(a, b) for a, b in zip(unreset[4].rates, outputs[4].rates))


def test_it_stands_aside_where_it_does_not_apply():
    net = vector_network("dp-oja")
    obs, starts, state = sequence_inputs(net)
    spikes = [net.encoder(obs[k], state.noise_key, net.steps) for k in range(obs.shape[0])]
    assert compiled_sequence_rates(net, spikes, starts, state) is not None
    with torch.no_grad():  # nothing to differentiate: the layers' ops alone are as fast
        assert compiled_sequence_rates(net, spikes, starts, state) is None
    first = state.layers[0]
    traced = state._replace(
        layers=(first._replace(psp=first.psp._replace(h1=first.psp.h1.clone().requires_grad_())), *state.layers[1:])
    )
    assert compiled_sequence_rates(net, spikes, starts, traced) is None  # a state that carries a gradient
    net.layers[1].weight.requires_grad_(False)
    assert compiled_sequence_rates(net, spikes, starts, state) is None  # a parameter without one
    net.layers[1].weight.requires_grad_(True)
    split = vector_network("dp-oja", plasticity_interval=5)
    assert compiled_sequence_rates(split, spikes, starts, split.initial_state(3)) is None  # two intervals a step
    outputs, final = split.forward_sequence(obs, starts, split.initial_state(3), final_state=False)
    assert final is None and len(outputs) == obs.shape[0]
