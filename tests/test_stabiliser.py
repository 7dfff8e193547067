"""The neuromodulation stabiliser option (``rule_kwargs=dict(modulation="tanh")``): bounded modulation and finite
gradients through long plastic sequences with the trace at its clip bound."""

import pytest
import torch

from sb3_spikeplastic.snn.coding import DiscreteDecoder, RasterInput
from sb3_spikeplastic.snn.network import NetworkState, SpikingPlasticNetwork, map_tensors
from sb3_spikeplastic.snn.plasticity import PlasticState, get_rule_class


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
    net = SpikingPlasticNetwork(RasterInput(steps, n_in), DiscreteDecoder(2, 4), hidden_sizes=(32,), steps=steps,
                                rule=rule, rule_kwargs=dict(modulation="tanh"))
    state = net.initial_state(4)
    # Start with every trace at ±E_max: the regime where the paper's unbounded rules overflowed.
    layers = tuple(s._replace(plastic=PlasticState(torch.randint(0, 2, s.plastic.trace.shape).float() * 2 - 1,
                                                   s.plastic.extra)) for s in state.layers)
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
