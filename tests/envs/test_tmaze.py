"""The spiking cue-association T-maze: API, timeline, spike statistics, labels, seeding, argument checks."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import sb3_spikeplastic.envs  # noqa: F401  -- registers the environments
from sb3_spikeplastic.envs import TMazeCueEnv

N = 10  # neurons per population
LEFT, RIGHT, DECISION, NOISE = (slice(i * N, (i + 1) * N) for i in range(4))
PROBABILITIES = {"low": (0.75, 0.05, 0.2), "high": (0.65, 0.25, 0.4)}  # appendix 5.4: event, rest, noise


def episode_raster(env: gymnasium.Env, seed: int, action: int = 0) -> tuple[np.ndarray, dict]:
    """All frames of one episode stacked into a (ms, 40) raster, and the final step's info."""
    obs, _ = env.reset(seed=seed)
    frames = [obs]
    while True:
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated:
            return np.concatenate(frames), info
        frames.append(obs)


def oracle_success(env_id: str, n_episodes: int, neurons: int = N) -> float:
    """Success of a policy that names the side whose first ``neurons`` cue neurons spiked more so far."""
    env = gymnasium.make(env_id)
    successes = 0
    for seed in range(n_episodes):
        obs, _ = env.reset(seed=seed)
        left = right = 0.0
        while True:
            left += obs[:, LEFT][:, :neurons].sum()
            right += obs[:, RIGHT][:, :neurons].sum()
            obs, _, terminated, _, info = env.step(int(right > left))  # only the last frame's action counts
            if terminated:
                successes += info["is_success"]
                break
    return successes / n_episodes


@pytest.mark.filterwarnings("ignore:.*unconventional shape")  # SB3 prefers 1D; the raster is (frame_ms, 40)
@pytest.mark.parametrize("env_id", ["TMazeCue-v0", "TMazeCueNoisy-v0"])
def test_registered_ids_pass_the_env_checkers(env_id):
    check_env(gymnasium.make(env_id).unwrapped, skip_render_check=True)
    sb3_check_env(gymnasium.make(env_id))


def test_spaces_and_noise_levels_of_the_registered_ids():
    low, high = gymnasium.make("TMazeCue-v0").unwrapped, gymnasium.make("TMazeCueNoisy-v0").unwrapped
    assert low.observation_space == gymnasium.spaces.Box(0, 1, (25, 40), np.float32)
    assert low.action_space == gymnasium.spaces.Discrete(2)
    assert (low.p_cue_event, low.p_cue_rest, low.p_noise) == PROBABILITIES["low"]
    assert (high.p_cue_event, high.p_cue_rest, high.p_noise) == PROBABILITIES["high"]
    assert TMazeCueEnv(noise="high", p_noise=0.1).p_noise == 0.1  # explicit probabilities win


def test_timeline_is_whole_frames_within_the_horizon():
    env = TMazeCueEnv()
    assert env.cue_phase_ms == 7 * 25 + 6 * 25
    assert [env.lead_in_ms(r) for r in (45, 75, 105)] == [5, 0, 20]
    assert [env.episode_length_ms(r) for r in (45, 75, 105)] == [400, 425, 475]
    seen = set()
    for seed in range(30):
        raster, _ = episode_raster(env, seed)
        seen.add(env.rest_ms)
        assert raster.shape == (env.episode_length_ms(env.rest_ms), 40)
        assert env.n_frames * 25 == len(raster) <= 500
    assert seen == {45, 75, 105}


@pytest.mark.parametrize("frame_ms", [1, 10, 50])
def test_other_frame_lengths_keep_the_decision_at_the_end(frame_ms):
    env = TMazeCueEnv(frame_ms=frame_ms, p_cue_event=1.0, p_cue_rest=0.0, p_noise=0.0)
    raster, info = episode_raster(env, seed=3)
    assert raster.shape[1:] == (40,) and len(raster) % frame_ms == 0
    decision = np.flatnonzero(raster[:, DECISION].any(axis=1))
    assert decision.tolist() == list(range(len(raster) - 25, len(raster)))
    assert info["correct_action"] == env.correct_action


@pytest.mark.parametrize("noise", ["low", "high"])
def test_firing_probabilities_match_the_configuration(noise):
    """Pooled over 150 episodes, each (population, period) fires at its probability within 5 standard errors."""
    p_event, p_rest, p_noise = PROBABILITIES[noise]
    env = TMazeCueEnv(noise=noise)
    spikes = {"event": [], "rest": [], "noise": []}
    for seed in range(150):
        raster, _ = episode_raster(env, seed)
        # The timeline from its documented end: decision (25 ms) after the rest, cue i at 50 ms strides before.
        event = np.zeros_like(raster, dtype=bool)
        event[-25:, DECISION] = True
        cue_phase_start = len(raster) - 25 - env.rest_ms - 325
        for i, side in enumerate(env.cues):
            start = cue_phase_start + 50 * i
            event[start : start + 25, RIGHT if side else LEFT] = True
        cue_neurons = np.zeros(40, dtype=bool)
        cue_neurons[:30] = True
        spikes["event"].append(raster[event])
        spikes["rest"].append(raster[~event & cue_neurons])
        spikes["noise"].append(raster[:, NOISE].ravel())
    for period, p in (("event", p_event), ("rest", p_rest), ("noise", p_noise)):
        samples = np.concatenate(spikes[period])
        tolerance = 5 * np.sqrt(p * (1 - p) / samples.size)
        assert abs(samples.mean() - p) < tolerance, (noise, period, samples.mean(), p, tolerance)


