"""``SpikePlasticPolicy``: the plastic spiking network as a Stable-Baselines3 actor-critic policy.

This is the only module that knows SB3 policies. The policy is recurrent: its network state (filters, traces)
is carried across environment steps by :class:`sb3_spikeplastic.PPO` during rollouts and by
:meth:`SpikePlasticPolicy.predict` (``state`` / ``episode_start``) everywhere else, so SB3's
``evaluate_policy`` and ``EvalCallback`` work unchanged. The state is never stored on the policy.
"""

from __future__ import annotations

import copy
import inspect
import math
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.distributions import CategoricalDistribution, DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import Schedule
from torch import Tensor, nn

from ..snn.coding import ContinuousDecoder, DiscreteDecoder, ObservationStandardizer, PopulationEncoder, RasterInput
from ..snn.network import NetworkOutput, NetworkState, SpikingPlasticNetwork
from ..snn.neurons import SRMParameters
from ..snn.plasticity import LEARNED_SOURCE, available_rules, get_rule_class
from .ablation import AblatedState, Ablation, ablate
from .modulation import ModulationSource, RewardInput, get_modulation_source

MISUSE_MESSAGE = (
    "SpikePlasticPolicy is recurrent (its synapses and neurons carry state across environment steps) and needs "
    "the recurrent PPO: use `from sb3_spikeplastic import PPO` instead of stable_baselines3.PPO"
)


def is_spike_raster_space(space: spaces.Space) -> bool:
    """A ``Box`` of shape ``(T, n)`` with bounds ``[0, 1]`` is taken as a spike raster (e.g. ``TMazeCue``)."""
    return (
        isinstance(space, spaces.Box)
        and len(space.shape) == 2
        and bool(np.all(space.low == 0))
        and bool(np.all(space.high == 1))
    )


#: Network steps T per environment step for vector observations when ``steps`` is not given (spike rasters: their
#: length).
VECTOR_STEPS = 10

#: Defaults of :class:`SpikePlasticPolicy` before the current ones. A model saved then records only the arguments
#: its user gave, so :meth:`sb3_spikeplastic.PPO.load` rebuilds it with these (:func:`previous_defaults_filled`).
PREVIOUS_DEFAULTS = dict(encoder_pop_size=50, encoder_beta=15.0, critic="snn", log_std_init=0.0, standardize_obs=False)


def previous_defaults_filled(policy_kwargs: dict, observation_space: spaces.Space, action_space: spaces.Space) -> dict:
    """``policy_kwargs`` of a model saved before the current defaults, with the defaults it was built with (T =
    50, 50 place cells with beta 15, 100 output neurons per action dimension, tau_s 10 ms, the spiking critic,
    ``log_std_init`` 0, no standardisation, the NDP rules' linear modulation). ``alpha``'s initialisation is
    left out: the saved parameters replace it."""
    kwargs = {**PREVIOUS_DEFAULTS, **policy_kwargs}
    if not is_spike_raster_space(observation_space):
        kwargs["steps"] = kwargs.get("steps") or 50
        kwargs["neuron"] = {"tau_s": 10.0, **(kwargs.get("neuron") or {})}
    if isinstance(action_space, spaces.Box):
        kwargs["action_pop_size"] = kwargs.get("action_pop_size") or 100
    if "modulation" in inspect.signature(get_rule_class(kwargs.get("rule", "dp-oja")).__init__).parameters:
        kwargs["rule_kwargs"] = {"modulation": "linear", **(kwargs.get("rule_kwargs") or {})}
    return kwargs


