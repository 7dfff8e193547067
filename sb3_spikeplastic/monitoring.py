"""What the spiking network is doing: TensorBoard scalars (``snn/``, ``plasticity/``), figures and hyperparameters.

* :class:`RolloutActivity` accumulates per-layer statistics over a rollout (cheap: the rates are computed
  anyway) and records them, with the traces' state at the rollout's end, through SB3's logger;
  :class:`RolloutActivityCallback` does this for every rollout (:class:`sb3_spikeplastic.PPO` adds it to ``learn``
  for spiking policies).
* :func:`record_episode` runs one episode of a policy on a single environment and keeps everything the network did
  (input, hidden and output spikes, membrane potentials, modulation, traces) as an :class:`EpisodeActivity`;
  :func:`sb3_spikeplastic.figures.activity_figure` draws it.
* :class:`ActivityFigureCallback` logs that figure to TensorBoard (``snn/activity``) every few rollouts.
* :func:`write_hyperparameters` writes a run's hyperparameters to TensorBoard once, as a Markdown table.
* :func:`spike_counts` and :func:`synaptic_operations` give the energy proxies of one environment step (spikes and
  SynOps per layer); :class:`EnergyMeter` averages them over any code that runs the network (e.g. an evaluation).
* :func:`inspect_command` is ``sb3-spikeplastic inspect``: the activity figures of :func:`inspection_episodes`.

Matplotlib is imported only when a figure is drawn, and only through ``matplotlib.figure.Figure`` (the Agg
renderer, no GUI backend).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from torch import Tensor
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Figure, Logger, TensorBoardOutputFormat

from .energy import energy_estimate, plasticity_operations
from .network import NetworkOutput, NetworkState, SpikingPlasticNetwork


def spike_counts(out: NetworkOutput, steps: int) -> Tensor:
    """Spikes per environment step and environment, averaged over the batch: ``(n_layers + 1,)``, the input
    population first, then the hidden layers and the output population.

    :param out: one environment step's output (with ``input_rate``).
    :param steps: network steps per environment step ``T`` (the rates are means over them).
    """
    return torch.stack([r.sum(-1).mean() for r in (out.input_rate, *out.rates)]) * steps


def synaptic_operations(spikes: Tensor, sizes: Sequence[int]) -> Tensor:
    """Synaptic operations (SynOps) per layer, the neuromorphic convention for the energy of a spiking network: each
    presynaptic spike is delivered to every neuron of the next layer, so SynOps = presynaptic spikes x fan-out.

    :param spikes: :func:`spike_counts` ``(n_layers + 1,)``.
    :param sizes: population sizes, input first (``SpikingPlasticNetwork.sizes``).
    :return: ``(n_layers,)``, layer ``i``'s incoming synaptic events.
    """
    return spikes[:-1] * torch.as_tensor(sizes[1:], dtype=spikes.dtype, device=spikes.device)


class EnergyMeter:
    """Mean spikes and SynOps per environment step over every forward pass of ``network`` inside the ``with``
    block (a forward hook: evaluation code, ``model.predict`` and rollouts are measured unchanged).

    ::

        with EnergyMeter(model.policy.snn) as meter:
            evaluate_policy(model, env, n_eval_episodes=10)
        print(meter.summary())

    :param network: the policy's network (``policy.snn``).
    """

    def __init__(self, network: SpikingPlasticNetwork):
        self.network = network
        self.env_steps = 0
        self._sums: Optional[Tensor] = None

    def _hook(self, module, inputs, output) -> None:
        out = output[0]
        batch = out.action.shape[0]
        counts = spike_counts(out, self.network.steps).detach() * batch
        self._sums = counts if self._sums is None else self._sums + counts
        self.env_steps += batch

    def __enter__(self) -> "EnergyMeter":
        self._handle = self.network.register_forward_hook(self._hook)
        return self

    def __exit__(self, *exc) -> None:
        self._handle.remove()

    def summary(self) -> dict[str, Any]:
        """``spikes_per_step`` (input first, then each layer), ``synops_per_step`` (per layer) and their totals
        ``total_spikes_per_step`` / ``total_synops_per_step`` (without the input's spikes, which the encoder
        makes), averaged over the environment steps measured; the plasticity's own work per step,
        ``plasticity_macs_per_step`` (per layer; ``None`` for a rule of one's own) and its total; and the energy
        estimate ``energy_nj`` (:func:`sb3_spikeplastic.energy.energy_estimate`)."""
        if not self.env_steps:
            raise RuntimeError("no environment step was measured")
        spikes = self._sums.double().cpu() / self.env_steps
        synops = synaptic_operations(spikes, self.network.sizes)
        plastic = plasticity_operations(self.network)
        return {"spikes_per_step": spikes.tolist(), "synops_per_step": synops.tolist(),
                "total_spikes_per_step": float(spikes[1:].sum()), "total_synops_per_step": float(synops.sum()),
                "plasticity_macs_per_step": plastic,
                "total_plasticity_macs_per_step": None if plastic is None else float(sum(plastic)),
                "energy_nj": energy_estimate(synops.tolist(), plastic)}


class RolloutActivity:
    """Running per-layer statistics of a rollout.

    Recorded per layer ``i``: ``snn/layer{i}/spike_rate`` (spikes per neuron per ms), ``snn/layer{i}/silent_fraction``
    (neurons that did not fire during an environment step), and for plastic layers ``plasticity/layer{i}/eta``,
    ``trace_abs_mean`` and ``trace_clip_fraction`` (synapses with ``|E| >= 0.99 E_max``) over the environments'
    traces at the end of the rollout, and for neuromodulated rules ``modulation_mean`` / ``modulation_std`` of
    :math:`M = W_m r_{post}` over the rollout's steps.

    Also recorded: ``plasticity/layer{i}/alpha_abs_mean`` (mean ``|alpha|`` of plastic layers) and, when ``policy``
    has a Gaussian action distribution, ``snn/action_std`` (``exp(log_std)`` averaged over action dimensions).

    Energy, per environment step and environment: ``snn/input/spikes_per_step``, ``snn/layer{i}/spikes_per_step``,
    ``snn/layer{i}/synops_per_step`` (:func:`synaptic_operations`) and the totals ``snn/spikes_per_step`` and
    ``snn/synops_per_step``.

    :param network: the policy's network.
    :param policy: the policy (optional; for ``snn/action_std``).
    """

    #: rollout steps whose rates are kept before their statistics are added up, all in one batch of tensor ops: a
    #: dozen small ops on every step took ~10 % of a HalfCheetah rollout's time (paper network, 8 environments)
    BATCH_STEPS = 64

    def __init__(self, network: SpikingPlasticNetwork, policy: Optional[torch.nn.Module] = None):
        self.network = network
        self.policy = policy
        self.reset()

    def reset(self) -> None:
        self.steps = 0
        # (n_layers, 4) sums over steps on the network's device: rate, silent fraction, modulation, modulation
        # squared (each a mean over the step's environments and neurons), and the spike counts. Kept there until
        # `record`, so that a rollout step never waits for the device (which would stall a GPU).
        self._sums: Optional[torch.Tensor] = None
        self._spikes: Optional[torch.Tensor] = None
        self._unsummed: list[tuple[Optional[Tensor], ...]] = []  # (input_rate, *rates) of the latest steps

    @torch.no_grad()
    def add(self, out: NetworkOutput) -> None:
        """Accumulate one rollout step's rates (all environments)."""
        self.steps += 1
        self._unsummed.append((out.input_rate, *out.rates))
        if len(self._unsummed) >= self.BATCH_STEPS:
            self._sum_up()

    def _sum_up(self) -> None:
        """Add the kept steps' statistics to the sums, each population's steps stacked ``(k, batch, n)``."""
        if not self._unsummed:
            return
        k = len(self._unsummed)
        input_rates, *layer_rates = [list(column) for column in zip(*self._unsummed)]
        self._unsummed = []
        rates = [torch.stack(column) for column in layer_rates]
        if input_rates[0] is not None:  # spike_counts of every step, summed
            spikes = torch.stack([r.sum(-1).mean(-1).sum() for r in (torch.stack(input_rates), *rates)])
            spikes = spikes * self.network.steps
            self._spikes = spikes if self._spikes is None else self._spikes + spikes
        rows = []
        for layer, r in zip(self.network.layers, rates):
            if layer.plastic and layer.rule.modulated:
                m = layer.rule.modulation(r)
                modulation = (m.mean(), m.pow(2).mean())
            else:
                modulation = (r.new_zeros(()), r.new_zeros(()))
            rows.append(torch.stack([r.mean(), (r == 0).float().mean(), *modulation]))
        stats = torch.stack(rows) * k  # every step's mean has the same weight
        self._sums = stats if self._sums is None else self._sums + stats

    @torch.no_grad()
    def record(self, logger: Logger, state: NetworkState) -> None:
        """Write the statistics of the rollout and of the final traces to ``logger``."""
        if self.steps == 0:
            return
        self._sum_up()
        means = (self._sums.double() / self.steps).tolist()
        if self._spikes is not None:
            spikes = self._spikes.double() / self.steps
            synops = synaptic_operations(spikes, self.network.sizes)
            logger.record("snn/input/spikes_per_step", spikes[0].item())
            logger.record("snn/spikes_per_step", spikes[1:].sum().item())
            logger.record("snn/synops_per_step", synops.sum().item())
            for i in range(len(self.network.layers)):
                logger.record(f"snn/layer{i}/spikes_per_step", spikes[i + 1].item())
                logger.record(f"snn/layer{i}/synops_per_step", synops[i].item())
        log_std = getattr(self.policy, "log_std", None)
        if isinstance(log_std, torch.Tensor):
            logger.record("snn/action_std", torch.exp(log_std).mean().item())
        for i, (layer, layer_state) in enumerate(zip(self.network.layers, state.layers)):
            rate, silent, modulation, modulation_sq = means[i]
            logger.record(f"snn/layer{i}/spike_rate", rate)
            logger.record(f"snn/layer{i}/silent_fraction", silent)
            if not layer.plastic:
                continue
            rule, trace = layer.rule, layer_state.plastic.trace
            logger.record(f"plasticity/layer{i}/eta", rule.eta.item())
            logger.record(f"plasticity/layer{i}/alpha_abs_mean", layer.alpha.abs().mean().item())
            logger.record(f"plasticity/layer{i}/trace_abs_mean", trace.abs().mean().item())
            logger.record(f"plasticity/layer{i}/trace_clip_fraction", (trace.abs() >= 0.99 * rule.e_max).float().mean().item())
            if rule.modulated:
                logger.record(f"plasticity/layer{i}/modulation_mean", modulation)
                logger.record(f"plasticity/layer{i}/modulation_std", max(modulation_sq - modulation**2, 0.0) ** 0.5)


class RolloutActivityCallback(BaseCallback):
    """:class:`RolloutActivity` of every rollout of a spiking policy, recorded at the rollout's end.

    It reads the rollout loop's variables that :class:`sb3_spikeplastic.PPO` hands to its callbacks: ``out`` (the
    step's :class:`~sb3_spikeplastic.network.NetworkOutput`) and ``state`` (the network state). For other policies
    it does nothing.
    """

    def _on_training_start(self) -> None:
        snn = getattr(self.model.policy, "snn", None)
        self.activity = None if snn is None else RolloutActivity(snn, self.model.policy)

    def _on_rollout_start(self) -> None:
        if self.activity is not None:
            self.activity.reset()

    def _on_step(self) -> bool:
        if self.activity is not None and "out" in self.locals:
            self.activity.add(self.locals["out"])
        return True

    def _on_rollout_end(self) -> None:
        if self.activity is not None and "state" in self.locals:
            self.activity.record(self.logger, self.locals["state"])


# --------------------------------------------------------------------------------------------------------------------
# One episode's activity, for figures


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
    from .envs.tmaze import TMazeCueEnv

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
def typical_seed(policy, make_env: Callable[[], gymnasium.Env], seed: int = 0, n_episodes: int = 10,
                 deterministic: bool = True, obs_transform: Optional[Callable[[np.ndarray], np.ndarray]] = None,
                 max_steps: int = 1000) -> tuple[int, Optional[str]]:
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
            episode = record_episode(policy, env, seed=seed + k, deterministic=deterministic, max_steps=max_steps,
                                     obs_transform=obs_transform)
        finally:
            env.close()
        if not episode.done or "is_success" not in episode.info:
            return seed, None
        outcomes.append(bool(episode.info["is_success"]))
    majority = sum(outcomes) * 2 >= len(outcomes)
    return seed + outcomes.index(majority), (f"{sum(outcomes)} of {n_episodes} episodes from seed {seed} "
                                             "succeeded")


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
    and record the network's activity step by step (``policy.snn(obs, state, record=True)``), from the initial
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
        out, state = net(policy._preprocess(x), state, record=True)
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
        modulation=[cat([r.modulation[i] for r in records]) if records[0].modulation[i] is not None else None
                    for i in range(n_layers)],
        traces=[cat([r.traces[i] for r in records]) if records[0].traces[i] is not None else None
                for i in range(n_layers)],
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


class ActivityFigureCallback(BaseCallback):
    """Every ``every`` rollouts, log a figure of one episode's network activity to TensorBoard (``snn/activity``):
    input / hidden / output spike rasters, output membrane potentials, the traces of a few synapses and the
    modulatory signals (:func:`sb3_spikeplastic.figures.activity_figure`).

    The episode runs on a separate single environment made by ``env`` (never a training environment), always reset
    with the same ``seed``, so successive figures show the same episode (e.g. the same T-maze cues) as training
    goes on. With ``VecNormalize`` the training statistics normalise its observations (without updating them).

    :param env: an environment id, or a function returning a fresh environment.
    :param every: rollouts between figures (>= 1).
    :param env_kwargs: ``gymnasium.make`` arguments when ``env`` is an id.
    :param seed: reset seed of the episode.
    :param max_steps: environment steps recorded (see :func:`record_episode`).
    :param deterministic: mean / arg-max actions.
    :param tag: the logger key.
    """

    def __init__(self, env: Union[str, Callable[[], gymnasium.Env]], every: int = 10,
                 env_kwargs: Optional[Mapping[str, Any]] = None, seed: int = 0, max_steps: Optional[int] = None,
                 deterministic: bool = True, tag: str = "snn/activity", verbose: int = 0):
        super().__init__(verbose)
        if int(every) < 1:
            raise ValueError(f"every={every!r} must be >= 1 rollout")
        if isinstance(env, str):
            env_id, kwargs = env, dict(env_kwargs or {})
            self._make_env: Callable[[], gymnasium.Env] = lambda: gymnasium.make(env_id, **kwargs)
            self._title = env_id
        else:
            self._make_env = env
            self._title = ""
        self.every, self.seed, self.max_steps = int(every), seed, max_steps
        self.deterministic, self.tag = deterministic, tag
        self.n_rollouts = 0
        self._env: Optional[gymnasium.Env] = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.n_rollouts += 1
        if self.n_rollouts % self.every:
            return
        self.logger.record(self.tag, Figure(self.make_figure(), close=True), exclude=("stdout", "log", "json", "csv"))

    def make_figure(self):
        """Record the episode and draw its figure (a ``matplotlib.figure.Figure``)."""
        from .figures import activity_figure

        if self._env is None:
            self._env = self._make_env()
            if not self._title and self._env.spec is not None:
                self._title = self._env.spec.id
        vec_normalize = self.model.get_vec_normalize_env()
        obs_transform = vec_normalize.normalize_obs if vec_normalize is not None and vec_normalize.norm_obs else None
        policy = self.model.policy
        was_training = policy.training
        policy.set_training_mode(False)
        try:
            activity = record_episode(policy, self._env, seed=self.seed, deterministic=self.deterministic,
                                      max_steps=self.max_steps, obs_transform=obs_transform)
        finally:
            policy.set_training_mode(was_training)
        return activity_figure(activity, title=f"{self._title}  step {self.num_timesteps:,}")

    def _on_training_end(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


# --------------------------------------------------------------------------------------------------------------------
# Hyperparameters


def flatten_config(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings flattened to dotted keys (``policy_kwargs.rule``)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten_config(value, name + "."))
        else:
            flat[name] = value
    return flat


def hyperparameter_markdown(config: Mapping[str, Any]) -> str:
    """A Markdown table (``| hyperparameter | value |``) of a (nested) configuration."""
    lines = ["| hyperparameter | value |", "|---|---|"]
    for key, value in flatten_config(config).items():
        text = str(value).replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {key} | {text} |")
    return "\n".join(lines)


def write_hyperparameters(logger: Logger, config: Mapping[str, Any], tag: str = "hyperparameters", step: int = 0) -> bool:
    """Write ``config`` as a Markdown table to the TensorBoard outputs of an SB3 ``logger`` (TensorBoard's TEXT
    tab). Returns whether there was a TensorBoard output to write to."""
    written = False
    for output in logger.output_formats:
        if isinstance(output, TensorBoardOutputFormat):
            output.writer.add_text(tag, hyperparameter_markdown(config), step)
            output.writer.flush()
            written = True
    return written


def inspect_command(run: Optional[str] = None, model: Optional[str] = None, env: Optional[str] = None,
                    vecnormalize: Optional[str] = None, best: bool = False,
                    env_kwargs: Optional[Sequence[str]] = None, output: Optional[str] = None, seed: int = 0,
                    max_steps: Optional[int] = None, deterministic: bool = True, no_progress: bool = False,
                    device: str = "cpu", torch_threads: int = 1,
                    folder: Optional[str] = None, exp_id: int = 0, load_checkpoint: Optional[int] = None,
                    load_last_checkpoint: bool = False) -> Callable[[], int]:
    """``sb3-spikeplastic inspect`` with these options (its long names): the model is found, loaded and checked
    (``ValueError``, nothing written); returns the inspection, which records each of :func:`inspection_episodes`
    (``typical`` from :func:`typical_seed`), draws it into ``<output>/activity_<name>.png`` (default:
    ``<run>/figures``), prints a line per episode and returns 0."""
    from .evaluation import check_fits
    from .inputs import check_output_path, model_source
    from .run_folder import load_model, make_eval_env

    if output:
        check_output_path(output, "-o/--output", directory=True)
    info, env_id = model_source(run, model, env, vecnormalize, best, env_kwargs, folder, exp_id,
                                load_checkpoint, load_last_checkpoint)
    torch.set_num_threads(torch_threads)
    loaded = load_model(info, device)
    if not hasattr(loaded.policy, "snn"):
        raise ValueError(f"{str(info.model_path)!r} is not a SpikePlasticPolicy model")
    obs_transform = None
    if info.vecnormalize is not None:
        from stable_baselines3.common.vec_env import VecNormalize

        stats = VecNormalize.load(str(info.vecnormalize), make_eval_env(env_id, 1, 0, info.env_kwargs))
        obs_transform = stats.normalize_obs
    check_fits(loaded, info, env_id, make_error=f"cannot make {env_id}")
    episodes = inspection_episodes(env_id, info.env_kwargs)
    out = Path(output) if output else (info.run_dir / "figures" if info.run_dir else Path("figures"))

    def inspect() -> int:
        import matplotlib
        from tqdm.auto import tqdm

        matplotlib.use("Agg")
        from .figures import activity_figure

        out.mkdir(parents=True, exist_ok=True)
        bar = tqdm(episodes.items(), total=len(episodes), unit="episode", disable=no_progress, dynamic_ncols=True,
                   leave=False)
        for name, make in bar:
            episode_seed, note = seed, None
            if name == "typical":
                episode_seed, note = typical_seed(loaded.policy, make, seed, deterministic=deterministic,
                                                  obs_transform=obs_transform)
            episode_env = make()
            try:
                activity = record_episode(loaded.policy, episode_env, seed=episode_seed, deterministic=deterministic,
                                          max_steps=max_steps, obs_transform=obs_transform)
            finally:
                episode_env.close()
            if name == "no_cue":  # the decision is made on the decision cue alone
                activity.info.pop("correct_action", None)
            fig = activity_figure(activity, title=f"{env_id} · {name.replace('_', ' ')}")
            path = out / f"activity_{name}.png"
            fig.savefig(path, dpi=110)
            detail = f" (seed {episode_seed}: {note})" if note else ""
            bar.write(f"{name:>9}: return {activity.episode_return:.3g} over {activity.n_steps} steps{detail} "
                      f"-> {path}")
        return 0

    return inspect
