"""Modulation sources: the reward read from observations, the TD error against a hand loop, exact replay by PPO,
save/load, the one-line errors, a source of one's own, and the CUDA path."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs import PreviousReward
from sb3_spikeplastic.sb3.modulation import (
    MODULATION_SOURCES,
    ModulationSource,
    RewardInput,
    TDErrorSource,
    read_reward,
    register_modulation_source,
)

SMALL = dict(n_steps=32, batch_size=32, bptt_steps=16, n_epochs=1)


def _cartpole():
    return PreviousReward(gym.make("CartPole-v1"))


def _model(source, env=None, policy_kwargs=None, **kwargs):
    kwargs = {**SMALL, **kwargs}
    policy_kwargs = {
        "rule": "ndp-oja",
        "hidden_sizes": [16],
        "rule_kwargs": {"modulation_source": source},
        **(policy_kwargs or {}),
    }
    return PPO("SpikePlasticPolicy", env or _cartpole(), policy_kwargs=policy_kwargs, seed=0, **kwargs)


def test_reward_input_reads_vectors_and_rasters():
    vector = RewardInput.parse(4, spaces.Box(-np.inf, np.inf, (5,)))
    assert vector == RewardInput((4,))
    obs = torch.tensor([[0.0, 1, 2, 3, 7.5], [0, 0, 0, 0, -2]])
    torch.testing.assert_close(read_reward(vector, obs, raster=False), torch.tensor([7.5, -2.0]))
    raster = RewardInput.parse(
        {"positive": [0, 1], "negative": [2], "scale": 2.0, "offset": 0.5}, spaces.Box(0, 1, (4, 3))
    )
    frames = torch.zeros(1, 4, 3)
    frames[0, :2, 0] = 1  # positive neurons: 2 spikes of 8 slots; negative: 1 of 4
    frames[0, 0, 2] = 1
    assert read_reward(raster, frames, raster=True).item() == pytest.approx(2.0 * (2 / 8 - 1 / 4) + 0.5)
    with pytest.raises(
        ValueError, match=r"reward_input positive indices \[5\] out of range for observations of size 5"
    ):
        RewardInput.parse([5], spaces.Box(-1, 1, (5,)))
    with pytest.raises(ValueError, match=r"reward_input keys \['sign'\] unknown; accepted: positive"):
        RewardInput.parse({"positive": [0], "sign": 1}, spaces.Box(-1, 1, (5,)))


def test_the_td_error_of_a_sequence_equals_a_hand_loop_and_its_steps():
    class Critic:
        def observation_value(self, obs):
            return obs[:, 0] * 2.0 + obs[:, 1]

    space = spaces.Box(-np.inf, np.inf, (3,))
    source = TDErrorSource(space, RewardInput((2,)), gamma=0.9)
    rng = np.random.default_rng(0)
    obs = torch.tensor(rng.normal(size=(6, 2, 3)), dtype=torch.float32)
    starts = torch.zeros(6, 2)
    starts[3, 0] = 1
    state = torch.tensor([[0.7, 1.0], [0.0, 0.0]])  # env 0 holds a value; env 1 starts fresh
    signals, final = source.sequence(obs, starts, state, Critic())
    expected = np.zeros((6, 2))
    for b in range(2):
        previous, held = float(state[b, 0]), float(state[b, 1])
        for k in range(6):
            if starts[k, b]:
                previous, held = 0.0, 0.0
            value = 2.0 * float(obs[k, b, 0]) + float(obs[k, b, 1])
            expected[k, b] = held * (float(obs[k, b, 2]) + 0.9 * value - previous)
            previous, held = value, 1.0
    np.testing.assert_allclose(signals[..., 0].numpy(), expected, rtol=1e-5, atol=1e-6)
    assert expected[0, 1] == 0 and expected[3, 0] == 0 and expected[4, 0] != 0
    # Step by step, carrying the state, gives the same signals.
    carried, stepped = state, []
    for k in range(6):
        carried = carried * (1 - starts[k]).unsqueeze(-1)
        signal, carried = source.sequence(obs[k : k + 1], torch.zeros(1, 2), carried, Critic())
        stepped.append(signal[0])
    torch.testing.assert_close(torch.stack(stepped), signals)
    torch.testing.assert_close(carried, final)


@pytest.mark.parametrize("source, policy_kwargs", [("reward", {}), ("td-error", {"critic": "mlp"})])
def test_ppo_replays_the_modulated_rollout_exactly(source, policy_kwargs):
    """At learning rate 0 the update's recomputed log-probabilities equal the rollout's: approx_kl is ~0."""
    env = "TMazeReversal-v0" if source == "td-error" else None
    model = _model(source, env, policy_kwargs, learning_rate=0.0)
    model.learn(64)
    assert model.logger.name_to_value["train/approx_kl"] < 1e-7
    assert model.logger.name_to_value["train/clip_fraction"] == 0


def test_a_reward_modulated_policy_round_trips_save_and_load(tmp_path):
    model = _model("reward")
    model.learn(32)
    assert model.policy.snn_config["reward_input"] == {"positive": [4], "negative": [], "scale": 1.0, "offset": 0.0}
    model.save(tmp_path / "m.zip")
    loaded = PPO.load(tmp_path / "m.zip")
    assert loaded.policy.modulation_source.name == "reward"
    env = _cartpole()
    obs = np.stack([env.reset(seed=s)[0] for s in range(3)])
    obs[:, 4] = [0.0, 1.0, 1.0]
    outputs = []
    for m in (model, loaded):
        state = m.policy.initial_state(3)
        with torch.no_grad():
            x = m.policy._preprocess(torch.as_tensor(obs))
            out, state = m.policy.network_step(x, state)
        outputs.append((out.action, state.layers[0].plastic.trace))
    torch.testing.assert_close(outputs[0], outputs[1], rtol=0, atol=0)


def test_the_reward_element_is_read_raw_and_moves_the_traces():
    model = _model("reward")
    policy = model.policy
    # CartPole's velocities (1, 3) are unbounded and standardised; the appended reward (4) is not.
    assert policy.obs_standardizer.mask.tolist() == [False, True, False, True, False]
    obs = torch.as_tensor(np.stack([_cartpole().reset(seed=0)[0]] * 2))
    obs[1, 4] = 1.0
    with torch.no_grad():
        out, state = policy.network_step(policy._preprocess(obs), policy.initial_state(2))
    torch.testing.assert_close(out.modulator, torch.tensor([[0.0], [1.0]]))
    trace = state.layers[0].plastic.trace
    assert not torch.allclose(trace[0], trace[1])


def test_td_error_takes_ppo_gamma_and_the_env_reward_input():
    model = _model("td-error", policy_kwargs={"critic": "mlp"}, gamma=0.95)
    assert model.policy.modulation_source.gamma == 0.95
    assert model.policy_kwargs["modulation_kwargs"] == {"gamma": 0.95}
    own = _model("td-error", policy_kwargs={"critic": "mlp", "modulation_kwargs": {"gamma": 0.5}}, gamma=0.95)
    assert own.policy.modulation_source.gamma == 0.5


@pytest.mark.parametrize(
    "source, env, policy_kwargs, message",
    [
        ("dopamine", None, {}, "unknown modulation_source 'dopamine'; accepted: learned, reward, td-error"),
        (
            "reward",
            None,
            {"rule": "dp-oja"},
            "rule 'dp-oja' takes no neuromodulation .* rules that do: ndp-oja, ndp-bcm",
        ),
        ("reward", "CartPole-v1", {}, "modulation_source='reward' needs the previous reward in the observation"),
        ("td-error", None, {}, "modulation_source='td-error' needs the value of the observation .* critic='mlp'"),
        ("td-error", None, {"critic": "mlp", "modulation_kwargs": {"gamma": 2}}, "gamma=2 must lie in"),
    ],
)
def test_bad_modulation_settings_are_one_line_errors(source, env, policy_kwargs, message):
    if "critic" not in policy_kwargs and source == "td-error":
        env = "TMazeReversal-v0"  # the spiking critic is the raster's default
    with pytest.raises(ValueError, match=message) as error:
        _model(source, env, policy_kwargs)
    assert "\n" not in str(error.value)


def test_a_registered_source_of_ones_own_trains():
    @register_modulation_source("surprise")
    class Surprise(ModulationSource):
        channels = 2
        state_size = 4

        def sequence(self, obs, episode_starts, state, policy):
            signals = []
            for k in range(obs.shape[0]):
                state = state * (1 - episode_starts[k]).unsqueeze(-1)
                signals.append((obs[k, :, :4] - state).abs()[:, :2])
                state = obs[k, :, :4]
            return torch.stack(signals), state

    try:
        model = _model("surprise", env=gym.make("CartPole-v1"))
        assert model.policy.snn_config["rule_kwargs"]["modulation_channels"] == 2
        model.learn(64)
        assert model.logger.name_to_value["train/approx_kl"] >= 0
    finally:
        MODULATION_SOURCES.pop("surprise")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("source, policy_kwargs", [("reward", {}), ("td-error", {"critic": "mlp"})])
def test_modulated_policies_run_on_cuda_as_on_the_cpu(source, policy_kwargs):
    outputs = []
    for device in ("cpu", "cuda"):
        model = _model(source, "TMazeReversal-v0", policy_kwargs, device=device, learning_rate=0.0)
        model.learn(32)
        assert model.logger.name_to_value["train/approx_kl"] < 1e-6
        raster = torch.zeros(2, *model.observation_space.shape, device=device)
        raster[1, :10, 10:20] = 1
        with torch.no_grad():
            out, _ = model.policy.network_step(raster, model.policy.initial_state(2))
        outputs.append(out.action.cpu())
    torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-4, atol=1e-4)


def test_the_documented_novelty_source_trains():
    """The worked example of docs/neuromodulation.md, as written, then a short training with it."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "neuromodulation.md").read_text()
    section = text.split("## A signal of one's own")[1]
    code = section.split("```python\n")[1].split("```")[0]
    namespace: dict = {}
    try:
        exec(compile(code, "docs/neuromodulation.md", "exec"), namespace)
        assert namespace["model"].policy.modulation_source.rate == 0.2
        model = _model("novelty", env=gym.make("TMazeCue-v0"), learning_rate=0.0)
        model.learn(64)
        assert model.logger.name_to_value["train/approx_kl"] < 1e-7
        signals, _ = model.policy.modulation_source.sequence(
            torch.ones(2, 1, 3, 4), torch.zeros(2, 1), torch.zeros(1, 12), model.policy
        )
        torch.testing.assert_close(signals[:, 0, 0], torch.tensor([1.0, 0.9]))  # |1 - 0|, then |1 - 0.1|
    finally:
        MODULATION_SOURCES.pop("novelty", None)


def test_the_reward_can_reach_the_modulation_only(tmp_path):
    """reward_to_encoder=False: the reversal T-maze's outcome neurons are silent in the network's input, the
    modulator still reads them; the setting survives save and load."""
    raster = torch.zeros(1, 25, 40)
    raster[0, :10, 10:20] = 1.0  # the reward population fired: the previous trial paid
    inputs = {}
    for routed in (True, False):
        model = _model("reward", "TMazeReversal-v0", {"reward_to_encoder": routed})
        if not routed:
            model.save(tmp_path / "m.zip")
            model = PPO.load(tmp_path / "m.zip")
            assert model.policy.snn_config["reward_to_encoder"] is False
        with torch.no_grad():
            out, _ = model.policy.network_step(raster, model.policy.initial_state(1), record=True)
        reward_input = RewardInput(**model.policy.snn_config["reward_input"])
        torch.testing.assert_close(out.modulator[:, 0], read_reward(reward_input, raster, raster=True))
        assert out.modulator.item() > 1.0  # more reward spikes than a trial shows on average: above the reward 1
        inputs[routed] = out.record.input_spikes[0, :, 10:30]
    assert inputs[True][:10, :10].sum() > 0 and inputs[False].sum() == 0
