"""Where a trained T-maze policy loses the answer: memory (the plastic trace) or readout (the decision frame).

Runs a trained model (deterministic, held-out seeds) and records, at each episode's decision frame,

* the trace ``E`` of the first (plastic) layer as it enters the decision frame (what the synapses remember),
* the hidden layer's firing rates during the decision frame (what the output layer sees),
* the policy's decision,

then fits an L2-regularised logistic regression (a linear probe) from each of the first two to the correct side on
75 % of the episodes and reports its accuracy on the other 25 %, beside the policy's own accuracy. A probe that
is right more often than the policy shows that the information is there and lost later: if the trace probe
beats the hidden-rate probe, reading the trace out through one frame of input spikes is the bottleneck.

A third probe reads the noise-free plastic input of each hidden neuron, ``(alpha * E) x`` with the decision
frame's spikes ``x`` replaced by their mean: what one weighted sum per neuron keeps of the trace. A fourth reads,
per hidden neuron, the sum of its left-cue trace columns minus the sum of its right-cue ones: what one sum per
neuron could keep with a sign-structured ``alpha``.

As a reference for what the input spikes allow, it also reports a spike counter on the same episodes: the
decision ``left-population spikes > right-population spikes``, counted over the whole episode (two numbers of
memory, no learning).

Usage::

    python experiments/tmaze_probe.py results/tmaze/runs/TMazeCueNoisy-v0_dp-oja_0/ppo/TMazeCueNoisy-v0_1
    python experiments/tmaze_probe.py RUN_FOLDER --episodes 4000 --env TMazeCueNoisy-v0
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium
import numpy as np
import torch
import yaml

import sb3_spikeplastic.envs  # noqa: F401  (registers the maze ids)
from sb3_spikeplastic import PPO

#: Episode seeds start here: far from the training and evaluation seeds of `sb3-spikeplastic train`.
PROBE_SEED = 2_000_000


def record(policy, env_id: str, episodes: int, batch: int = 100, env_kwargs: dict | None = None
           ) -> dict[str, np.ndarray]:
    """Per episode: the layer-0 trace entering the decision frame, the hidden rates during it, the policy's
    logit difference (right - left), the correct side, the cue margin and the input's left-right spike count."""
    rows: dict[str, list] = {"trace": [], "hidden": [], "logit_diff": [], "correct": [], "count_diff": [], "margin": [],
                              "decision_input": []}
    for start in range(0, episodes, batch):
        envs = [gymnasium.make(env_id, **(env_kwargs or {})) for _ in range(min(batch, episodes - start))]
        n = len(envs)
        obs = np.stack([env.reset(seed=PROBE_SEED + start + i)[0] for i, env in enumerate(envs)])
        last = np.array([env.unwrapped.n_frames - 1 for env in envs])
        rows["correct"].append([env.unwrapped.correct_action for env in envs])
        rows["margin"].append([abs(2 * sum(env.unwrapped.cues) - len(env.unwrapped.cues)) for env in envs])
        state = policy.initial_state(n)
        trace = np.zeros((n, state.layers[0].plastic.trace[0].numel()))
        hidden, diff = np.zeros((n, policy.snn.sizes[1])), np.zeros(n)
        count_diff = np.zeros(n)  # left minus right population spikes so far
        decision_input = np.zeros((n, obs.shape[-1]))  # each input's firing rate in the decision frame
        pop = envs[0].unwrapped.neurons_per_population
        with torch.no_grad():
            for t in range(last.max() + 1):
                at_decision = last == t
                running = t <= last
                count_diff[running] += obs[running, :, :pop].sum((1, 2)) - obs[running, :, pop:2 * pop].sum((1, 2))
                trace[at_decision] = state.layers[0].plastic.trace.flatten(1)[torch.as_tensor(at_decision)].numpy()
                decision_input[at_decision] = obs[at_decision].mean(1)
                starts = torch.full((n,), float(t == 0))
                _, _, _, state, out = policy.step(torch.as_tensor(obs), state, starts, deterministic=True)
                hidden[at_decision] = out.rates[0][torch.as_tensor(at_decision)].numpy()
                diff[at_decision] = (out.action[:, 1] - out.action[:, 0])[torch.as_tensor(at_decision)].numpy()
                for i, env in enumerate(envs):
                    if t < last[i]:
                        obs[i] = env.step(0)[0]  # actions before the decision frame are ignored by the maze
        rows["trace"].append(trace)
        rows["hidden"].append(hidden)
        rows["logit_diff"].append(diff)
        rows["count_diff"].append(count_diff)
        rows["decision_input"].append(decision_input)
    return {k: np.concatenate([np.asarray(v) for v in vs]) for k, vs in rows.items()}


