"""The NDP rules with their neuromodulation from outside the network: the update against a NumPy reference, the
gains' gradient against finite differences, and the network's checks of the modulator."""

import numpy as np
import pytest
import torch

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.coding import DiscreteDecoder, RasterInput
from sb3_spikeplastic.snn.network import SpikingPlasticNetwork
from sb3_spikeplastic.snn.plasticity import builtin_form, compiled_form, get_rule_class


def _rule(name, n_in=5, n_out=4, **kwargs):
    torch.manual_seed(3)
    rule = get_rule_class(name)(n_in, n_out, e_max=0.05, eta_init=0.3, **kwargs).double()
    with torch.no_grad():
        for p in rule.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return rule


def _reference_modulation(rule, r_post, m, learned):
    """M = tanh(G m + b [+ W_m r_post]) in NumPy, float64."""
    g, b = rule.modulator_gains.detach().numpy(), rule.modulator_bias.detach().numpy()
    x = m @ g.T + b
    if learned:
        x = x + r_post @ rule.w_m.detach().numpy().T
    return np.tanh(x)


@pytest.mark.parametrize("learned", [False, True])
def test_ndp_oja_update_with_an_external_modulator_matches_numpy(learned):
    rule = _rule("ndp-oja", modulation_source="reward", modulation_channels=2, learned_modulation=learned)
    assert (rule.w_m is not None) == learned
    rng = np.random.default_rng(0)
    E = rng.uniform(-0.05, 0.05, (3, 4, 5))
    r_pre, r_post, m = rng.uniform(0, 1, (3, 5)), rng.uniform(0, 1, (3, 4)), rng.normal(0, 1, (3, 2))
    eta = float(rule.eta.detach())
    M = _reference_modulation(rule, r_post, m, learned)
    prediction = np.einsum("boi,bi->bo", E, r_pre)
    expected = np.clip((1 - eta) * E + eta * np.einsum("bo,bi->boi", M * r_post - prediction, r_pre), -0.05, 0.05)
    state = rule.initial_state(3, torch.float64)._replace(trace=torch.tensor(E))
    with torch.no_grad():
        new = rule.step(torch.tensor(r_pre), torch.tensor(r_post), state, torch.tensor(m))
    np.testing.assert_allclose(new.trace.numpy(), expected, rtol=1e-12, atol=1e-14)
    assert (np.abs(expected) == 0.05).any()  # the clip is exercised


