"""How the gradient of one step's action grows with the length of backpropagation through time on HalfCheetah.

For each BPTT length L, the network runs L environment steps (from a state warmed on 32 steps) and the sum of the
last step's mean actions is backpropagated; the script prints every parameter's gradient norm. A norm growing
geometrically with L is a self-exciting loop through the state (for positive-mean ``alpha``, the plastic trace's
Hebbian loop, see docs/halfcheetah.md).

Usage::

    python experiments/halfcheetah_gradient_probe.py --rule dp-oja
    python experiments/halfcheetah_gradient_probe.py --rule dp-oja --policy-kwargs "dict(alpha_init_mean=0.0, alpha_init_std=1.0)"
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import sb3_spikeplastic  # noqa: F401  (registers the environments)
from sb3_spikeplastic.config import parse_python_literal
from sb3_spikeplastic.policy import SpikePlasticPolicy


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rule", default="dp-oja")
    parser.add_argument("--steps", type=int, default=10, help="network steps T per environment step")
    parser.add_argument("--encoder-pop-size", type=int, default=10)
    parser.add_argument("--action-pop-size", type=int, default=20)
    parser.add_argument("--policy-kwargs", default="dict()", help="more SpikePlasticPolicy arguments, rl-zoo form")
    parser.add_argument("--lengths", nargs="+", type=int, default=[1, 2, 4, 8, 16, 32])
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    env = VecNormalize(make_vec_env("HalfCheetah-v5", args.n_envs, seed=args.seed), norm_reward=False)
    observations = [env.reset()]
    for _ in range(300):  # random actions; the normalisation statistics settle on the way
        observations.append(env.step(rng.uniform(-1, 1, (args.n_envs, 6)).astype(np.float32))[0])
    obs = torch.tensor(np.array(observations[-(32 + max(args.lengths)):]), dtype=torch.float32)
    policy = SpikePlasticPolicy(env.observation_space, env.action_space, lambda _: 1e-3, rule=args.rule,
                                hidden_sizes=(64, 64), steps=args.steps, encoder_pop_size=args.encoder_pop_size,
                                action_pop_size=args.action_pop_size, **parse_python_literal(args.policy_kwargs))
    snn = policy.snn
    state = snn.initial_state(args.n_envs)
    with torch.no_grad():
        for k in range(32):
            _, state = snn(obs[k], state)
    print("BPTT steps | " + " | ".join(name for name, _ in snn.named_parameters()))
    for length in args.lengths:
        snn.zero_grad()
        outputs, _ = snn.forward_sequence(obs[32:32 + length], torch.zeros(length, args.n_envs), state)
        outputs[-1].action.sum().backward()
        norms = [p.grad.norm().item() if p.grad is not None else 0.0 for _, p in snn.named_parameters()]
        print(f"{length} | " + " | ".join(f"{n:.2e}" for n in norms), flush=True)


if __name__ == "__main__":
    main()
