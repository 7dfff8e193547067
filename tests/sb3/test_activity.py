"""The rollout's TensorBoard scalars (``RolloutActivity``): spike rates, silent fractions, plasticity, modulation,
the action std and the energy, each the mean over every step of the rollout."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers import tmaze_model
from stable_baselines3.common.logger import KVWriter, Logger
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.activity import RolloutActivity
from sb3_spikeplastic.snn.energy import spike_counts
from sb3_spikeplastic.snn.network import NetworkOutput

SMALL = dict(hidden_sizes=(16,), steps=10, encoder_pop_size=8, action_pop_size=4)


class Capture:
    """Stands in for SB3's logger: keeps what is recorded."""

    def __init__(self):
        self.values = {}

    def record(self, key, value, exclude=None):
        self.values[key] = value


class Written(KVWriter):
    """An SB3 logger output that keeps every value written."""

    def __init__(self):
        self.values = {}

    def write(self, key_values, key_excluded, step=0):
        self.values.update(key_values)


def test_rollout_scalars_discrete():
    """``learn`` logs the activity of every rollout (RolloutActivityCallback) beside the callbacks it is given."""
    model = tmaze_model("ndp-oja", env_kwargs={"neurons_per_population": 10})
    written = Written()
    model.set_logger(Logger(None, [written]))
    calls = []
    model.learn(64, callback=lambda _locals, _globals: calls.append(1) or True)
    assert len(calls) == 64 // 2  # the user's callback ran at every rollout step
    values = written.values
    # spikes per step and neuron, at most one per 1 ms network step: the rate, silent neurons contributing nothing
    rate, silent = values["snn/layer0/spike_rate"], values["snn/layer0/silent_fraction"]
    assert 0.0 < rate <= 1.0 - silent
    snn = model.policy.snn
    assert values["snn/layer0/spikes_per_step"] == pytest.approx(rate * snn.sizes[1] * snn.steps, rel=1e-5)
    for key in (
        "snn/layer0/spike_rate",
        "snn/layer0/silent_fraction",
        "snn/layer1/spike_rate",
        "plasticity/layer0/eta",
        "plasticity/layer0/trace_abs_mean",
        "plasticity/layer0/trace_clip_fraction",
        "plasticity/layer0/alpha_abs_mean",
        "plasticity/layer0/modulation_mean",
        "plasticity/layer0/modulation_std",
    ):
        assert key in values, key
    assert "snn/action_std" not in values  # discrete actions: no Gaussian


def test_rollout_scalars_action_std_for_continuous_actions():
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=20)])
    model = PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=16,
        batch_size=16,
        bptt_steps=8,
        n_epochs=1,
        seed=0,
        policy_kwargs=dict(rule="dp-oja", log_std_init=-0.5, **SMALL),
    )
    activity = RolloutActivity(model.policy.snn, model.policy)
    activity.add(
        model.policy.step(
            torch.zeros(1, 3, device=model.device), model.policy.initial_state(1), torch.ones(1, device=model.device)
        )[-1]
    )
    capture = Capture()
    activity.record(capture, model.policy.initial_state(1))
    assert capture.values["snn/action_std"] == pytest.approx(np.exp(-0.5), rel=1e-6)


def test_rollout_statistics_are_the_means_of_every_steps():
    """The rollout's statistics, added up in batches of steps, are the means over the steps of each step's rate,
    silent fraction, modulation and spike counts, over more steps than one batch holds."""
    model = tmaze_model("ndp-oja", env_kwargs={"neurons_per_population": 10})
    snn = model.policy.snn
    generator = torch.Generator().manual_seed(0)

    def rates(n):  # about a third silent
        r = torch.rand(3, n, generator=generator, dtype=torch.float64).float().to(model.device)
        return torch.where(r < 0.3, torch.zeros_like(r), r)

    n_steps = RolloutActivity.BATCH_STEPS + 37
    outputs = [
        NetworkOutput(None, tuple(rates(n) for n in snn.sizes[1:]), None, rates(snn.sizes[0])) for _ in range(n_steps)
    ]
    activity = RolloutActivity(snn, model.policy)
    for out in outputs:
        activity.add(out)
    capture = Capture()
    activity.record(capture, snn.initial_state(3))
    for i, layer in enumerate(snn.layers):
        layer_rates = [out.rates[i] for out in outputs]
        expected = {
            "snn/layer{}/spike_rate": np.mean([float(r.mean()) for r in layer_rates]),
            "snn/layer{}/silent_fraction": np.mean([float((r == 0).float().mean()) for r in layer_rates]),
            "snn/layer{}/spikes_per_step": np.mean([float(spike_counts(out, snn.steps)[i + 1]) for out in outputs]),
        }
        if layer.plastic and layer.rule.modulated:
            m = [layer.rule.modulation(r).detach() for r in layer_rates]
            mean, square = np.mean([float(x.mean()) for x in m]), np.mean([float(x.pow(2).mean()) for x in m])
            expected["plasticity/layer{}/modulation_mean"] = mean
            expected["plasticity/layer{}/modulation_std"] = (square - mean**2) ** 0.5
        for key, value in expected.items():
            assert capture.values[key.format(i)] == pytest.approx(value, rel=1e-5), key.format(i)
    assert "plasticity/layer0/modulation_mean" in capture.values
    inputs = np.mean([float(spike_counts(out, snn.steps)[0]) for out in outputs])
    assert capture.values["snn/input/spikes_per_step"] == pytest.approx(inputs, rel=1e-5)


def test_rollout_energy_scalars_agree_with_rates():
    model = tmaze_model("dp-oja")
    written = Written()
    model.set_logger(Logger(None, [written]))
    model.learn(64)
    v, net = written.values, model.policy.snn
    for i, layer in enumerate(net.layers):
        rate = v[f"snn/layer{i}/spike_rate"]
        assert v[f"snn/layer{i}/spikes_per_step"] == pytest.approx(rate * layer.n_out * net.steps, rel=1e-4)
    synops = [v["snn/input/spikes_per_step"] * net.sizes[1]] + [
        v[f"snn/layer{i - 1}/spikes_per_step"] * net.sizes[i + 1] for i in range(1, len(net.layers))
    ]
    assert [v[f"snn/layer{i}/synops_per_step"] for i in range(len(net.layers))] == pytest.approx(synops, rel=1e-5)
    assert v["snn/synops_per_step"] == pytest.approx(sum(synops), rel=1e-5)
