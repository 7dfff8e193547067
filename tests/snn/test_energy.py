"""The energy estimate (sb3_spikeplastic.snn.energy): the plasticity's own operations and the cost arithmetic."""

import math

import pytest
from helpers import tmaze_model

from sb3_spikeplastic.snn.energy import AC_PJ, MAC_PJ, energy_estimate, plasticity_operations, trace_update_macs


@pytest.mark.parametrize("rule, per_synapse, modulated", [
    ("dp-linear", 3, False), ("dp-oja", 4, False), ("dp-bcm", 3, False), ("ndp-oja", 4, True), ("ndp-bcm", 3, True),
])
def test_plasticity_operations_count_every_synapse_and_the_modulation(rule, per_synapse, modulated):
    net = tmaze_model(rule).policy.snn
    sizes, updates = net.sizes, net.steps // net.interval
    assert updates == 1 and len(sizes) == 3  # one update per 25 ms frame; 16 inputs -> 16 -> output population
    expected = [updates * (per_synapse * n_in * n_out + (n_out * n_out if modulated else 0))
                for n_in, n_out in zip(sizes[:-1], sizes[1:])]
    assert plasticity_operations(net) == expected
    assert trace_update_macs(net.layers[0].rule) == per_synapse


def test_static_layers_do_no_plastic_work_and_several_updates_per_step_count():
    net = tmaze_model("dp-oja", policy_kwargs=dict(rule="dp-oja", hidden_sizes=(16,), plastic_layers=[0],
                                                   plasticity_interval=5)).policy.snn
    n_in, n_out = net.sizes[0], net.sizes[1]
    assert net.steps // net.interval == 5
    assert plasticity_operations(net) == [5 * 4 * n_in * n_out, 0.0]
    assert plasticity_operations(tmaze_model("static").policy.snn) == [0.0, 0.0]


def test_energy_estimate_in_nanojoules():
    got = energy_estimate([1000.0, 500.0], [100.0, 0.0])
    assert got["synops_nj"] == pytest.approx(1500 * AC_PJ / 1000) and AC_PJ == 0.9 and MAC_PJ == 4.6
    assert got["plasticity_nj"] == pytest.approx(0.46) and got["total_nj"] == pytest.approx(1.35 + 0.46)
    unknown = energy_estimate([1000.0], None)
    assert math.isnan(unknown["plasticity_nj"]) and math.isnan(unknown["total_nj"])


def test_a_rule_of_ones_own_has_no_known_cost():
    from sb3_spikeplastic import register_rule
    from sb3_spikeplastic.snn.plasticity import DPLinearRule

    @register_rule("energy-test-linear", override=True)
    class Unknown(DPLinearRule):  # a subclass may change the terms: its cost is not assumed
        pass

    net = tmaze_model("energy-test-linear").policy.snn
    assert trace_update_macs(net.layers[0].rule) is None and plasticity_operations(net) is None


def test_energy_meter_summary_adds_the_plasticity_and_the_estimate():
    import torch

    from sb3_spikeplastic.snn.energy import EnergyMeter

    model = tmaze_model("ndp-bcm")
    net, obs = model.policy.snn, torch.ones(3, *model.observation_space.shape, device=model.device)
    state = net.initial_state(3)
    with EnergyMeter(net) as meter:
        for _ in range(2):
            _, state = net(obs, state)
    summary = meter.summary()
    macs = plasticity_operations(net)
    assert summary["plasticity_macs_per_step"] == macs and summary["total_plasticity_macs_per_step"] == sum(macs)
    expected = sum(summary["synops_per_step"]) * AC_PJ / 1000 + sum(macs) * MAC_PJ / 1000
    assert summary["energy_nj"]["total_nj"] == pytest.approx(expected) and sum(summary["synops_per_step"]) > 0