class SpikePlasticPolicy(ActorCriticPolicy):
    """Actor-critic policy whose actor is a spiking network with differentiable plasticity (SpikePropamine).

    Observations: a 1-D ``Box`` is population-encoded (place cells); a ``Box`` of shape ``(T, n)`` in ``[0, 1]``
    is a spike raster and passes straight through (then ``T`` is the raster length). Actions: ``Box`` through the
    paper's ±1 half-population decoder and a Gaussian with a learned state-independent ``log_std``;
    ``Discrete`` through one output population per action, rates times a learned scale as logits.
    The critic is a small MLP on the spike rates of every layer (``critic="snn"``: it sees the plastic memory) or
    on the observation (``critic="mlp"``: memoryless).

    The defaults for vector observations are the CPU-sized network that learns HalfCheetah
    (``PPO("SpikePlasticPolicy", "HalfCheetah-v5")``; measurements in ``docs/halfcheetah.md``), not the paper's
    50 ms / 50-cell network (``hyperparams/paper.yml``): ``steps=10``, 10 place cells per dimension with
    ``encoder_beta=0.5`` (the paper's overlap of neighbouring cells at that spacing), 20 output neurons per action
    dimension, ``tau_s = T / 5`` ms, zero-mean ``alpha`` (a positive mean makes the trace's Hebbian loop
    self-exciting on place-cell inputs and BPTT gradients overflow), the memoryless critic, ``log_std_init=-2``
    (SB3: 0) and a running standardisation of unbounded observation dimensions into the encoder's range.
    Spike-raster observations keep the paper's neuron constants, the rules' positive ``alpha`` and the spiking
    critic (the cue T-maze needs its memory).

    :param observation_space: observation space.
    :param action_space: action space (``Box`` or ``Discrete``).
    :param lr_schedule: learning-rate schedule.
    :param rule: plasticity rule name (``static``, ``dp-linear``, ``dp-oja``, ``dp-bcm``, ``ndp-oja``,
        ``ndp-bcm`` or any registered with :func:`~sb3_spikeplastic.snn.plasticity.register_rule`).
    :param hidden_sizes: neurons per hidden layer (paper: ``(64, 64)``).
    :param steps: network steps ``T`` per environment step (1 ms each; paper HalfCheetah: 50). ``None``: the
        raster length for spike observations, else 10.
    :param plastic_layers: indices of the plastic layers (0 is input->first hidden, the last is the output
        layer) or ``"all"``.
    :param neuron: SRM constants as a dict of :class:`~sb3_spikeplastic.snn.neurons.SRMParameters` fields
        (``theta``, ``tau_s``, ``tau_ref``, ``scale_ref``, ``tau_rho``, ``scale_rho``, ``dt``). With
        population-encoded observations ``tau_s`` defaults to ``T / 5`` ms (the paper's 10 ms at T = 50, 2 ms at
        the default T = 10), so that an input's PSP peaks within the environment step; otherwise 10 ms.
    :param e_max: trace clip bound :math:`E_{max}`.
    :param plasticity_interval: :math:`\\Delta\\tau` in network steps (must divide ``steps``; default ``steps``).
    :param rule_kwargs: extra arguments of the rule (e.g. ``eta_init``; ``modulation="linear"`` for the NDP rules'
        unbounded modulation as the paper writes it, instead of their default ``tanh``; ``modulation_source`` for
        their neuromodulation from outside the network: ``"reward"``, ``"td-error"`` or a registered source,
        :mod:`sb3_spikeplastic.sb3.modulation`).
    :param encoder_pop_size: place cells per observation dimension (paper: 50; default 10).
    :param encoder_beta: place-cell sharpness (paper: 15 for 50 cells over [-3, 3]; default 0.5 keeps the
        paper's overlap ``beta * spacing^2 = 0.22`` for 10 cells: with 15, values between two centres fire
        neither cell above the floor).
    :param encoder_p_min: floor spike probability (paper: 0.05).
    :param obs_bounds: ``(low, high)`` for the encoder where the observation space is unbounded (scalars or
        arrays): the range of the standardised values. Finite space bounds are used as they are.
    :param obs_indices: the observation dimensions the encoder encodes (``None``: all). The paper's HalfCheetah
        network encodes the 6 joint angles and 6 joint velocities, indices ``[2..7, 11..16]`` of HalfCheetah-v5.
    :param input_rms_rate: expected rms firing probability of spike-raster inputs (weight init only).
    :param action_pop_size: output neurons per action dimension (continuous, even; paper: 100) or per action
        (discrete). ``None``: 20 for ``Box``, 1 for ``Discrete``.
    :param logit_scale_init: initial scale of the discrete decoder's logits.
    :param w_init_gain: initial weight spread per layer
        (see :class:`~sb3_spikeplastic.snn.network.SpikingPlasticNetwork`).
    :param w_init_mean: initial weight mean per layer.
    :param alpha_init_mean: initial plasticity-coefficient mean per layer (``None``: 0 for population-encoded
        observations, the rule's default for spike rasters).
    :param alpha_init_std: initial plasticity-coefficient std per layer (``None``: 1 for population-encoded
        observations, 10% of the mean for spike rasters).
    :param critic: ``"snn"`` (value from the spiking layers' rates) or ``"mlp"`` (memoryless MLP on the
        standardised observation). ``None``: ``"snn"`` for spike rasters, ``"mlp"`` for vectors.
    :param critic_hidden: hidden units of the critic's MLP.
    :param log_std_init: initial log standard deviation of the Gaussian actions (SB3: 0). -2 (std 0.14): with
        std 1 HalfCheetah's control cost alone is about -0.6 per step and swamps the first rollouts' returns.
    :param alpha_lr_scale: learning-rate multiplier of the plasticity coefficients ``alpha`` (an optimizer
        parameter group; :class:`sb3_spikeplastic.PPO` keeps the ratio when the learning rate changes). Adam moves
        every parameter by about the learning rate per update whatever its size, and ``alpha`` starts about ten
        times larger than ``W``: with one shared rate it barely leaves its initial values, so the network cannot
        learn which synapses' traces to read. 1 is the plain shared rate (the T-maze entry's value and its
        measurements: ``docs/reproducing-tmaze.md``).
    :param standardize_obs: standardise the observation dimensions whose space bounds are infinite with running
        statistics (:class:`~sb3_spikeplastic.snn.coding.ObservationStandardizer`, ``policy.obs_standardizer``),
        updated by :class:`sb3_spikeplastic.PPO` after each rollout's update and saved with the model; the
        encoder then clips them to ``obs_bounds``. Dimensions with finite bounds and spike rasters are never
        changed. Composes with ``VecNormalize`` (its output is then standardised again, close to the identity);
        ``False`` leaves observations as they come.
    :param reward_input: where the observation carries the previous step's reward, for the modulation sources that
        read it (:class:`~sb3_spikeplastic.sb3.modulation.RewardInput`: an index, a list of indices or a dict of its
        fields). ``None``: :class:`sb3_spikeplastic.PPO` takes the environment's ``reward_input`` attribute (the
        :class:`~sb3_spikeplastic.envs.PreviousReward` wrapper's, ``TMazeReversal-v0``'s). The element is never
        standardised.
    :param modulation_kwargs: settings of the modulation source (``td-error``: ``gamma``, by default PPO's).
    :param reward_to_encoder: whether the encoder also sees the ``reward_input`` elements (or neurons); ``False``
        routes the reward to the modulation only (the encoder sees zeros there).
    :param ablation: plasticity ablation that :meth:`predict` applies (:mod:`sb3_spikeplastic.sb3.ablation`:
        ``"none"``, ``"frozen"``, ``"reset-every:N"``, ``"shuffled"`` or an
        :class:`~sb3_spikeplastic.sb3.ablation.Ablation`; also settable later as ``policy.ablation``); training never
        applies it.
    :param kwargs: passed to :class:`~stable_baselines3.common.policies.ActorCriticPolicy` (optimizer etc.).
    """

    recurrent = True

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        rule: str = "dp-oja",
        hidden_sizes: Sequence[int] = (64, 64),
        steps: Optional[int] = None,
        plastic_layers: Union[str, Sequence[int]] = "all",
        neuron: Optional[dict] = None,
        e_max: float = 1.0,
        plasticity_interval: Optional[int] = None,
        rule_kwargs: Optional[dict] = None,
        encoder_pop_size: int = 10,
        encoder_beta: float = 0.5,
        encoder_p_min: float = 0.05,
        obs_bounds: tuple = (-3.0, 3.0),
        obs_indices: Optional[Sequence[int]] = None,
        input_rms_rate: float = 0.25,
        action_pop_size: Optional[int] = None,
        logit_scale_init: float = 20.0,
        w_init_gain: Union[float, Sequence[float]] = 3.0,
        w_init_mean: Union[float, Sequence[float]] = 0.0,
        alpha_init_mean: Optional[Union[float, Sequence[float]]] = None,
        alpha_init_std: Optional[Union[float, Sequence[float]]] = None,
        critic: Optional[str] = None,
        critic_hidden: int = 64,
        log_std_init: float = -2.0,
        alpha_lr_scale: float = 1.0,
        standardize_obs: bool = True,
        reward_input: Union[dict, int, Sequence[int], None] = None,
        modulation_kwargs: Optional[dict] = None,
        reward_to_encoder: bool = True,
        ablation: Union[str, Ablation, None] = None,
        **kwargs: Any,
    ):
        if kwargs.pop("use_sde", False):
            raise ValueError("use_sde=True is not supported by SpikePlasticPolicy (its actions come from spike rates)")
        if (
            isinstance(alpha_lr_scale, bool)
            or not isinstance(alpha_lr_scale, (int, float))
            or not (0 < alpha_lr_scale < float("inf"))
        ):
            raise ValueError(f"alpha_lr_scale={alpha_lr_scale!r} must be a positive finite number (1: no scaling)")
        if critic not in (None, "snn", "mlp"):
            raise ValueError(f"unknown critic {critic!r}; accepted: snn, mlp")
        if not isinstance(action_space, (spaces.Box, spaces.Discrete)):
            raise ValueError(f"SpikePlasticPolicy supports Box and Discrete actions, got {action_space}")
        if not isinstance(observation_space, spaces.Box):
            raise ValueError(f"SpikePlasticPolicy supports Box observations, got {observation_space}")
        raster = is_spike_raster_space(observation_space)
        if not raster and len(observation_space.shape) != 1:
            raise ValueError(
                f"observation shape {observation_space.shape} is neither a vector (population-encoded) nor a "
                "(T, n) spike raster with bounds [0, 1]"
            )
        if steps is not None and (isinstance(steps, bool) or int(steps) != steps or steps < 1):
            raise ValueError(f"steps={steps!r} must be a positive integer (network steps T per environment step)")
        if raster and obs_indices is not None:
            raise ValueError(
                "obs_indices selects dimensions of a population-encoded vector; spike-raster "
                "observations pass through whole"
            )
        if raster and steps is not None and steps != observation_space.shape[0]:
            raise ValueError(f"steps={steps} does not match the spike-raster length {observation_space.shape[0]}")
        steps = int(observation_space.shape[0] if raster else (steps or VECTOR_STEPS))
        self._ablation = Ablation.parse(ablation)
        neuron = dict(neuron or {})
        rule_kwargs = dict(rule_kwargs or {})
        modulation = inspect.signature(get_rule_class(rule).__init__).parameters.get("modulation")
        if modulation is not None and modulation.default is not inspect.Parameter.empty:
            rule_kwargs.setdefault("modulation", modulation.default)  # recorded: a saved model keeps its form
        critic = critic or ("snn" if raster else "mlp")
        if reward_input is not None:
            reward_input = RewardInput.parse(reward_input, observation_space).as_dict()
        modulation_kwargs = dict(modulation_kwargs or {})
        source = rule_kwargs.get("modulation_source", LEARNED_SOURCE)
        if source != LEARNED_SOURCE:
            rule_kwargs["modulation_channels"] = _check_modulation_source(source, rule, critic, reward_input).channels
        if not raster:
            neuron.setdefault("tau_s", steps / 5.0)
            if alpha_init_mean is None:
                alpha_init_mean = 0.0
                alpha_init_std = 1.0 if alpha_init_std is None else alpha_init_std
        # Defaults are resolved here, so that a saved model records the values it was built with.
        self.snn_config = dict(
            rule=rule,
            hidden_sizes=tuple(int(h) for h in hidden_sizes),
            steps=steps,
            plastic_layers=plastic_layers,
            neuron=neuron,
            e_max=e_max,
            plasticity_interval=plasticity_interval,
            rule_kwargs=rule_kwargs,
            encoder_pop_size=encoder_pop_size,
            encoder_beta=encoder_beta,
            encoder_p_min=encoder_p_min,
            obs_bounds=tuple(obs_bounds),
            obs_indices=None if obs_indices is None else [int(i) for i in obs_indices],
            input_rms_rate=input_rms_rate,
            action_pop_size=action_pop_size or (20 if isinstance(action_space, spaces.Box) else 1),
            logit_scale_init=logit_scale_init,
            w_init_gain=w_init_gain,
            w_init_mean=w_init_mean,
            alpha_init_mean=alpha_init_mean,
            alpha_init_std=alpha_init_std,
            critic=critic,
            critic_hidden=critic_hidden,
            alpha_lr_scale=float(alpha_lr_scale),
            standardize_obs=bool(standardize_obs),
            reward_input=reward_input,
            reward_to_encoder=bool(reward_to_encoder),
            modulation_kwargs=modulation_kwargs,
        )
        super().__init__(observation_space, action_space, lr_schedule, log_std_init=log_std_init, **kwargs)

    # ----------------------------------------------------------------------------------------------------------
    # Construction

    def _make_encoder(self) -> nn.Module:
        cfg, space = self.snn_config, self.observation_space
        if is_spike_raster_space(space):
            return RasterInput(space.shape[0], space.shape[1], cfg["input_rms_rate"])
        low = np.broadcast_to(np.asarray(cfg["obs_bounds"][0], dtype=np.float64), space.shape)
        high = np.broadcast_to(np.asarray(cfg["obs_bounds"][1], dtype=np.float64), space.shape)
        low = np.where(np.isfinite(space.low), space.low, low)
        high = np.where(np.isfinite(space.high), space.high, high)
        return PopulationEncoder(
            low, high, cfg["encoder_pop_size"], cfg["encoder_beta"], cfg["encoder_p_min"], cfg.get("obs_indices")
        )

    def _make_decoder(self) -> nn.Module:
        cfg, space = self.snn_config, self.action_space
        if isinstance(space, spaces.Box):
            return ContinuousDecoder(space.low, space.high, cfg["action_pop_size"])
        return DiscreteDecoder(int(space.n), cfg["action_pop_size"], cfg["logit_scale_init"])

    def _build(self, lr_schedule: Schedule) -> None:
        cfg = self.snn_config
        try:
            neuron = SRMParameters(**cfg["neuron"])
        except TypeError:
            raise ValueError(
                f"bad neuron constants {cfg['neuron']}; accepted keys: {', '.join(SRMParameters._fields)}"
            ) from None
        self.snn = SpikingPlasticNetwork(
            self._make_encoder(),
            self._make_decoder(),
            cfg["hidden_sizes"],
            cfg["steps"],
            cfg["rule"],
            cfg["plastic_layers"],
            neuron,
            cfg["e_max"],
            cfg["plasticity_interval"],
            cfg["rule_kwargs"],
            cfg["w_init_gain"],
            cfg["w_init_mean"],
            cfg["alpha_init_mean"],
            cfg["alpha_init_std"],
        )
        space = self.observation_space
        reward_input = None if cfg.get("reward_input") is None else RewardInput(**cfg["reward_input"])
        source = cfg["rule_kwargs"].get("modulation_source", LEARNED_SOURCE)
        #: the signal from outside the network that the plastic rules read (``None``: they form their own)
        self.modulation_source: Optional[ModulationSource] = (
            None
            if source == LEARNED_SOURCE
            else get_modulation_source(source)(space, reward_input, **cfg.get("modulation_kwargs", {}))
        )
        # The reward elements the encoder does not see (reward_to_encoder=False), else None; a buffer, so that it
        # moves with the policy's device, not saved.
        hidden = None
        if reward_input is not None and not cfg.get("reward_to_encoder", True):
            hidden = torch.tensor([*reward_input.positive, *reward_input.negative], dtype=torch.long)
        self.register_buffer("_hidden_reward", hidden, persistent=False)
        unbounded = ~(np.isfinite(space.low) & np.isfinite(space.high)).reshape(-1)
        if reward_input is not None and not is_spike_raster_space(space):
            # The sources read the reward as the environment paid it.
            unbounded[[*reward_input.positive, *reward_input.negative]] = False
        self.obs_standardizer = ObservationStandardizer(
            unbounded & bool(cfg.get("standardize_obs", True)) & (not is_spike_raster_space(space))
        )
        if isinstance(self.action_dist, DiagGaussianDistribution):
            self.log_std = nn.Parameter(torch.full((get_action_dim(self.action_space),), float(self.log_std_init)))
        elif not isinstance(self.action_dist, CategoricalDistribution):
            raise ValueError(f"unsupported action distribution {type(self.action_dist).__name__}")
        hidden = cfg["critic_hidden"]
        if cfg["critic"] == "snn":
            critic_in = sum(self.snn.sizes[1:])
        else:
            critic_in = int(np.prod(self.observation_space.shape))
        self.value_net = nn.Sequential(nn.Linear(critic_in, hidden), nn.Tanh(), nn.Linear(hidden, 1))
        self.optimizer = self.optimizer_class(
            self._parameter_groups(lr_schedule(1)), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    def _parameter_groups(self, lr: float) -> list[dict]:
        """The optimizer's parameter groups: the plasticity coefficients (at ``alpha_lr_scale`` times the rate,
        recorded as the group's ``lr_scale``) and everything else."""
        scale = self.snn_config["alpha_lr_scale"]
        alphas = [layer.alpha for layer in self.snn.layers if layer.alpha is not None]
        if scale == 1.0 or not alphas:
            # One group, as before the option existed: saved optimizers of earlier models still load.
            return [{"params": list(self.parameters())}]
        ids = {id(a) for a in alphas}
        return [
            {"params": [p for p in self.parameters() if id(p) not in ids], "lr_scale": 1.0},
            {"params": alphas, "lr": lr * scale, "lr_scale": scale},
        ]

    def resolved_arguments(self) -> dict[str, Any]:
        """The policy's own constructor arguments with the values its defaults resolved to: given back to the
        constructor, they build the same network whatever the defaults are then."""
        return {**copy.deepcopy(self.snn_config), "log_std_init": float(self.log_std_init)}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        for unused in (
            "net_arch",
            "activation_fn",
            "ortho_init",
            "use_sde",
            "full_std",
            "use_expln",
            "squash_output",
            "sde_net_arch",
        ):
            data.pop(unused, None)
        data.update(self.snn_config)
        data["ablation"] = str(self._ablation)
        return data

    @property
    def ablation(self) -> Ablation:
        """The plasticity ablation :meth:`predict` applies (:mod:`sb3_spikeplastic.sb3.ablation`); set it with an
        :class:`~sb3_spikeplastic.sb3.ablation.Ablation` or its string (``"frozen"``, ``"reset-every:50"``...). Saved
        with the model; :class:`sb3_spikeplastic.PPO`'s rollouts and updates ignore it."""
        return self._ablation

    @ablation.setter
    def ablation(self, value: Union[str, Ablation, None]) -> None:
        self._ablation = Ablation.parse(value)

    # ----------------------------------------------------------------------------------------------------------
    # Recurrent interface used by sb3_spikeplastic.PPO

    def initial_state(self, n_envs: int, seed: int = 0) -> NetworkState:
        """Initial network state for ``n_envs`` environments (``seed`` picks the input-noise streams)."""
        state = self.snn.initial_state(n_envs, seed=seed, device=self.device)
        if self.modulation_source is None:
            return state
        return state._replace(source=self.modulation_source.initial_state(n_envs, self.device))

    def _source_state(self, state: NetworkState) -> Tensor:
        """The modulation source's state in ``state`` (its initial state where the state was built without it)."""
        if state.source is not None:
            return state.source
        return self.modulation_source.initial_state(state.noise_key.shape[0], state.noise_key.device)

    def network_step(
        self, obs: Tensor, state: NetworkState, record: bool = False, hold_plastic: bool = False
    ) -> tuple[NetworkOutput, NetworkState]:
        """One step of the spiking network on preprocessed ``obs`` from ``state`` (not reset here), with the
        modulation source's signal where the rules read one; ``record`` and ``hold_plastic`` as in
        :meth:`~sb3_spikeplastic.snn.network.SpikingPlasticNetwork.forward`."""
        modulator = None
        if self.modulation_source is not None:
            starts = obs.new_zeros(1, obs.shape[0])
            signals, source = self.modulation_source.sequence(obs.unsqueeze(0), starts, self._source_state(state), self)
            modulator, state = signals[0], state._replace(source=source)
        return self.snn(self._encoder_view(obs), state, record=record, hold_plastic=hold_plastic, modulator=modulator)

    def _encoder_view(self, obs: Tensor) -> Tensor:
        """``obs`` as the network's encoder sees it: without the reward elements where ``reward_to_encoder`` is off."""
        if self._hidden_reward is None:
            return obs
        return obs.index_fill(-1, self._hidden_reward, 0.0)

    def observation_value(self, obs: Tensor) -> Tensor:
        """The critic's value ``(batch,)`` of preprocessed observations, before the network runs on them
        (``critic="mlp"``, which reads the observation only; the TD-error modulation source's values)."""
        if self.snn_config["critic"] != "mlp":
            raise ValueError("observation_value needs critic='mlp' (the 'snn' critic reads the network's rates)")
        return self.value_net(obs.flatten(1).float()).squeeze(-1)

    def _value(self, obs: Tensor, out: NetworkOutput) -> Tensor:
        if self.snn_config["critic"] == "snn":
            # Detached: the value loss trains only the readout. Through the plastic traces the raw gradients reach
            # 1e6+, so a shared value gradient would dominate the clipped update and drown the policy gradient.
            features = torch.cat(out.rates, -1).detach()
        else:
            features = obs.flatten(1).float()
        return self.value_net(features)

    def _distribution(self, out: NetworkOutput, action_masks: Optional[Tensor] = None):
        if isinstance(self.action_dist, DiagGaussianDistribution):
            return self.action_dist.proba_distribution(out.action, self.log_std)
        logits = out.action
        if action_masks is not None:
            # A large finite negative rather than -inf: zero probability, and entropy terms 0 * logit stay 0.
            logits = torch.where(action_masks.reshape(logits.shape).bool(), logits, torch.full_like(logits, -1e8))
        return self.action_dist.proba_distribution(action_logits=logits)

    def step(
        self,
        obs: Tensor,
        state: NetworkState,
        episode_start: Tensor,
        deterministic: bool = False,
        action_masks: Optional[Tensor] = None,
    ):
        """One rollout step: ``(actions, values, log_probs, new_state, network_output)`` after resetting the state
        where ``episode_start`` is 1; ``action_masks`` ``(batch, n_actions)`` (``Discrete`` only) closes actions."""
        return self._step(self._preprocess(obs), state, episode_start, deterministic, action_masks)

    def _step(
        self,
        obs: Tensor,
        state: NetworkState,
        episode_start: Tensor,
        deterministic: bool = False,
        action_masks: Optional[Tensor] = None,
        sync_free: bool = False,
        hold_plastic: bool = False,
    ):
        """:meth:`step` of already preprocessed ``obs``; ``sync_free`` as in :meth:`_evaluate_sequence`,
        ``hold_plastic`` as in :meth:`~sb3_spikeplastic.snn.network.SpikingPlasticNetwork.forward`."""
        out, new_state = self.network_step(obs, state.reset(episode_start, sync_free), hold_plastic=hold_plastic)
        if type(self.action_dist) is DiagGaussianDistribution and not torch.is_grad_enabled():
            actions, log_prob = diag_gaussian_sample(out.action, self.log_std, deterministic)
        else:
            distribution = self._distribution(out, action_masks)
            actions = distribution.get_actions(deterministic=deterministic)
            log_prob = distribution.log_prob(actions)
        actions = actions.reshape((-1, *self.action_space.shape))
        return actions, self._value(obs, out), log_prob, new_state, out

    def value_with_state(self, obs: Tensor, state: NetworkState, episode_start: Optional[Tensor] = None) -> Tensor:
        """Value of ``obs`` seen from ``state`` (the state itself is not advanced: bootstrap values)."""
        obs = self._preprocess(obs)
        if episode_start is not None:
            state = state.reset(episode_start)
        out, _ = self.network_step(obs, state)
        return self._value(obs, out)

    def evaluate_actions_sequence(
        self,
        obs: Tensor,
        actions: Tensor,
        episode_starts: Tensor,
        state: NetworkState,
        action_masks: Optional[Tensor] = None,
    ):
        """Re-run sequences ``(L, batch, ...)`` from chunk-start ``state`` with truncated BPTT through the whole
        chunk (traces included), resetting where ``episode_starts`` is 1; ``action_masks`` ``(L, batch,
        n_actions)`` are the masks the rollout sampled with (``Discrete`` only).

        :return: ``(values, log_prob, entropy, outputs)``; the first three flattened over ``L * batch``
            (time-major), ``outputs`` the per-step :class:`~sb3_spikeplastic.snn.network.NetworkOutput`.
        """
        obs = self._preprocess(obs.flatten(0, 1)).view(obs.shape[0], obs.shape[1], *self.observation_space.shape)
        return self._evaluate_sequence(obs, actions, episode_starts, state, action_masks)

    def _evaluate_sequence(
        self,
        obs: Tensor,
        actions: Tensor,
        episode_starts: Tensor,
        state: NetworkState,
        action_masks: Optional[Tensor],
        sync_free: bool = False,
    ):
        """:meth:`evaluate_actions_sequence` of already preprocessed ``obs``; with ``sync_free`` no operation
        waits for the device (for CUDA-graph capture, :mod:`sb3_spikeplastic.sb3.cuda_graphs`)."""
        modulators = None
        if self.modulation_source is not None:
            modulators, _ = self.modulation_source.sequence(obs, episode_starts, self._source_state(state), self)
        outputs, _ = self.snn.forward_sequence(
            self._encoder_view(obs), episode_starts, state, sync_free, modulators, final_state=False
        )
        merged = NetworkOutput(
            torch.cat([o.action for o in outputs]), tuple(torch.cat(r) for r in zip(*[o.rates for o in outputs])), None
        )
        distribution = self._distribution(merged, None if action_masks is None else action_masks.flatten(0, 1))
        flat_actions = actions.flatten(0, 1)
        if isinstance(self.action_space, spaces.Discrete):
            flat_actions = flat_actions.long().flatten()
        values = self._value(obs.flatten(0, 1), merged)
        return values, distribution.log_prob(flat_actions), distribution.entropy(), outputs

    def _preprocess(self, obs: Tensor) -> Tensor:
        obs = obs.float()
        if not torch.isfinite(obs).all():
            raise ValueError(
                "non-finite observation passed to SpikePlasticPolicy (NaN or inf); check the env or VecNormalize"
            )
        return self.obs_standardizer(obs) if self.obs_standardizer.active else obs

    def update_observation_statistics(self, observations: Union[np.ndarray, Tensor]) -> None:
        """Add raw observations ``(..., *obs_shape)`` to the running statistics of ``standardize_obs`` (a no-op
        where nothing is standardised). :class:`sb3_spikeplastic.PPO` calls it with each rollout's observations
        after training on them."""
        if self.obs_standardizer.active:
            self.obs_standardizer.update(torch.as_tensor(observations))

    # ----------------------------------------------------------------------------------------------------------
    # SB3 API

    def forward(self, obs: Tensor, deterministic: bool = False):
        # stable_baselines3.PPO's rollout calls this without state: refuse instead of training silently wrong.
        raise RuntimeError(MISUSE_MESSAGE)

    def predict(
        self,
        observation: np.ndarray,
        state: Optional[NetworkState] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
        action_masks: Optional[np.ndarray] = None,
    ):
        """Actions for ``observation`` and the next network state, as SB3's recurrent policies do.

        :param observation: one observation or a batch (vectorised env).
        :param state: the state returned by the previous call; ``None`` starts fresh.
        :param episode_start: 1 where an episode starts (the state is reset there); ``None``: no reset.
        :param deterministic: use the mean action (Gaussian) or the arg-max (discrete). Input spikes stay random
            but replayable: the same observations and state give the same actions.
        :param action_masks: open actions ``(n_envs, n_actions)`` (``Discrete`` only; ``None``: all open).
        :return: ``(actions, new_state)``; under an :attr:`ablation` the state is an
            :class:`~sb3_spikeplastic.sb3.ablation.AblatedState` (the network state and each environment's step count
            since its episode start), to pass back as it is.
        """
        self.set_training_mode(False)
        obs_tensor, vectorized_env = self.obs_to_tensor(observation)
        n_envs = obs_tensor.shape[0]
        if state is None:
            state = self.initial_state(n_envs)
        starts = (
            torch.zeros(n_envs)
            if episode_start is None
            else torch.as_tensor(np.asarray(episode_start, dtype=np.float32).reshape(-1))
        )
        with torch.no_grad():
            masks = (
                None
                if action_masks is None
                else torch.as_tensor(np.asarray(action_masks, dtype=bool), device=self.device)
            )
            if self._ablation.active:
                actions, state = self._ablated_step(obs_tensor, state, starts.to(self.device), deterministic, masks)
            else:
                if isinstance(state, AblatedState):  # the ablation was switched off mid-episode
                    state = state.network
                actions, _, _, state, _ = self.step(obs_tensor, state, starts.to(self.device), deterministic, masks)
        actions = self.clip_actions(actions.cpu().numpy())
        if not vectorized_env:
            actions = actions.squeeze(axis=0)
        return actions, state

    def _ablated_step(
        self,
        obs: Tensor,
        state: Union[NetworkState, AblatedState],
        episode_start: Tensor,
        deterministic: bool,
        action_masks: Optional[Tensor],
    ) -> tuple[Tensor, AblatedState]:
        """:meth:`predict`'s step under :attr:`ablation`: the state is reset where episodes start, then ablated
        (:func:`~sb3_spikeplastic.sb3.ablation.ablate`; ``frozen`` also drops the updates inside the step); a plain
        :class:`NetworkState` counts its steps from 0."""
        if isinstance(state, AblatedState):
            network, steps = state
        else:
            network, steps = state, torch.zeros(obs.shape[0], dtype=torch.long, device=self.device)
        steps = torch.where(episode_start.to(steps.device) > 0, torch.zeros_like(steps), steps)
        network = ablate(self._ablation, network.reset(episode_start), steps)
        actions, _, _, network, _ = self._step(
            self._preprocess(obs),
            network,
            torch.zeros_like(episode_start),
            deterministic,
            action_masks,
            hold_plastic=self._ablation.holds_plastic,
        )
        return actions, AblatedState(network, steps + 1)

    def clip_actions(self, actions: np.ndarray) -> np.ndarray:
        """Sampled actions as the environment accepts them: clipped to a ``Box`` action space's bounds (a
        Gaussian sample can leave them), unchanged otherwise."""
        if isinstance(self.action_space, spaces.Box):
            return np.clip(actions, self.action_space.low, self.action_space.high)
        return actions

    def _predict(self, observation: Tensor, deterministic: bool = False) -> Tensor:
        raise RuntimeError(MISUSE_MESSAGE)

    def predict_values(self, obs: Tensor) -> Tensor:
        raise RuntimeError(MISUSE_MESSAGE)

    def evaluate_actions(self, obs: Tensor, actions: Tensor):
        raise RuntimeError(MISUSE_MESSAGE)


def diag_gaussian_sample(mean: Tensor, log_std: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor]:
    """Actions ``(batch, n)`` of SB3's ``DiagGaussianDistribution`` around ``mean`` (its mode where
    ``deterministic``) and their log-probabilities ``(batch,)``: torch's ``Normal`` sample and log-density op for op,
    so the values and the random stream are the same, without building the distribution objects at every step."""
    std = torch.ones_like(mean) * log_std.exp()
    actions = mean if deterministic else mean + torch.empty_like(mean).normal_() * std
    log_prob = -((actions - mean) ** 2) / (2 * std**2) - std.log() - math.log(math.sqrt(2 * math.pi))
    return actions, log_prob.sum(dim=1)


def _check_modulation_source(name: str, rule: str, critic: str, reward_input: Optional[dict]) -> type[ModulationSource]:
    """The source class of ``rule_kwargs.modulation_source=name``, after the checks that it can run (one-line
    errors naming what is missing)."""
    source = get_modulation_source(name)
    if "modulation_source" not in inspect.signature(get_rule_class(rule).__init__).parameters:
        able = [
            r
            for r in available_rules()
            if "modulation_source" in inspect.signature(get_rule_class(r).__init__).parameters
        ]
        raise ValueError(
            f"rule {rule!r} takes no neuromodulation (modulation_source={name!r}); rules that do: {', '.join(able)}"
        )
    if source.needs_reward and reward_input is None:
        raise ValueError(
            f"modulation_source={name!r} needs the previous reward in the observation: wrap the environment in "
            "sb3_spikeplastic.envs.PreviousReward (or use one with a reward_input, e.g. TMazeReversal-v0), "
            "or pass policy_kwargs reward_input=..."
        )
    if source.needs_observation_value and critic != "mlp":
        raise ValueError(
            f"modulation_source={name!r} needs the value of the observation before the network runs: "
            f"critic='mlp', not {critic!r}"
        )
    return source


class MisusedSpikePlasticPolicy(SpikePlasticPolicy):
    """What ``stable_baselines3.PPO("SpikePlasticPolicy", ...)`` resolves to: it refuses at construction."""

    def __init__(self, *args, **kwargs):
        raise TypeError(MISUSE_MESSAGE)


# SB3 resolves a policy given by name only through the algorithm class's ``policy_aliases``; without an entry,
# ``stable_baselines3.PPO("SpikePlasticPolicy", ...)`` fails with "unknown policy" and no hint. The entry (added
# when this module is imported, never replacing another one) makes it fail with a pointer to sb3_spikeplastic.PPO.
import stable_baselines3  # noqa: E402

for _algorithm in (stable_baselines3.PPO, stable_baselines3.A2C):
    _algorithm.policy_aliases.setdefault("SpikePlasticPolicy", MisusedSpikePlasticPolicy)
