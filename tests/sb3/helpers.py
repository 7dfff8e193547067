"""Small spiking plastic PPO models on the cue T-maze, for the tests of every folder.

A plain module, not a test module: pytest's ``pythonpath`` (pyproject.toml) puts this folder on ``sys.path``, and the
subprocesses of test_ppo.py import it from this folder, their working directory.
"""

from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.zoo.config import model_arguments, normalize_arguments, resolve_hyperparams


def vec(make, n, seed=0):
    """``n`` monitored environments from ``make``, seeded."""
    env = DummyVecEnv([lambda: Monitor(make()) for _ in range(n)])
    env.seed(seed)
    return env


def tmaze(n=2, **env_kwargs):
    """``n`` small cue T-mazes (4 neurons per population unless given)."""
    env_kwargs = {"neurons_per_population": 4, **env_kwargs}
    return vec(lambda: TMazeCueEnv(**env_kwargs), n)


def tmaze_model(rule="ndp-oja", n_envs=2, env_kwargs=None, **ppo_kwargs):
    """A small spiking plastic PPO on the T-maze (one hidden layer of 16; one 32-step rollout per update)."""
    kwargs = dict(
        n_steps=32, batch_size=32, bptt_steps=16, n_epochs=1, seed=0, policy_kwargs=dict(rule=rule, hidden_sizes=(16,))
    )
    return PPO("SpikePlasticPolicy", tmaze(n_envs, **(env_kwargs or {})), **{**kwargs, **ppo_kwargs})


def shipped_model(env_id, conf=None, rule=None, seed=0, **overrides):
    """A model of the packaged entry of ``env_id`` (``conf``: another packaged file; ``rule``: the entry's rule
    replaced) with ``overrides`` (e.g. a smaller rollout), on ``make_vec_env`` environments seeded with ``seed``,
    normalised by VecNormalize where the entry says so."""
    config = resolve_hyperparams(env_id, conf, [f"{k}={v}" for k, v in overrides.items()], rule=rule)
    policy, ppo_kwargs, policy_kwargs = model_arguments(config)
    env = make_vec_env(env_id, config["n_envs"], seed=seed)
    norm = normalize_arguments(config)
    if norm is not None:
        env = VecNormalize(env, **norm)
    return PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs, seed=seed)
