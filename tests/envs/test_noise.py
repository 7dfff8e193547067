"""Observation, action and joint-friction noise wrappers, the factory and the NoisyHalfCheetah-v5 id."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from sb3_spikeplastic.envs import (
    NOISE_TYPES,
    ActionNoise,
    FrictionNoise,
    ObservationNoise,
    TMazeCueEnv,
    make_noisy_env,
    noise_kwargs,
)

NOMINAL_DAMPING = np.array([6.0, 4.5, 3.0, 4.5, 3.0, 1.5])  # HalfCheetah-v5's six actuated joints
ACTUATED = slice(3, 9)  # their degrees of freedom; 0-2 are the unactuated root
MAKE_WRAPPER = {
    "obs": lambda env, sigma: ObservationNoise(env, sigma),
    "action": lambda env, sigma: ActionNoise(env, sigma),
    "friction": lambda env, sigma: FrictionNoise(env, sigma),
    "geom_friction": lambda env, sigma: FrictionNoise(env, sigma, target="geom_friction"),
}
pytestmark = pytest.mark.usefixtures("mujoco_log_in_tmp")  # HalfCheetah writes ./MUJOCO_LOG.TXT


def cheetah(max_episode_steps: int = 1000) -> gymnasium.Env:
    return gymnasium.make("HalfCheetah-v5", max_episode_steps=max_episode_steps)


def rollout(env: gymnasium.Env, seed: int, actions: np.ndarray, episodes: int = 2) -> list:
    """Everything the environment returns over ``episodes`` episodes (the first one seeded) of fixed actions."""
    out = []
    for episode in range(episodes):
        obs, info = env.reset(seed=seed if episode == 0 else None)
        out.append(obs)
        for action in actions:
            obs, reward, terminated, truncated, info = env.step(action)
            out += [obs, reward, terminated, truncated]
            if terminated or truncated:
                break
    return out


def bitwise_equal(a: list, b: list) -> bool:
    return len(a) == len(b) and all(np.asarray(x).tobytes() == np.asarray(y).tobytes() for x, y in zip(a, b))


ACTIONS = np.random.default_rng(0).uniform(-1, 1, size=(30, 6)).astype(np.float32)


@pytest.mark.filterwarnings("ignore:.*is different from the unwrapped version")
@pytest.mark.filterwarnings("ignore:.*Box observation space m")  # HalfCheetah's observation space is unbounded
@pytest.mark.parametrize("sigma", [0.0, 0.1])
def test_noisy_halfcheetah_passes_the_env_checkers(sigma):
    kwargs = dict(obs_noise=sigma, action_noise=sigma, friction_noise=sigma)
    check_env(gymnasium.make("NoisyHalfCheetah-v5", **kwargs), skip_render_check=True)
    sb3_check_env(gymnasium.make("NoisyHalfCheetah-v5", **kwargs))


def test_noisy_halfcheetah_spec_recreates_the_stack():
    env = gymnasium.make("NoisyHalfCheetah-v5", obs_noise=0.1, action_noise=0.2, friction_noise=0.3)
    assert env.spec.max_episode_steps == 1000
    assert [w.name for w in env.spec.additional_wrappers] == ["FrictionNoise", "ActionNoise", "ObservationNoise"]
    assert bitwise_equal(rollout(env, 1, ACTIONS), rollout(gymnasium.make(env.spec), 1, ACTIONS))
    wrapped = make_noisy_env("HalfCheetah-v5", action_noise=0.2)
    assert bitwise_equal(rollout(wrapped, 1, ACTIONS), rollout(gymnasium.make(wrapped.spec), 1, ACTIONS))


@pytest.mark.parametrize("kind", list(MAKE_WRAPPER))
def test_zero_sigma_is_an_exact_no_op(kind):
    bare = rollout(cheetah(20), 3, ACTIONS)
    env = MAKE_WRAPPER[kind](cheetah(20), 0.0)
    assert bitwise_equal(bare, rollout(env, 3, ACTIONS))
    assert np.array_equal(env.unwrapped.model.dof_damping[ACTUATED], NOMINAL_DAMPING)


@pytest.mark.parametrize("kind", list(MAKE_WRAPPER))
def test_noise_is_seeded_and_separate_from_the_env_stream(kind):
    first = rollout(MAKE_WRAPPER[kind](cheetah(20), 0.3), 3, ACTIONS)
    assert bitwise_equal(first, rollout(MAKE_WRAPPER[kind](cheetah(20), 0.3), 3, ACTIONS))
    assert not bitwise_equal(first, rollout(MAKE_WRAPPER[kind](cheetah(20), 0.3), 4, ACTIONS))
    assert not bitwise_equal(first, rollout(cheetah(20), 3, ACTIONS))
    if kind != "obs":  # the noise never draws from the environment's generator: same initial state as bare
        assert np.array_equal(first[0], cheetah().reset(seed=3)[0])


def test_observation_noise_adds_gaussian_noise_and_keeps_the_dtype():
    def observations(env):
        first, _ = env.reset(seed=0)
        return np.array([first] + [env.step(np.zeros(6, np.float32))[0] for _ in range(200)])

    noisy = observations(ObservationNoise(cheetah(), 0.5))
    z = noisy - observations(cheetah())  # the actions are fixed, so the dynamics are unchanged
    assert noisy.dtype == np.float64
    assert abs(z.mean()) < 0.05 and abs(z.std() - 0.5) < 0.03


def test_observation_noise_on_some_indices_perturbs_only_those_with_the_all_element_draws():
    def observations(env):
        first, _ = env.reset(seed=0)
        return np.array([first] + [env.step(np.zeros(6, np.float32))[0] for _ in range(50)])

    bare = observations(cheetah())
    every = observations(ObservationNoise(cheetah(), 0.5)) - bare
    some = observations(gymnasium.make("NoisyHalfCheetah-v5", obs_noise=0.5, obs_indices=[8, 0, 3])) - bare
    chosen = np.zeros(17, bool)
    chosen[[0, 3, 8]] = True
    assert np.all(some[:, ~chosen] == 0.0)
    assert np.allclose(some[:, chosen], every[:, chosen], atol=1e-12) and np.all(some[:, chosen] != 0.0)
    assert ObservationNoise(cheetah(), 0.5, indices=[8, 0, 3]).indices == (0, 3, 8)


def test_action_noise_is_multiplicative_per_dimension(action_recorder):
    recorder = action_recorder(cheetah())
    env = ActionNoise(recorder, 0.2)
    env.reset(seed=0)
    action = np.full(6, 0.5, np.float32)
    for _ in range(500):
        env.step(action)
    applied = np.array(recorder.actions)
    assert recorder.actions[0].dtype == np.float32
    z = applied / action - 1
    assert abs(z.mean()) < 0.03 and abs(z.std() - 0.2) < 0.02
    assert np.abs(np.corrcoef(z.T) - np.eye(6)).max() < 0.15  # independent across dimensions


@pytest.mark.parametrize("target", ["damping", "geom_friction"])
def test_friction_noise_is_drawn_per_episode_from_the_nominal_values(target):
    env = FrictionNoise(cheetah(10), 0.3, target=target)
    model = env.unwrapped.model
    nominal_damping, nominal_friction = model.dof_damping.copy(), model.geom_friction.copy()
    seen = []
    for episode in range(4):
        _, info = env.reset(seed=0 if episode == 0 else None)
        factors = info["friction_factors"]
        if target == "damping":
            assert factors.shape == (6,)
            assert np.array_equal(model.dof_damping[ACTUATED], NOMINAL_DAMPING * factors)
            assert np.array_equal(model.dof_damping[:3], nominal_damping[:3])
            assert np.array_equal(model.geom_friction, nominal_friction)
            seen.append(model.dof_damping.copy())
        else:
            assert factors.shape == (model.ngeom,)
            assert np.array_equal(model.geom_friction, nominal_friction * factors[:, None])
            assert np.array_equal(model.dof_damping, nominal_damping)
            seen.append(model.geom_friction.copy())
        for _ in range(10):  # held for the whole episode
            *_, truncated, step_info = env.step(np.zeros(6, np.float32))
            assert np.array_equal(step_info["friction_factors"], factors)
        assert truncated
    assert not np.array_equal(seen[0], seen[1])
    env.close()
    assert np.array_equal(model.dof_damping, nominal_damping)
    assert np.array_equal(model.geom_friction, nominal_friction)


def test_friction_factors_are_clipped_at_zero():
    env = FrictionNoise(cheetah(), 3.0)
    factors = np.concatenate([env.reset(seed=seed)[1]["friction_factors"] for seed in range(20)])
    assert (factors == 0).any() and (factors >= 0).all()
    assert (env.unwrapped.model.dof_damping >= 0).all()


def test_make_noisy_env_wraps_only_the_non_zero_noises():
    env = make_noisy_env("HalfCheetah-v5", action_noise=0.1, friction_noise=0.2, max_episode_steps=7)
    assert isinstance(env, ActionNoise) and isinstance(env.env, FrictionNoise)
    assert env.spec.max_episode_steps == 7
    assert isinstance(make_noisy_env(cheetah(), obs_noise=0.1), ObservationNoise)
    bare = cheetah()
    assert make_noisy_env(bare) is bare


def test_noise_kwargs_maps_every_noise_type():
    # every noise type's arguments make make_noisy_env apply that noise, with that sigma, and no other
    wrapper = {"obs": ObservationNoise, "action": ActionNoise, "friction": FrictionNoise}
    for noise_type in NOISE_TYPES:
        env, applied = make_noisy_env(cheetah(), **noise_kwargs(noise_type, 0.3)), []
        while isinstance(env, gymnasium.Wrapper):
            applied += [(type(env), env.sigma)] if type(env) in wrapper.values() else []
            env = env.env
        assert applied == [(wrapper[noise_type], 0.3)], noise_type
    assert noise_kwargs("obs", 0.1) == {"obs_noise": 0.1}
    assert noise_kwargs("action", 0.2) == {"action_noise": 0.2}
    assert noise_kwargs("friction", 0.3, "geom_friction") == {"friction_noise": 0.3, "friction_target": "geom_friction"}
    assert noise_kwargs("obs", 0.1, obs_indices=[2, 3]) == {"obs_noise": 0.1, "obs_indices": [2, 3]}


@pytest.mark.parametrize(
    "make, bad",
    [
        (lambda: ObservationNoise(cheetah(), -0.1), "-0.1"),
        (lambda: ActionNoise(cheetah(), float("nan")), "nan"),
        (lambda: FrictionNoise(cheetah(), float("inf")), "inf"),
        (lambda: FrictionNoise(cheetah(), 0.1, target="frictionloss"), "'frictionloss'"),
        (lambda: FrictionNoise(TMazeCueEnv(), 0.1), "TMazeCueEnv"),
        (lambda: ActionNoise(TMazeCueEnv(), 0.1), "Discrete(2)"),
        (lambda: make_noisy_env("HalfCheetah-v5", obs_noise=-1), "-1"),
        (lambda: make_noisy_env(cheetah(), max_episode_steps=5), "max_episode_steps"),
        (lambda: noise_kwargs("gravity", 0.1), "'gravity'"),
        (lambda: noise_kwargs("action", 0.1, obs_indices=[0]), "'action'"),
        (lambda: ObservationNoise(cheetah(), 0.1, indices=[3, 17]), "17"),
        (lambda: ObservationNoise(cheetah(), 0.1, indices=[]), "[]"),
        (lambda: ObservationNoise(cheetah(), 0.1, indices=[1, 1]), "[1, 1]"),
        (lambda: ObservationNoise(cheetah(), 0.1, indices=[0.5]), "0.5"),
    ],
)
def test_bad_arguments_name_the_value(make, bad):
    with pytest.raises(ValueError) as excinfo:
        make()
    message = str(excinfo.value)
    assert bad in message and "\n" not in message
    if "target" in message:
        assert "'damping'" in message and "'geom_friction'" in message
    if "obs ind" in message:  # a bad index names the accepted range
        assert "[0, 16]" in message
    if "gravity" in message:
        assert all(repr(name) in message for name in NOISE_TYPES)