def test_ndp_bcm_update_with_an_external_modulator_matches_numpy():
    rule = _rule("ndp-bcm", modulation_source="td-error", modulation="linear")
    rng = np.random.default_rng(1)
    E = rng.uniform(-0.01, 0.01, (2, 4, 5))
    phi = rng.uniform(0, 0.5, (2, 5))
    r_pre, r_post, m = rng.uniform(0, 1, (2, 5)), rng.uniform(0, 1, (2, 4)), rng.normal(0, 1, (2, 1))
    eta, eta_phi, psi = float(rule.eta.detach()), float(rule.eta_phi.detach()), rule.psi.detach().numpy()
    M = m @ rule.modulator_gains.detach().numpy().T + rule.modulator_bias.detach().numpy()  # linear form
    r_beta = r_pre * (r_pre - (phi + psi))
    expected = np.clip((1 - eta) * E + eta * np.einsum("bo,bi->boi", M * r_post, r_beta), -0.05, 0.05)
    state = rule.initial_state(2, torch.float64)._replace(trace=torch.tensor(E), extra=(torch.tensor(phi),))
    with torch.no_grad():
        new = rule.step(torch.tensor(r_pre), torch.tensor(r_post), state, torch.tensor(m))
    np.testing.assert_allclose(new.trace.numpy(), expected, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(new.extra[0].numpy(), (1 - eta_phi) * phi + eta_phi * r_pre, rtol=1e-12)


def test_the_gains_gradient_matches_finite_differences():
    rule = _rule("ndp-oja", modulation_source="reward")
    rng = np.random.default_rng(2)
    state = rule.initial_state(2, torch.float64)._replace(trace=torch.tensor(rng.uniform(-0.01, 0.01, (2, 4, 5))))
    r_pre, r_post = torch.tensor(rng.uniform(0, 1, (2, 5))), torch.tensor(rng.uniform(0, 1, (2, 4)))
    m = torch.tensor(rng.normal(0, 1, (2, 1)))
    weights = torch.tensor(rng.normal(0, 1, (2, 4, 5)))

    def loss(gains, bias):  # gradcheck perturbs the parameters themselves, in place
        return (rule.step(r_pre, r_post, state, m).trace * weights).sum()

    assert torch.autograd.gradcheck(loss, (rule.modulator_gains, rule.modulator_bias), eps=1e-6, atol=1e-7)


def test_external_rules_leave_the_compiled_op_and_keep_their_form():
    learned = get_rule_class("ndp-oja")(3, 2)
    external = get_rule_class("ndp-oja")(3, 2, modulation_source="reward")
    assert compiled_form(learned) is not None and compiled_form(external) is None
    assert builtin_form(external) == compiled_form(learned)  # the same terms for the energy count
    assert external.modulation_macs() == 2 * 1 and learned.modulation_macs() == 2 * 2
    with pytest.raises(ValueError, match="learned_modulation=False needs an external modulation_source"):
        get_rule_class("ndp-oja")(3, 2, learned_modulation=False)
    with pytest.raises(ValueError, match="modulation_channels=0 must be a positive integer"):
        get_rule_class("ndp-oja")(3, 2, modulation_source="reward", modulation_channels=0)
    with pytest.raises(ValueError, match="needs a modulator"):
        external.modulation(torch.zeros(1, 2))


def _network(source="reward", channels=1):
    torch.manual_seed(0)
    kwargs = {} if source is None else {"modulation_source": source, "modulation_channels": channels}
    return SpikingPlasticNetwork(
        RasterInput(10, 12, 0.3), DiscreteDecoder(2, 4), (8,), 10, "ndp-oja", "all", rule_kwargs=kwargs
    )


def test_the_network_checks_its_modulator():
    net, plain = _network(channels=2), _network(None)
    assert net.modulator_channels == 2 and plain.modulator_channels == 0
    obs = (torch.rand(3, 10, 12) < 0.3).float()
    with pytest.raises(ValueError, match=r"modulator of shape \(batch, channels\) = \(3, 2\).*got None"):
        net(obs, net.initial_state(3))
    with pytest.raises(ValueError, match=r"got \(3, 1\)"):
        net(obs, net.initial_state(3), modulator=torch.zeros(3, 1))
    with pytest.raises(ValueError, match="no plastic layer's rule takes one"):
        plain(obs, plain.initial_state(3), modulator=torch.zeros(3, 2))


def test_the_modulator_steers_the_traces_and_the_sequence_replays_the_steps(monkeypatch):
    """Zero and non-zero signals give other traces; forward_sequence with the same modulators equals the steps, on
    the compiled path and the eager one."""
    net = _network()
    obs = (torch.rand(4, 3, 10, 12) < 0.4).float()
    modulators = torch.randn(4, 3, 1)
    starts = torch.zeros(4, 3)
    starts[2, 1] = 1
    for eager in (False, True):
        if eager:
            monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
        state = net.initial_state(3)
        stepped = []
        for k in range(4):
            out, state = net(obs[k], state.reset(starts[k]), modulator=modulators[k])
            stepped.append(out.action)
        outputs, final = net.forward_sequence(obs, starts, net.initial_state(3), modulators=modulators)
        torch.testing.assert_close(torch.stack([o.action for o in outputs]), torch.stack(stepped))
        torch.testing.assert_close(final.layers[0].plastic.trace, state.layers[0].plastic.trace)
        _, silent = net.forward_sequence(obs, starts, net.initial_state(3), modulators=torch.zeros_like(modulators))
        assert not torch.allclose(silent.layers[0].plastic.trace, final.layers[0].plastic.trace)