def test_oracle_solves_it_and_a_constant_policy_is_at_chance():
    assert oracle_success("TMazeCue-v0", 200) >= 0.95
    env = gymnasium.make("TMazeCue-v0")
    constant = np.mean([episode_raster(env, seed, action=1)[1]["is_success"] for seed in range(200)])
    assert 0.35 <= constant <= 0.65


def test_high_noise_is_harder():
    # Ten neurons per side make the majority obvious at both levels; one neuron per side shows the difference.
    low, high = oracle_success("TMazeCue-v0", 400, neurons=1), oracle_success("TMazeCueNoisy-v0", 400, neurons=1)
    assert high < low - 0.03, (low, high)


def test_reward_only_on_the_decision_frame():
    env = TMazeCueEnv()
    env.reset(seed=5)
    correct = env.correct_action
    assert correct == int(sum(env.cues) > 3)
    for _ in range(env.n_frames - 1):
        obs, reward, terminated, truncated, info = env.step(1 - correct)  # wrong actions before the end are free
        assert (reward, terminated, truncated, info) == (0.0, False, False, {})
    obs, reward, terminated, truncated, info = env.step(correct)
    assert (reward, terminated, truncated) == (1.0, True, False)
    assert info == {"is_success": True, "correct_action": correct}
    assert obs.shape == (25, 40) and not obs.any()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=5)
    for _ in range(env.n_frames - 1):
        env.step(correct)
    assert env.step(1 - correct)[1:3] == (-1.0, True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_action_masks_open_both_actions_only_on_the_decision_frame(seed):
    env = gymnasium.make("TMazeCueNoisy-v0")
    env.reset(seed=seed)
    n_frames = env.unwrapped.n_frames
    masks = []
    for _ in range(n_frames):
        masks.append(env.get_wrapper_attr("action_masks")().tolist())
        *_, terminated, _, _ = env.step(0)
    assert terminated
    assert masks == [[True, False]] * (n_frames - 1) + [[True, True]]


def test_seeding():
    env = gymnasium.make("TMazeCue-v0")
    first, _ = episode_raster(env, 7)
    cues = list(env.unwrapped.cues)
    second, _ = episode_raster(env, 7)
    assert env.unwrapped.cues == cues and np.array_equal(first, second)
    other, _ = episode_raster(env, 8)
    assert first.shape != other.shape or not np.array_equal(first, other)


def test_fixed_cues_share_the_noise_of_the_seed():
    all_left, all_right = TMazeCueEnv(cues=[0] * 7), TMazeCueEnv(cues=[1] * 7)
    left, info_left = episode_raster(all_left, 11)
    right, info_right = episode_raster(all_right, 11)
    assert all_left.cues == [0] * 7 and info_left["correct_action"] == 0 and info_right["correct_action"] == 1
    assert all_left.rest_ms == all_right.rest_ms
    assert np.array_equal(left[:, NOISE], right[:, NOISE])
    assert left[:, LEFT].sum() > 5 * left[:, RIGHT].sum()


@pytest.mark.parametrize(
    "kwargs, bad",
    [
        ({"noise": "medium"}, "'medium'"),
        ({"n_cues": 6}, "6"),
        ({"n_cues": 0}, "0"),
        ({"cue_ms": 2.5}, "2.5"),
        ({"gap_ms": -1}, "-1"),
        ({"frame_ms": 0}, "0"),
        ({"rest_choices_ms": ()}, "()"),
        ({"rest_choices_ms": (45, -5)}, "-5"),
        ({"p_cue_event": 1.5}, "1.5"),
        ({"p_noise": float("nan")}, "nan"),
        ({"cues": [0, 1]}, "[0, 1]"),
        ({"cues": [0, 1, 2, 0, 1, 0, 1]}, "2"),
        ({"horizon_ms": 400}, "400"),
        ({"render_mode": "human"}, "'human'"),
    ],
)
def test_bad_arguments_name_the_value(kwargs, bad):
    with pytest.raises(ValueError) as excinfo:
        TMazeCueEnv(**kwargs)
    message = str(excinfo.value)
    assert bad in message and "\n" not in message
    if "noise" in kwargs:
        assert "'low'" in message and "'high'" in message


def test_bad_action_is_rejected():
    env = TMazeCueEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action=2"):
        env.step(2)
