"""Memory acceptance test (as sb3-contrib does with CartPoleNoVel): a cue–delay–decision task that a stateless
policy cannot solve is solved by a plastic policy, while the fixed-weight SNN stays near chance.

Task: one cue (left or right, 25 ms), a delay of 75 or 105 ms of background noise, then the decision frame. At
the decision the cue's PSP has decayed to ~1 % of its peak (alpha kernel, tau_s = 10 ms), so only a memory that
outlasts the delay — here the plastic trace E — can tell the sides apart. Runtime ~1 min on one core.
"""

import helpers
import torch
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv

ENV_KWARGS = dict(n_cues=1, rest_choices_ms=(75, 105))
POLICY_KWARGS = dict(hidden_sizes=[32], plastic_layers=[0], w_init_gain=[3, 9], w_init_mean=[0, 0.2],
                     action_pop_size=8, logit_scale_init=10)


def make_env():
    return Monitor(TMazeCueEnv(**ENV_KWARGS))


def deterministic_success(model, n_episodes=200, n_envs=20, seed=123):
    env = DummyVecEnv([make_env for _ in range(n_envs)])
    env.seed(seed)
    return helpers.deterministic_success(model, env, n_episodes)


def train(rule, timesteps=12_288):
    torch.manual_seed(0)
    env = DummyVecEnv([make_env for _ in range(8)])
    env.seed(0)
    model = PPO("SpikePlasticPolicy", env, n_steps=64, batch_size=256, bptt_steps=32, n_epochs=4,
                learning_rate=3e-3, max_grad_norm=1.0, seed=0, policy_kwargs=dict(rule=rule, **POLICY_KWARGS))
    model.learn(timesteps)
    return model


def test_plastic_policy_solves_cue_delay_decision_and_static_does_not():
    plastic = deterministic_success(train("dp-oja"))
    static = deterministic_success(train("static"))
    assert plastic >= 0.9, f"plastic success {plastic}"
    assert static <= 0.7, f"static success {static}"
