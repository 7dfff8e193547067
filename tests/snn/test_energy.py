"""The energy estimate (sb3_spikeplastic.snn.energy): spike counts and synaptic operations, the meter of an
evaluation, the plasticity's own operations and the cost arithmetic."""

import math

import numpy as np
import pytest
import torch
from helpers import tmaze_model

from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.snn.energy import (
    AC_PJ,
    MAC_PJ,
    EnergyMeter,
    energy_estimate,
    plasticity_operations,
    spike_counts,
    synaptic_operations,
    trace_update_macs,
)
from sb3_spikeplastic.snn.network import NetworkOutput


@pytest.mark.parametrize(
    "rule, per_synapse, modulated",
    [
        ("dp-linear", 3, False),
        ("dp-oja", 4, False),
        ("dp-bcm", 3, False),
        ("ndp-oja", 4, True),
        ("ndp-bcm", 3, True),
    ],
)
def test_plasticity_operations_count_every_synapse_and_the_modulation(rule, per_synapse, modulated):
    net = tmaze_model(rule).policy.snn
    sizes, updates = net.sizes, net.steps // net.interval
    assert updates == 1 and len(sizes) == 3  # one update per 25 ms frame; 16 inputs -> 16 -> output population
    expected = [
        updates * (per_synapse * n_in * n_out + (n_out * n_out if modulated else 0))
        for n_in, n_out in zip(sizes[:-1], sizes[1:])
    ]
    assert plasticity_operations(net) == expected
    assert trace_update_macs(net.layers[0].rule) == per_synapse


def test_static_layers_do_no_plastic_work_and_several_updates_per_step_count():
    net = tmaze_model(
        "dp-oja", policy_kwargs=dict(rule="dp-oja", hidden_sizes=(16,), plastic_layers=[0], plasticity_interval=5)
    ).policy.snn
    n_in, n_out = net.sizes[0], net.sizes[1]
    assert net.steps // net.interval == 5
    assert plasticity_operations(net) == [5 * 4 * n_in * n_out, 0.0]
    assert plasticity_operations(tmaze_model("static").policy.snn) == [0.0, 0.0]


def test_energy_estimate_in_nanojoules():
    got = energy_estimate([1000.0, 500.0], [100.0, 0.0])
    # 1,500 accumulates of 0.9 pJ and 100 multiply-accumulates of 4.6 pJ (32-bit float, 45 nm)
    assert got["synops_nj"] == pytest.approx(1.35) and got["plasticity_nj"] == pytest.approx(0.46)
    assert got["total_nj"] == pytest.approx(1.35 + 0.46)
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


def test_spike_counts_and_synops_by_hand():
    # batch of 2, T = 10: input 3 neurons, one hidden layer of 2, output of 4
    out = NetworkOutput(
        torch.zeros(2, 1),
        (torch.tensor([[0.1, 0.3], [0.0, 0.2]]), torch.tensor([[0.1, 0.0, 0.0, 0.1], [0.0] * 4])),
        None,
        torch.tensor([[0.5, 0.0, 0.1], [0.2, 0.2, 0.2]]),
    )
    spikes = spike_counts(out, steps=10)
    # input: (6 + 6) / 2 = 6 spikes; hidden: (4 + 2) / 2 = 3; output: 2 / 2 = 1
    assert spikes.tolist() == pytest.approx([6.0, 3.0, 1.0])
    # each input spike reaches the 2 hidden neurons, each hidden spike the 4 output neurons
    assert synaptic_operations(spikes, [3, 2, 4]).tolist() == pytest.approx([12.0, 12.0])


def test_energy_meter_counts_every_spike_of_an_evaluation():
    model = tmaze_model("ndp-oja")
    net = model.policy.snn
    obs = torch.as_tensor(
        np.stack([TMazeCueEnv(neurons_per_population=4).observation_space.sample() for _ in range(3)]),
        dtype=torch.float32,
        device=model.device,
    )
    state = net.initial_state(3)
    recorded = []
    with EnergyMeter(net) as meter:
        for _ in range(4):
            out, state = net(model.policy._preprocess(obs), state, record=True)
            recorded.append(out.record)
    net(model.policy._preprocess(obs), state)  # outside the block: not counted
    assert meter.env_steps == 12
    # independently: spikes counted in the recorded rasters, averaged over the 12 environment steps
    spikes = [sum(r.input_spikes.sum().item() for r in recorded) / 12]
    spikes += [sum(r.spikes[i].sum().item() for r in recorded) / 12 for i in range(len(net.layers))]
    summary = meter.summary()
    assert summary["spikes_per_step"] == pytest.approx(spikes, rel=1e-5)
    sizes = net.sizes
    assert summary["synops_per_step"] == pytest.approx(
        [spikes[i] * sizes[i + 1] for i in range(len(net.layers))], rel=1e-5
    )
    assert summary["total_spikes_per_step"] == pytest.approx(sum(spikes[1:]), rel=1e-5) and spikes[1] > 0
