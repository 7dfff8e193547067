"""TensorBoard monitoring: rollout scalars, one episode's activity, the activity figure, hyperparameter text."""

import io

import gymnasium as gym
import matplotlib.image
import numpy as np
import pytest
import torch
from stable_baselines3.common.logger import KVWriter, Logger, make_output_format
from stable_baselines3.common.vec_env import DummyVecEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from helpers import tmaze_model

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.zoo.figures import activity_figure
from sb3_spikeplastic.sb3.activity import RolloutActivity
from sb3_spikeplastic.snn.energy import spike_counts
from sb3_spikeplastic.zoo.callbacks import ActivityFigureCallback
from sb3_spikeplastic.zoo.hparams import hyperparameter_markdown, write_hyperparameters
from sb3_spikeplastic.zoo.recording import record_episode
from sb3_spikeplastic.snn.network import NetworkOutput

SMALL = dict(hidden_sizes=(16,), steps=10, encoder_pop_size=8, action_pop_size=4)


def assert_png_nontrivial(data: bytes):
    assert len(data) > 5_000
    image = matplotlib.image.imread(io.BytesIO(data), format="png")
    pixels = image.reshape(-1, image.shape[-1])
    assert image.ndim == 3 and (pixels != pixels[0]).any()  # more than one colour


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
    for key in ("snn/layer0/spike_rate", "snn/layer0/silent_fraction", "snn/layer1/spike_rate",
                "plasticity/layer0/eta", "plasticity/layer0/trace_abs_mean", "plasticity/layer0/trace_clip_fraction",
                "plasticity/layer0/alpha_abs_mean", "plasticity/layer0/modulation_mean",
                "plasticity/layer0/modulation_std"):
        assert key in values, key
    assert "snn/action_std" not in values  # discrete actions: no Gaussian


def test_rollout_scalars_action_std_for_continuous_actions():
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=20)])
    model = PPO("SpikePlasticPolicy", env, n_steps=16, batch_size=16, bptt_steps=8, n_epochs=1, seed=0,
                policy_kwargs=dict(rule="dp-oja", log_std_init=-0.5, **SMALL))
    activity = RolloutActivity(model.policy.snn, model.policy)
    activity.add(model.policy.step(torch.zeros(1, 3, device=model.device), model.policy.initial_state(1),
                                   torch.ones(1, device=model.device))[-1])
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
    outputs = [NetworkOutput(None, tuple(rates(n) for n in snn.sizes[1:]), None, rates(snn.sizes[0]))
               for _ in range(n_steps)]
    activity = RolloutActivity(snn, model.policy)
    for out in outputs:
        activity.add(out)
    capture = Capture()
    activity.record(capture, snn.initial_state(3))
    for i, layer in enumerate(snn.layers):
        layer_rates = [out.rates[i] for out in outputs]
        expected = {"snn/layer{}/spike_rate": np.mean([float(r.mean()) for r in layer_rates]),
                    "snn/layer{}/silent_fraction": np.mean([float((r == 0).float().mean()) for r in layer_rates]),
                    "snn/layer{}/spikes_per_step": np.mean([float(spike_counts(out, snn.steps)[i + 1])
                                                            for out in outputs])}
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


def test_record_episode_tmaze_is_complete_and_leaves_global_rng_alone():
    model = tmaze_model("dp-bcm", n_envs=1, env_kwargs={"neurons_per_population": 10})
    env = TMazeCueEnv()
    rng = torch.random.get_rng_state()
    activity = record_episode(model.policy, env, seed=3)
    assert torch.equal(rng, torch.random.get_rng_state())
    assert activity.done and activity.n_steps == env.n_frames
    total = activity.n_steps * 25
    assert activity.input_spikes.shape == (total, 40)
    assert [s.shape for s in activity.spikes] == [(total, 16), (total, 2)]
    assert [m.shape for m in activity.membrane] == [(total, 16), (total, 2)]
    assert activity.traces[0].shape == (activity.n_steps, 16, 40)
    assert activity.modulation == [None, None]  # dp-bcm is not neuromodulated
    maze = TMazeCueEnv()
    maze.reset(seed=3)  # the same episode: its cues decide the correct arm
    assert activity.info["correct_action"] == maze.correct_action
    assert activity.info["is_success"] == (int(activity.actions[-1]) == maze.correct_action)
    assert [g[0] for g in activity.input_groups] == ["left cue", "right cue", "decision", "noise"]
    # the recorded raster is the environment's: same seed, same spikes
    first, _ = TMazeCueEnv().reset(seed=3)
    assert np.array_equal(activity.input_spikes[:25], first)
    # replayable: the same seed gives the same episode
    again = record_episode(model.policy, TMazeCueEnv(), seed=3)
    assert np.array_equal(again.spikes[0], activity.spikes[0]) and again.actions == activity.actions


def test_activity_figure_png(tmp_path):
    model = tmaze_model("ndp-oja", n_envs=1, env_kwargs={"neurons_per_population": 10})
    activity = record_episode(model.policy, TMazeCueEnv(), seed=0)
    assert activity.modulation[0] is not None
    fig = activity_figure(activity, title="test")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=60)
    assert_png_nontrivial(buffer.getvalue())
    # continuous actions, several hidden layers, cut episode
    env = gym.make("Pendulum-v1")
    model = PPO("SpikePlasticPolicy", DummyVecEnv([lambda: gym.make("Pendulum-v1")]), n_steps=16, batch_size=16,
                bptt_steps=8, policy_kwargs=dict(rule="ndp-bcm", hidden_sizes=(8, 8), steps=10, encoder_pop_size=8,
                                                 action_pop_size=4))
    activity = record_episode(model.policy, env, max_steps=7)
    assert activity.n_steps == 7 and not activity.done and len(activity.spikes) == 3
    fig = activity_figure(activity)
    fig.savefig(tmp_path / "pendulum.png", dpi=60)
    assert_png_nontrivial((tmp_path / "pendulum.png").read_bytes())


