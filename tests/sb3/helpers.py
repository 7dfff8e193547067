"""Shared test helpers (importable from the test modules: pytest puts tests/ on sys.path)."""

import numpy as np
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv


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
    kwargs = dict(n_steps=32, batch_size=32, bptt_steps=16, n_epochs=1, seed=0,
                  policy_kwargs=dict(rule=rule, hidden_sizes=(16,)))
    return PPO("SpikePlasticPolicy", tmaze(n_envs, **(env_kwargs or {})), **{**kwargs, **ppo_kwargs})


def deterministic_success(model, env, n_episodes):
    """Success rate (``info["is_success"]``) of ``model`` over the first ``n_episodes`` episodes that end in the
    vectorised, already seeded ``env``, with deterministic actions and the recurrent state carried through."""
    obs, state, starts, successes = env.reset(), None, np.ones(env.num_envs, bool), []
    while len(successes) < n_episodes:
        actions, state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
        obs, _, starts, infos = env.step(actions)
        successes += [infos[i]["is_success"] for i in np.flatnonzero(starts)]
    return float(np.mean(successes[:n_episodes]))


#: A CartPole hyperparameter file of a few hundred steps (MlpPolicy: no spike kernels to compile), for commands
#: that train many short runs (optimize, grid).
TINY_CARTPOLE = """CartPole-v1:
  policy: MlpPolicy
  n_timesteps: 512
  n_envs: 2
  n_steps: 32
  batch_size: 32
  n_epochs: 1
"""


def run_cli(capsys, *argv):
    """``sb3-spikeplastic ARGV`` in this process: ``(exit status, stdout, stderr)``."""
    from sb3_spikeplastic import cli

    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err
