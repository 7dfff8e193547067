"""The reversal T-maze: API, timeline, seeding, argument checks, and its reference good-arm rates against
simulated policies."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import sb3_spikeplastic.envs  # noqa: F401  -- registers the environments
from sb3_spikeplastic.envs.reversal import (
    TMazeReversalEnv,
    bayes_choice,
    best_memoryless_policy,
    memoryless_rate,
    reference_rates,
)

N = 10  # neurons per population
DECISION, REWARD, NO_REWARD, NOISE = (slice(i * N, (i + 1) * N) for i in range(4))


def test_passes_the_checkers_and_is_registered_at_both_noise_levels():
    check_env(TMazeReversalEnv(), skip_render_check=True)
    sb3_check_env(TMazeReversalEnv())
    assert gymnasium.make("TMazeReversal-v0").unwrapped.p_noise == 0.2
    assert gymnasium.make("TMazeReversalNoisy-v0").unwrapped.p_noise == 0.4


def test_an_episode_is_n_trials_choices_with_the_outcome_shown_next():
    env = TMazeReversalEnv(p_cue_event=1.0, p_cue_rest=0.0, p_noise=0.0)
    obs, _ = env.reset(seed=4)
    assert obs.shape == (25, 40)
    assert obs[:10, REWARD].sum() == obs[:10, NO_REWARD].sum() == 0  # no outcome before the first trial
    assert obs[10:, DECISION].all() and obs[:10, DECISION].sum() == 0
    rewards, infos = [], []
    for trial in range(10):
        obs, reward, terminated, truncated, info = env.step(trial % 2)
        assert info["trial"] == trial and info["choice"] == trial % 2 and not truncated
        assert info["good_arm"] == env.good_arm(trial) and info["good_choice"] == (trial % 2 == info["good_arm"])
        assert reward == float(info["paid"])
        assert terminated == (trial == 9)
        if not terminated:  # the outcome of this choice, and only that, in the next trial's first 10 ms
            assert obs[:10, REWARD].all() == info["paid"] and obs[:10, NO_REWARD].all() == (not info["paid"])
            assert obs[10:, REWARD].sum() == obs[10:, NO_REWARD].sum() == 0
        rewards.append(reward)
        infos.append(info)
    assert infos[-1]["good_choice_rate"] == np.mean([i["good_choice"] for i in infos])
    assert infos[-1]["reversal_trial"] == env.reversal_trial
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_the_good_arm_swaps_once_in_the_window():
    env = TMazeReversalEnv()
    seen_first, seen_reversal = set(), set()
    for seed in range(60):
        env.reset(seed=seed)
        arms = [env.good_arm(t) for t in range(10)]
        r = env.reversal_trial
        assert arms == [env.first_good_arm] * r + [1 - env.first_good_arm] * (10 - r)
        seen_first.add(env.first_good_arm)
        seen_reversal.add(r)
    assert seen_first == {0, 1} and seen_reversal == {4, 5, 6}
    env = TMazeReversalEnv(reversal=False)
    env.reset(seed=0)
    assert env.reversal_trial is None and len({env.good_arm(t) for t in range(10)}) == 1


def test_arms_pay_with_their_probabilities():
    env = TMazeReversalEnv(reversal=False, p_reward=0.8)
    good_paid, bad_paid = [], []
    for seed in range(300):
        env.reset(seed=seed)
        for trial in range(10):
            choice = trial % 2
            _, reward, *_, info = env.step(choice)
            (good_paid if info["good_choice"] else bad_paid).append(reward)
    assert np.mean(good_paid) == pytest.approx(0.8, abs=0.04) and np.mean(bad_paid) == pytest.approx(0.2, abs=0.04)


def test_a_seed_fixes_the_episode_and_the_same_choice_gets_the_same_outcome():
    def play(seed, choices):
        env = TMazeReversalEnv()
        frames = [env.reset(seed=seed)[0]]
        for choice in choices:
            obs, reward, *_ = env.step(choice)
            frames.append(obs)
        return np.stack(frames), env.reversal_trial

    choices = [0, 1, 1, 0, 0, 1, 0, 1, 1, 0]
    a, b = play(7, choices), play(7, choices)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    assert not np.array_equal(a[0], play(8, choices)[0])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(noise="medium"), "noise='medium' is not one of"),
        (dict(n_trials=0), "n_trials=0 must be an integer >= 1"),
        (dict(p_reward=1.5), "p_reward=1.5 must be a probability"),
        (dict(reversal="yes"), "reversal='yes' must be True or False"),
        (dict(reversal_trials=(4,)), "reversal_trials=(4,) must be (first, last)"),
        (dict(reversal_trials=(6, 10)), "must satisfy 1 <= first <= last < n_trials=10"),
        (dict(outcome_ms=0), "outcome_ms=0 must be an integer >= 1"),
    ],
)
def test_bad_arguments_are_one_line_errors(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")) as error:
        TMazeReversalEnv(**kwargs)
    assert "\n" not in str(error.value)


def simulated_rate(choose, n_episodes: int, seed: int = 0) -> float:
    """Good-arm rate of ``choose(env, choices, outcomes, shown)`` over ``n_episodes`` episodes of the default env;
    ``shown``: the outcome the current trial shows (0 none, 1 paid, 2 not paid), read from its spikes."""
    env = TMazeReversalEnv(p_cue_event=1.0, p_cue_rest=0.0, p_noise=0.0)
    rng = np.random.default_rng(seed)
    good = 0
    for episode in range(n_episodes):
        obs, _ = env.reset(seed=seed + episode)
        choices, outcomes = [], []
        for _ in range(10):
            shown = 1 if obs[:10, REWARD].any() else 2 if obs[:10, NO_REWARD].any() else 0
            choice = choose(env, choices, outcomes, shown, rng)
            obs, reward, terminated, _, info = env.step(choice)
            choices.append(choice)
            outcomes.append(bool(reward))
            good += info["good_choice"]
    return good / (10 * n_episodes)


def test_reference_rates_are_what_the_policies_reach():
    """Each reference rate is exact (computed); simulated on the environment it falls within 4 standard errors."""
    rates = reference_rates()
    assert rates["random"] == 0.5 and rates["oracle"] == 1.0
    assert rates["memoryless"] == pytest.approx(0.5938, abs=1e-3) and rates["bayes"] == pytest.approx(0.8554, abs=1e-3)
    policy, rate = best_memoryless_policy()
    assert rate == rates["memoryless"] and rate > memoryless_rate((0.5, 0.5, 0.5)) == pytest.approx(0.5)
    n = 1500
    tolerance = 4 * np.sqrt(0.25 / (10 * n))  # trials within an episode are correlated: a generous bound
    memoryless = simulated_rate(lambda env, c, o, shown, rng: int(rng.random() >= policy[shown]), n)
    assert memoryless == pytest.approx(rates["memoryless"], abs=2 * tolerance)
    bayes = simulated_rate(lambda env, c, o, shown, rng: bayes_choice(c, o), n)
    assert bayes == pytest.approx(rates["bayes"], abs=2 * tolerance)
    oracle = simulated_rate(lambda env, c, o, shown, rng: env.good_arm(len(c)), 50)
    assert oracle == 1.0
    assert simulated_rate(lambda env, c, o, shown, rng: int(rng.integers(2)), n) == pytest.approx(0.5, abs=tolerance)


def test_the_bayesian_learner_follows_the_evidence():
    assert bayes_choice([], []) == 0  # a tie: left
    assert bayes_choice([0, 0], [False, False]) == 1  # left failed twice: right is the good arm
    assert bayes_choice([1, 1, 1], [True, True, True]) == 1
    # Four trials of a paying right arm, then right fails twice after the reversal window opened: switch.
    assert bayes_choice([1, 1, 1, 1, 1, 1], [True, True, True, True, False, False]) == 0


@pytest.mark.parametrize("noise", ["low", "high"])
def test_the_reward_input_reads_the_previous_reward_from_the_spikes(noise):
    """Averaged over trials, what the declared reward input reads from a raster is the reward the previous trial
    paid (1 or 0), and 0.5 in the first trial."""
    import torch

    from sb3_spikeplastic.sb3.modulation import RewardInput, read_reward

    env = TMazeReversalEnv(noise=noise)
    reward_input = RewardInput.parse(env.reward_input, env.observation_space)
    read = {None: [], 0.0: [], 1.0: []}
    for seed in range(150):
        obs, _ = env.reset(seed=seed)
        previous, done = None, False
        while not done:
            read[previous].append(read_reward(reward_input, torch.as_tensor(obs), raster=True).item())
            obs, reward, done, _, _ = env.step(seed % 2)
            previous = float(reward)
    assert np.mean(read[None]) == pytest.approx(0.5, abs=0.03)
    assert np.mean(read[1.0]) == pytest.approx(1.0, abs=0.03)
    assert np.mean(read[0.0]) == pytest.approx(0.0, abs=0.03)
