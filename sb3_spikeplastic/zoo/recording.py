"""One episode of a spiking policy with everything its network did, for figures and inspection.

:func:`record_episode` runs one episode of a policy on a single environment and keeps the input, hidden and output
spikes, membrane potentials, modulation and traces as an :class:`EpisodeActivity`
(:func:`sb3_spikeplastic.zoo.figures.activity_figure` draws it); :func:`inspection_episodes` and
:func:`typical_seed` choose which episodes ``inspect`` and ``enjoy`` show.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Optional

import gymnasium
import numpy as np
import torch
from gymnasium import spaces


@dataclasses.dataclass
class EpisodeActivity:
    """Everything the network did during (the first ``max_steps`` steps of) one episode, as numpy arrays.

    Time runs over network steps (1 ms each): ``n_steps * steps_per_env_step`` of them.

    :param input_spikes: ``(time, n_in)`` input spikes.
    :param spikes: per layer (hidden layers, then the output population) ``(time, n)`` spikes.
    :param membrane: per layer ``(time, n)`` membrane potentials.
    :param modulation: per layer ``(n_intervals, n)`` neuromodulatory signal of each plasticity interval, or
        ``None`` for unmodulated layers.
    :param traces: per layer ``(n_intervals, n_out, n_in)`` trace ``E`` after each interval, or ``None`` for
        static layers.
    :param steps_per_env_step: network steps ``T`` per environment step.
    :param interval: network steps per plasticity interval.
    :param theta: firing threshold.
    :param actions: the actions taken.
    :param rewards: the rewards received.
    :param done: whether the episode ended within the recorded steps.
    :param info: the last step's ``info``.
    :param rule: the plasticity rule's name.
    :param input_groups: optional ``(label, first, stop)`` ranges of input neurons (e.g. T-maze populations).
    """

    input_spikes: np.ndarray
    spikes: list[np.ndarray]
    membrane: list[np.ndarray]
    modulation: list[Optional[np.ndarray]]
    traces: list[Optional[np.ndarray]]
    steps_per_env_step: int
    interval: int
    theta: float
    actions: list[Any]
    rewards: list[float]
    done: bool
    info: dict
    rule: str = ""
    input_groups: Optional[list[tuple[str, int, int]]] = None

    @property
    def n_steps(self) -> int:
        """Environment steps recorded."""
        return len(self.rewards)

    @property
    def episode_return(self) -> float:
        return float(np.sum(self.rewards))


def tmaze_input_groups(env: gymnasium.Env) -> Optional[list[tuple[str, int, int]]]:
    """The input populations of a ``TMazeCueEnv`` (left cue, right cue, decision, noise), else ``None``."""
    from sb3_spikeplastic.envs.tmaze import TMazeCueEnv

    inner = env.unwrapped
    if not isinstance(inner, TMazeCueEnv):
        return None
    n = inner.neurons_per_population
    return [(label, i * n, (i + 1) * n) for i, label in enumerate(("left cue", "right cue", "decision", "noise"))]


def inspection_episodes(env_id: str, env_kwargs: Mapping[str, Any]) -> dict[str, Callable[[], gymnasium.Env]]:
    """The episodes ``sb3-spikeplastic inspect`` draws, as environment factories: ``typical`` (its seed chosen by
    :func:`typical_seed`), and for the cue
    T-maze also ``all_left`` and ``all_right`` (every cue on one side) and ``no_cue`` (every cue population,
    the decision cue's too, at its rest rate throughout: the decision is made on the decision cue alone)."""
    from ..envs.tmaze import TMazeCueEnv

    kwargs = dict(env_kwargs)
    episodes = {"typical": lambda: gymnasium.make(env_id, **kwargs)}
    probe = gymnasium.make(env_id, **kwargs)
    maze = probe.unwrapped
    probe.close()
    if isinstance(maze, TMazeCueEnv):
        episodes["all_left"] = lambda: gymnasium.make(env_id, **{**kwargs, "cues": [0] * maze.n_cues})
        episodes["all_right"] = lambda: gymnasium.make(env_id, **{**kwargs, "cues": [1] * maze.n_cues})
        episodes["no_cue"] = lambda: gymnasium.make(env_id, **{**kwargs, "p_cue_event": maze.p_cue_rest})
    return episodes


@torch.no_grad()
def typical_seed(
    policy,
    make_env: Callable[[], gymnasium.Env],
    seed: int = 0,
    n_episodes: int = 10,
    deterministic: bool = True,
    obs_transform: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    max_steps: int = 1000,
) -> tuple[int, Optional[str]]:
    """A reset seed whose episode ends the way most do: the first of ``seed .. seed + n_episodes - 1`` whose
    ``info["is_success"]`` is the majority's, and a note such as ``"9 of 10 episodes from seed 0 succeeded"``.

    An environment that reports no success (or episodes longer than ``max_steps``) gives ``(seed, None)``: only
    short episodic tasks are scanned, so that a figure of a model that succeeds 98 % of the time is not, by the
    luck of one seed, a failure.
    """
    outcomes = []
    for k in range(n_episodes):
        env = make_env()
        try:
            episode = record_episode(
                policy,
                env,
                seed=seed + k,
                deterministic=deterministic,
                max_steps=max_steps,
                obs_transform=obs_transform,
            )
        finally:
            env.close()
        if not episode.done or "is_success" not in episode.info:
            return seed, None
        outcomes.append(bool(episode.info["is_success"]))
    majority = sum(outcomes) * 2 >= len(outcomes)
    return seed + outcomes.index(majority), (f"{sum(outcomes)} of {n_episodes} episodes from seed {seed} succeeded")


@torch.no_grad()
def record_episode(
    policy,
    env: gymnasium.Env,
    seed: Optional[int] = 0,
    deterministic: bool = True,
    max_steps: Optional[int] = None,
    obs_transform: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    network_seed: int = 0,
) -> EpisodeActivity:
    """Run one episode of a :class:`~sb3_spikeplastic.SpikePlasticPolicy` on a single (non-vectorised) environment
    and record the network's activity step by step (``policy.network_step(obs, state, record=True)``), from the initial
    (reset) network state.

    The global random generators are not touched when ``deterministic`` (the input spikes come from the network's
    counter-based sampler), so calling this during training does not change the training run.

    :param policy: the policy.
    :param env: a Gymnasium environment with the policy's spaces.
    :param seed: ``env.reset(seed=...)``: the same seed shows the same episode (e.g. the same cues) every time.
    :param deterministic: mean / arg-max actions.
    :param max_steps: record at most this many environment steps (``None``: about one second of network time,
        ``max(1, 1000 // T)`` steps).
    :param obs_transform: applied to each observation before the policy (e.g. ``VecNormalize.normalize_obs``).
    :param network_seed: seed of the input sampler's stream.
    """
    net = policy.snn
    T = net.steps
    if max_steps is None:
        max_steps = max(1, 1000 // T)
    obs, info = env.reset(seed=seed)
    state = policy.initial_state(1, seed=network_seed)
    records, actions, rewards, done = [], [], [], False
    for _ in range(max_steps):
        x = obs_transform(obs) if obs_transform is not None else obs
        x = torch.as_tensor(np.asarray(x, dtype=np.float32)[None], device=policy.device)
        out, state = policy.network_step(policy._preprocess(x), state, record=True)
        action = policy._distribution(out).get_actions(deterministic=deterministic).cpu().numpy()[0]
        if isinstance(policy.action_space, spaces.Box):
            action = policy.clip_actions(action.reshape(policy.action_space.shape))
        else:
            action = int(np.asarray(action).reshape(-1)[0])
        obs, reward, terminated, truncated, info = env.step(action)
        records.append(out.record)
        actions.append(action)
        rewards.append(float(reward))
        if terminated or truncated:
            done = True
            break

    def cat(tensors, axis=0):
        return np.concatenate([t[0].float().cpu().numpy() for t in tensors], axis)

    n_layers = len(net.layers)
    return EpisodeActivity(
        input_spikes=cat([r.input_spikes for r in records]),
        spikes=[cat([r.spikes[i] for r in records]) for i in range(n_layers)],
        membrane=[cat([r.membrane[i] for r in records]) for i in range(n_layers)],
        modulation=[
            cat([r.modulation[i] for r in records]) if records[0].modulation[i] is not None else None
            for i in range(n_layers)
        ],
        traces=[
            cat([r.traces[i] for r in records]) if records[0].traces[i] is not None else None for i in range(n_layers)
        ],
        steps_per_env_step=T,
        interval=net.interval,
        theta=float(net.neuron.theta),
        actions=actions,
        rewards=rewards,
        done=done,
        info=dict(info),
        rule=str(getattr(net, "rule_name", "")),
        input_groups=tmaze_input_groups(env),
    )