def test_figure_callback_and_hyperparameter_text_reach_tensorboard(tmp_path):
    model = tmaze_model("dp-oja", env_kwargs={"neurons_per_population": 10})
    model.set_logger(Logger(str(tmp_path), [make_output_format("tensorboard", str(tmp_path))]))
    config = {"n_steps": 32, "policy_kwargs": {"rule": "dp-oja", "hidden_sizes": [16]}, "normalize": False}
    assert write_hyperparameters(model.logger, config)
    model.learn(192, callback=ActivityFigureCallback("TMazeCue-v0", every=2))
    model.logger.close()
    ea = EventAccumulator(str(tmp_path), size_guidance={"images": 0, "tensors": 0})
    ea.Reload()
    tags = ea.Tags()
    assert "snn/layer0/spike_rate" in tags["scalars"] and "plasticity/layer0/eta" in tags["scalars"]
    images = ea.Images("snn/activity")
    assert [i.step for i in images] == [128]  # rollout 2 of 3, 64 steps each
    assert_png_nontrivial(images[0].encoded_image_string)
    text = ea.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "| policy_kwargs.rule | dp-oja |" in text and "| n_steps | 32 |" in text


def test_hyperparameter_markdown_flattens_and_escapes():
    table = hyperparameter_markdown({"a": 1, "b": {"c": [1, 2], "d": "x|y"}, "e": {}})
    assert table.splitlines() == ["| hyperparameter | value |", "|---|---|", "| a | 1 |", "| b.c | [1, 2] |",
                                  "| b.d | x\\|y |", "| e | {} |"]


def test_figure_callback_validates_its_interval():
    with pytest.raises(ValueError, match="every=0 must be >= 1"):
        ActivityFigureCallback("TMazeCue-v0", every=0)


def test_spike_counts_and_synops_by_hand():
    from sb3_spikeplastic.snn.energy import spike_counts, synaptic_operations
    from sb3_spikeplastic.snn.network import NetworkOutput

    # batch of 2, T = 10: input 3 neurons, one hidden layer of 2, output of 4
    out = NetworkOutput(torch.zeros(2, 1),
                        (torch.tensor([[0.1, 0.3], [0.0, 0.2]]), torch.tensor([[0.1, 0.0, 0.0, 0.1], [0.0] * 4])),
                        None, torch.tensor([[0.5, 0.0, 0.1], [0.2, 0.2, 0.2]]))
    spikes = spike_counts(out, steps=10)
    # input: (6 + 6) / 2 = 6 spikes; hidden: (4 + 2) / 2 = 3; output: 2 / 2 = 1
    assert spikes.tolist() == pytest.approx([6.0, 3.0, 1.0])
    # each input spike reaches the 2 hidden neurons, each hidden spike the 4 output neurons
    assert synaptic_operations(spikes, [3, 2, 4]).tolist() == pytest.approx([12.0, 12.0])


def test_energy_meter_counts_every_spike_of_an_evaluation():
    from sb3_spikeplastic.snn.energy import EnergyMeter

    model = tmaze_model("ndp-oja")
    net = model.policy.snn
    obs = torch.as_tensor(np.stack([TMazeCueEnv(neurons_per_population=4).observation_space.sample()
                                    for _ in range(3)]), dtype=torch.float32, device=model.device)
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
    assert summary["synops_per_step"] == pytest.approx([spikes[i] * sizes[i + 1] for i in range(len(net.layers))],
                                                       rel=1e-5)
    assert summary["total_spikes_per_step"] == pytest.approx(sum(spikes[1:]), rel=1e-5) and spikes[1] > 0


def test_rollout_energy_scalars_agree_with_rates():
    model = tmaze_model("dp-oja")
    written = Written()
    model.set_logger(Logger(None, [written]))
    model.learn(64)
    v, net = written.values, model.policy.snn
    for i, layer in enumerate(net.layers):
        assert v[f"snn/layer{i}/spikes_per_step"] == pytest.approx(v[f"snn/layer{i}/spike_rate"] * layer.n_out * net.steps,
                                                                   rel=1e-4)
    synops = [v["snn/input/spikes_per_step"] * net.sizes[1]] + [
        v[f"snn/layer{i - 1}/spikes_per_step"] * net.sizes[i + 1] for i in range(1, len(net.layers))]
    assert [v[f"snn/layer{i}/synops_per_step"] for i in range(len(net.layers))] == pytest.approx(synops, rel=1e-5)
    assert v["snn/synops_per_step"] == pytest.approx(sum(synops), rel=1e-5)


def test_typical_seed_is_the_first_episode_that_ends_as_most_do(monkeypatch):
    from types import SimpleNamespace

    from sb3_spikeplastic.zoo import recording as monitoring

    outcomes = {}

    def episode(policy, env, seed, **kwargs):
        return SimpleNamespace(done=True, info={} if outcomes is None else {"is_success": outcomes[seed]})

    monkeypatch.setattr(monitoring, "record_episode", episode)
    make = lambda: SimpleNamespace(close=lambda: None)  # noqa: E731
    outcomes = {5: False, 6: True, 7: True, 8: False}
    assert monitoring.typical_seed(None, make, 5, n_episodes=4) == (6, "2 of 4 episodes from seed 5 succeeded")
    outcomes = {0: True, 1: False, 2: False}
    assert monitoring.typical_seed(None, make, 0, n_episodes=3) == (1, "1 of 3 episodes from seed 0 succeeded")
    outcomes = None  # no success reported: the seed asked for
    assert monitoring.typical_seed(None, make, 3, n_episodes=3) == (3, None)