def probe_accuracy(features: np.ndarray, labels: np.ndarray, train_fraction: float = 0.75, l2: float = 1e-3) -> float:
    """Held-out accuracy of an L2-regularised logistic regression (standardised features, LBFGS)."""
    x = torch.as_tensor(features, dtype=torch.float64)
    y = torch.as_tensor(labels, dtype=torch.float64)
    train = torch.arange(len(y)) < int(train_fraction * len(y))
    mean, std = x[train].mean(0), x[train].std(0) + 1e-9
    x = (x - mean) / std
    w = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
    b = torch.zeros((), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.LBFGS([w, b], max_iter=500, line_search_fn="strong_wolfe")

    def closure():
        optimizer.zero_grad()
        logits = x[train] @ w + b
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, y[train]) + l2 * w.square().sum()
        loss.backward()
        return loss

    optimizer.step(closure)
    with torch.no_grad():
        return (((x[~train] @ w + b) > 0).double() == y[~train]).double().mean().item()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="run folder of `sb3-spikeplastic train` (its final model) or a .zip")
    parser.add_argument("--env", help="maze id (default: the run's)")
    parser.add_argument("--episodes", type=int, default=2000)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.run.suffix == ".zip":
        model_path, env_id = args.run, args.env
    else:
        env_id = args.env or args.run.name.rsplit("_", 1)[0]
        model_path = args.run / f"{env_id}.zip"
    if env_id is None:
        parser.error("--env is needed with a .zip model")
    # The run's environment arguments (e.g. frame_ms), as `sb3-spikeplastic train` saved them.
    config = model_path.parent / env_id / "config.yml"
    env_kwargs = yaml.safe_load(config.read_text())[env_id].get("env_kwargs") if config.exists() else None
    policy = PPO.load(model_path, device="cpu").policy
    data = record(policy, env_id, args.episodes, env_kwargs=env_kwargs)
    test = np.arange(len(data["correct"])) >= int(0.75 * len(data["correct"]))
    own = ((data["logit_diff"] > 0) == data["correct"])[test].mean()
    counter = ((data["count_diff"] < 0) == data["correct"])[test].mean()
    print(f"{model_path} on {env_id}, {args.episodes} episodes (probes: 75 % fit, 25 % held out)")
    print(f"  policy's decision                       {own:.3f}")
    print(f"  linear probe on the hidden rates         {probe_accuracy(data['hidden'], data['correct']):.3f}")
    print(f"  linear probe on the layer-0 trace E      {probe_accuracy(data['trace'], data['correct']):.3f}")
    # What the hidden layer can get of E: its plastic input (alpha * E) x with the decision frame's input spikes
    # x replaced by their mean over episodes (no input noise), one number per hidden neuron.
    alpha = policy.snn.layers[0].alpha.detach().cpu().numpy()
    trace = data["trace"].reshape(-1, *alpha.shape)
    drive = (alpha * trace * data["decision_input"].mean(0)).sum(-1)
    print("  linear probe on the noise-free plastic input per hidden neuron "
          f"{probe_accuracy(drive, data['correct']):.3f}")
    # What a sign-structured alpha (+ on one cue population's columns, - on the other's) would read instead.
    pop = alpha.shape[1] // 4
    left_minus_right = trace[..., :pop].sum(-1) - trace[..., pop:2 * pop].sum(-1)
    print("  linear probe on left-minus-right trace sums per hidden neuron "
          f"{probe_accuracy(left_minus_right, data['correct']):.3f}")
    print(f"  spike counter (left - right, whole episode) {counter:.3f}")
    right = (data["logit_diff"] > 0) == data["correct"]
    for margin in np.unique(data["margin"]):
        split = data["margin"] == margin
        print(f"  policy's decision on {margin}-cue margins ({split.mean():.0%} of episodes) {right[split].mean():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
