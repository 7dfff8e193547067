"""The network and PPO on every available device against the pure-PyTorch CPU reference.

Parametrised over ``cpu`` and, where present, ``cuda``. The reference runs on the CPU with the compiled ops
disabled (``SB3_SPIKEPLASTIC_NO_COMPILE=1``), so on ``cpu`` these tests compare the compiled CPU path with the
fallback and on ``cuda`` the CUDA path (its spike-loop kernel and eager PyTorch elsewhere) with the same
fallback. float64 keeps the two summation orders' differences (~1e-15) far from flipping a spike.
"""

from __future__ import annotations

import copy

import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.coding import ContinuousDecoder, PopulationEncoder
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.snn.network import SpikingPlasticNetwork, tensor_leaves

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="needs a CUDA device"))]
RULES = ["static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"]


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
    return ([o.action.detach().cpu() for o in outputs], [r.detach().cpu() for o in outputs for r in o.rates],
            [t.detach().cpu() for t in tensor_leaves(final)], {n: p.grad.cpu() for n, p in net.named_parameters()})


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("rule", RULES)
def test_network_on_device_matches_the_cpu_fallback(device, rule, monkeypatch):
    torch.manual_seed(3)
    net = SpikingPlasticNetwork(PopulationEncoder([-3] * 4, [3] * 4), ContinuousDecoder([-1] * 2, [1] * 2, pop_size=10),
                                (32, 24), steps=25, rule=rule).double()
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


@pytest.mark.parametrize("device", DEVICES)
def test_ppo_learns_saves_and_loads_across_devices(device, tmp_path):
    """Two rollouts and updates on the device (action masks, plastic traces and the chunked buffer included);
    the saved model loads on the CPU with the same parameters and acts."""
    env = DummyVecEnv([lambda: TMazeCueEnv(neurons_per_population=4)] * 2)
    model = PPO("SpikePlasticPolicy", env, n_steps=32, batch_size=32, bptt_steps=16, n_epochs=2, seed=0,
                use_action_masks=True, device=device,
                policy_kwargs=dict(rule="ndp-oja", hidden_sizes=(16,)))
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(64)
    assert model.device.type == device
    assert all(p.device.type == device for p in model.policy.parameters())
    assert any(not torch.equal(v, before[k]) for k, v in model.policy.state_dict().items())  # it trained
    model.save(tmp_path / "model.zip")
    loaded = PPO.load(tmp_path / "model.zip", device="cpu")
    for key, value in model.policy.state_dict().items():
        assert torch.equal(loaded.policy.state_dict()[key], value.cpu()), key
    obs = env.reset()
    actions, state = loaded.predict(obs, episode_start=torch.ones(2).numpy().astype(bool), deterministic=True,
                                    action_masks=env.env_method("action_masks"))
    assert actions.shape == (2,) and state is not None
