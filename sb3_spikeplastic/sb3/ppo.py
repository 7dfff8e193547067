"""Recurrent PPO for spiking plastic policies: a thin layer over ``stable_baselines3.PPO``.

For a recurrent policy (:class:`~sb3_spikeplastic.sb3.policy.SpikePlasticPolicy`) the algorithm

* carries the per-environment network state through rollouts, resetting it where an episode starts;
* stores a state snapshot only at the start of each ``bptt_steps``-long chunk (never per step);
* trains on shuffled minibatches of whole chunks, re-running each chunk from its snapshot with truncated BPTT
  (through the plastic traces too), resetting inside a chunk where an episode starts;
* bootstraps both the last value and time-limit truncations with the post-step state.

Any other policy (``MlpPolicy``...) goes through SB3's own code paths unchanged.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from typing import Any, ClassVar, Optional, Union

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO as SB3PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import Tensor
from torch.nn import functional as F

from ..snn.cpu_settings import spiking_cpu_settings
from ..snn.network import NetworkState
from ..snn.plasticity import LEARNED_SOURCE
from .activity import RolloutActivityCallback
from .buffers import ChunkRolloutBuffer, ChunkSamples, check_chunking
from .cuda_graphs import GraphedRolloutStep, GraphedSequenceEvaluation
from .policy import SpikePlasticPolicy, previous_defaults_filled

#: Accepted values of ``PPO(grad_clip=...)``.
GRAD_CLIP_MODES = ("global", "per-parameter")

#: The arguments whose default (``None``) depends on the policy: ``(SB3's value, the value for recurrent spiking
#: policies)``. ``PPO`` docstring: why.
POLICY_DEPENDENT_DEFAULTS = {
    "learning_rate": (3e-4, 1e-3),
    "batch_size": (64, 256),
    "grad_clip": ("global", "per-parameter"),
}

#: ``chunks_per_pass="auto"`` on the CPU: the most chunks per pass whose backpropagation graph (estimated by
#: ``SpikingPlasticNetwork.backward_bytes_per_step``) stays within this many bytes.
AUTO_PASS_GRAPH_BYTES = 2**30


class PPO(SB3PPO):
    """Proximal Policy Optimization (``stable_baselines3.PPO``) extended to recurrent spiking plastic policies.

    A drop-in for SB3's PPO: with ``MlpPolicy`` and friends it behaves exactly like it, SB3's defaults included.
    With ``"SpikePlasticPolicy"`` it trains with truncated backpropagation through time over chunks of
    ``bptt_steps`` environment steps (see the module docstring), and three defaults differ from SB3's
    (:data:`POLICY_DEPENDENT_DEFAULTS`; an explicit value always wins):

    * ``grad_clip="per-parameter"`` (SB3 clips globally): backpropagation through the plastic traces makes the
      plastic layers' gradients orders of magnitude larger than the readout's and the critic's, which a global
      clip would shrink below Adam's ``eps`` until they stop learning.
    * ``batch_size=256`` (SB3: 64), eight whole chunks of ``bptt_steps=32``, as the shipped entries: smaller
      minibatches spend more of their time in per-operation overhead on the CPU (``benchmarks/README.md``).
    * ``learning_rate=1e-3`` (SB3: 3e-4): with per-parameter clipping and Adam, 3e-4 left the HalfCheetah policy
      near its initial return after 100k steps (``docs/halfcheetah.md``, runs C and D).

    :param learning_rate: as SB3; ``None``: 3e-4, or 1e-3 for recurrent spiking policies.
    :param batch_size: transitions per minibatch, as SB3; ``None``: 64, or 256 for recurrent spiking policies
        (a multiple of ``bptt_steps``).
    :param bptt_steps: environment steps per training chunk (truncated-BPTT length) for recurrent policies;
        must divide ``n_steps`` and ``batch_size``.
    :param grad_clip: how ``max_grad_norm`` applies: ``"global"`` (SB3: one norm over all parameters) or
        ``"per-parameter"`` (each parameter tensor's gradient clipped to ``max_grad_norm`` on its own, as the
        unit-wise clipping of Brock et al. 2021). ``None``: ``"per-parameter"`` for recurrent spiking policies,
        ``"global"`` otherwise. ``train/grad_norm`` logs the global pre-clip norm either way (the median over the
        update's minibatches), ``train/grad_norm/<parameter>`` each parameter's.
    :param use_action_masks: ask the environments for ``action_masks()`` (sb3-contrib ``MaskablePPO``'s
        convention: a boolean array of open actions) before every rollout step; a recurrent policy with
        ``Discrete`` actions then samples only open actions and is trained with the same masks. Where one action
        is open, its log-probability is 0 and the step adds no policy gradient: on tasks that ignore most actions
        (the cue T-maze acts once per episode, as in the paper) this removes the noise of the ignored ones.
    :param cuda_graphs: on a CUDA device, replay each rollout step and each minibatch's forward and backward
        pass as CUDA graphs (:mod:`sb3_spikeplastic.sb3.cuda_graphs`): the same values and gradients as eager
        PyTorch (the rollout's action samples use other random numbers of the same distribution), without the
        hundreds of kernel launches per environment step that otherwise bound the GPU by the host. Ignored on
        the CPU.
    :param chunks_per_pass: for recurrent policies, run the forward and backward pass of at most this many chunks at
        once and add up the minibatch's gradient over the passes: the same update, with the memory of the
        backpropagation graph (which holds every step's traces) bounded by ``chunks_per_pass`` instead of the
        minibatch. Must divide ``batch_size // bptt_steps``. ``None``: the whole minibatch in one pass.
        ``"auto"``: on the CPU, the most chunks per pass (a divisor) whose graph stays within
        :data:`AUTO_PASS_GRAPH_BYTES` (1 GiB: the paper's HalfCheetah network with a plastic rule runs its 64-chunk
        minibatches in one pass, peaking at ~1.5 GB; two passes would peak ~0.5 GB lower for ~5-8 % less speed);
        on a GPU, one pass. ``train/chunks_per_pass`` logs the choice.
    :param flush_denormal: for recurrent policies, flush subnormal floats to zero while ``learn()`` runs
        (:func:`~sb3_spikeplastic.snn.cpu_settings.spiking_cpu_settings`; the mode is put back on return). The PSP
        filters of silent neurons, the traces and their gradients decay through the subnormal floats, where CPU
        arithmetic is up to ~100x slower; flushed to zero they change no spike, and the HalfCheetah entry trains
        ~1.3x faster (``benchmarks/README.md``). ``False`` leaves the mode as it is.
    :param keep_freed_memory: for recurrent policies on the CPU, make the block cache torch's CPU allocator while
        ``learn()`` runs (:mod:`sb3_spikeplastic.snn.cpu_settings`; the previous allocator is put back on return):
        freed large blocks go to the next allocation of their size, where glibc would search its bins for every
        one (a training step allocates the same sizes in every BPTT step). The paper's HalfCheetah network trains a
        few percent faster and peaks ~0.2 GB lower. ``False`` leaves the allocator as it is.
    Other parameters as :class:`stable_baselines3.PPO`; ``batch_size`` keeps its meaning (transitions per
    minibatch), so a minibatch holds ``batch_size // bptt_steps`` chunks.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3PPO.policy_aliases,
        "SpikePlasticPolicy": SpikePlasticPolicy,
    }

    def __init__(
        self,
        policy: Union[str, type[BasePolicy]],
        env: Union[GymEnv, str],
        learning_rate: Union[float, Schedule, None] = None,
        n_steps: int = 2048,
        batch_size: Optional[int] = None,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: Union[float, Schedule] = 0.2,
        clip_range_vf: Union[None, float, Schedule] = None,
        normalize_advantage: bool = True,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        rollout_buffer_class: Optional[type[RolloutBuffer]] = None,
        rollout_buffer_kwargs: Optional[dict[str, Any]] = None,
        target_kl: Optional[float] = None,
        stats_window_size: int = 100,
        tensorboard_log: Optional[str] = None,
        policy_kwargs: Optional[dict[str, Any]] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[torch.device, str] = "auto",
        bptt_steps: int = 32,
        grad_clip: Optional[str] = None,
        use_action_masks: bool = False,
        cuda_graphs: bool = True,
        chunks_per_pass: Union[int, str, None] = "auto",
        flush_denormal: bool = True,
        keep_freed_memory: bool = True,
        _init_setup_model: bool = True,
    ):
        self.bptt_steps = int(bptt_steps)
        self.cuda_graphs = bool(cuda_graphs)
        self.flush_denormal = bool(flush_denormal)
        self.keep_freed_memory = bool(keep_freed_memory)
        policy_class = self.policy_aliases.get(policy, policy) if isinstance(policy, str) else policy
        spiking = bool(getattr(policy_class, "recurrent", False))
        defaults = {k: v[spiking] for k, v in POLICY_DEPENDENT_DEFAULTS.items()}
        learning_rate = defaults["learning_rate"] if learning_rate is None else learning_rate
        batch_size = defaults["batch_size"] if batch_size is None else batch_size
        grad_clip = defaults["grad_clip"] if grad_clip is None else grad_clip
        if grad_clip not in GRAD_CLIP_MODES:
            raise ValueError(f"unknown grad_clip {grad_clip!r}; accepted: {', '.join(GRAD_CLIP_MODES)}")
        self.grad_clip = grad_clip
        if spiking:
            # Before SB3's own checks, whose warnings about mini-batches do not apply to chunks.
            check_chunking(self.bptt_steps, n_steps, batch_size)
            n_chunks = batch_size // self.bptt_steps
            if chunks_per_pass not in (None, "auto") and (
                isinstance(chunks_per_pass, (str, bool)) or chunks_per_pass < 1 or n_chunks % chunks_per_pass
            ):
                raise ValueError(
                    f"chunks_per_pass={chunks_per_pass!r} must divide the chunks per minibatch, "
                    f"batch_size // bptt_steps = {n_chunks}, or be None or 'auto'"
                )
        self.chunks_per_pass = chunks_per_pass if chunks_per_pass in (None, "auto") else int(chunks_per_pass)
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            batch_size=batch_size,
            n_epochs=n_epochs,
            gamma=gamma,
            gae_lambda=gae_lambda,
            clip_range=clip_range,
            clip_range_vf=clip_range_vf,
            normalize_advantage=normalize_advantage,
            ent_coef=ent_coef,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,
            use_sde=use_sde,
            sde_sample_freq=sde_sample_freq,
            rollout_buffer_class=rollout_buffer_class,
            rollout_buffer_kwargs=rollout_buffer_kwargs,
            target_kl=target_kl,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.use_action_masks = bool(use_action_masks)
        if self.use_action_masks:
            self._check_action_masks()
        if self.recurrent and self.env is not None and self.batch_size > self.n_steps * self.n_envs:
            raise ValueError(
                f"batch_size={self.batch_size} exceeds the rollout size n_steps * n_envs = {self.n_steps * self.n_envs}"
            )
        if _init_setup_model:
            self._setup_model()

    @classmethod
    def load(
        cls, path, env=None, device="auto", custom_objects=None, print_system_info=False, force_reset=True, **kwargs
    ):
        """SB3's ``load``; a spiking model saved before its ``policy_kwargs`` recorded every resolved argument
        is rebuilt with the defaults of its time (:func:`~sb3_spikeplastic.sb3.policy.previous_defaults_filled`)."""
        custom_objects = dict(custom_objects or {})
        if "policy_kwargs" not in custom_objects:
            start = path.tell() if hasattr(path, "tell") else None
            data, _, _ = load_from_zip_file(path, device="cpu", custom_objects=custom_objects)
            if start is not None:
                path.seek(start)
            policy_class = (data or {}).get("policy_class")
            saved = (data or {}).get("policy_kwargs") or {}
            if (
                isinstance(policy_class, type)
                and issubclass(policy_class, SpikePlasticPolicy)
                and ("standardize_obs" not in saved)
            ):
                custom_objects["policy_kwargs"] = previous_defaults_filled(
                    saved, data["observation_space"], data["action_space"]
                )
        return super().load(
            path,
            env=env,
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )

    @property
    def network_state(self) -> Optional[NetworkState]:
        """The per-environment network state (filters, traces, noise keys) that the next rollout continues from;
        ``None`` for feed-forward policies."""
        return self._last_network_state

    @property
    def recurrent(self) -> bool:
        return bool(getattr(self.policy_class, "recurrent", False))

    def _check_action_masks(self) -> None:
        if not self.recurrent:
            raise ValueError(
                "use_action_masks=True needs a recurrent SpikePlasticPolicy; for feed-forward policies "
                "use sb3-contrib's MaskablePPO"
            )
        if not isinstance(self.action_space, spaces.Discrete):
            raise ValueError(f"use_action_masks=True needs Discrete actions, got {self.action_space}")
        if self.env is not None and not self.env.has_attr("action_masks"):
            raise ValueError(
                "use_action_masks=True but the environment has no action_masks() method "
                "(sb3-contrib MaskablePPO's convention)"
            )

    def _setup_model(self) -> None:
        if self.recurrent:
            self.rollout_buffer_class = ChunkRolloutBuffer
            self.rollout_buffer_kwargs = {**(self.rollout_buffer_kwargs or {}), "chunk_len": self.bptt_steps}
        if isinstance(self.policy_class, type) and issubclass(self.policy_class, SpikePlasticPolicy):
            self.policy_kwargs = self._modulation_filled(self.policy_kwargs)
        super()._setup_model()
        if isinstance(self.policy, SpikePlasticPolicy):
            # What the defaults resolved to, so that a saved model rebuilds the same policy under later defaults.
            self.policy_kwargs = {**self.policy_kwargs, **self.policy.resolved_arguments()}
        self._last_network_state: Optional[NetworkState] = None
        self._graphed_evaluation: Optional[GraphedSequenceEvaluation] = None
        self._graphed_step: Optional[GraphedRolloutStep] = None
        self._skipped_steps, self._warned_nonfinite = 0, False
        self._parameter_grad_norms: dict[str, list[float]] = {}
        if self.recurrent:
            self._last_network_state = self.policy.initial_state(self.n_envs, seed=self.seed or 0)

    def _modulation_filled(self, policy_kwargs: dict) -> dict:
        """``policy_kwargs`` with what an external modulation source needs and the user left out: the environment's
        ``reward_input`` (:class:`~sb3_spikeplastic.envs.PreviousReward`, ``TMazeReversal-v0``) and, for the TD
        error, this algorithm's ``gamma``."""
        source = (policy_kwargs.get("rule_kwargs") or {}).get("modulation_source", LEARNED_SOURCE)
        if source == LEARNED_SOURCE:
            return policy_kwargs
        filled = dict(policy_kwargs)
        if filled.get("reward_input") is None and self.env is not None:
            try:
                filled["reward_input"] = self.env.get_attr("reward_input", indices=[0])[0]
            except AttributeError:
                pass  # the policy names what is missing
        if source == "td-error":
            filled["modulation_kwargs"] = {"gamma": self.gamma, **(filled.get("modulation_kwargs") or {})}
        return filled

    def _init_callback(self, callback, progress_bar: bool = False) -> BaseCallback:
        """SB3's callback setup, plus the ``snn/`` and ``plasticity/`` scalars of every rollout for spiking
        policies (:class:`~sb3_spikeplastic.sb3.activity.RolloutActivityCallback`)."""
        if self.recurrent:
            from stable_baselines3.common.callbacks import ConvertCallback

            if callback is not None and not isinstance(callback, (list, BaseCallback)):
                callback = ConvertCallback(callback)  # a plain function, as SB3 accepts
            given = [] if callback is None else callback if isinstance(callback, list) else [callback]
            callback = [*given, RolloutActivityCallback()]
        return super()._init_callback(callback, progress_bar)

    def _excluded_save_params(self) -> list[str]:
        # The rollout state belongs to the running environments, not to the model.
        return [
            *super()._excluded_save_params(),
            "_last_network_state",
            "_graphed_evaluation",
            "_graphed_step",
            "_skipped_steps",
            "_warned_nonfinite",
            "_parameter_grad_norms",
        ]

    def _training_evaluation(self):
        """``(obs, actions, starts, states, masks) -> (values, log_prob, entropy)`` for the update: CUDA graphs
        where enabled and on a CUDA device, else the policy's eager ``evaluate_actions_sequence``."""
        if self.cuda_graphs and self.device.type == "cuda":
            if self._graphed_evaluation is None:
                self._graphed_evaluation = GraphedSequenceEvaluation(self.policy)
            return self._graphed_evaluation
        return lambda *batch: self.policy.evaluate_actions_sequence(*batch)[:3]

    def _rollout_step(self):
        """``policy.step`` for rollouts: a replayed CUDA graph where enabled and on a CUDA device."""
        if self.cuda_graphs and self.device.type == "cuda":
            if self._graphed_step is None:
                self._graphed_step = GraphedRolloutStep(self.policy)
            return self._graphed_step
        return self.policy.step

    def predict(
        self,
        observation,
        state=None,
        episode_start=None,
        deterministic: bool = False,
        action_masks: Optional[np.ndarray] = None,
    ):
        """SB3's ``predict``, plus ``action_masks`` ``(n_envs, n_actions)`` as in sb3-contrib's ``MaskablePPO``
        (recurrent :class:`SpikePlasticPolicy` and ``Discrete`` actions only)."""
        if action_masks is None:
            return super().predict(observation, state, episode_start, deterministic)
        if not self.recurrent:
            raise ValueError(
                "action_masks needs a recurrent SpikePlasticPolicy; for feed-forward policies use "
                "sb3-contrib's MaskablePPO"
            )
        return self.policy.predict(observation, state, episode_start, deterministic, action_masks=action_masks)

    def learn(
        self,
        total_timesteps: int,
        callback=None,
        log_interval: int = 1,
        tb_log_name: str = "PPO",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ):
        """SB3's ``learn``. A policy's plasticity ablation (``policy.ablation``) applies to ``predict`` only (and so to
        ``EvalCallback``'s evaluations): rollouts and updates run the network unablated, and a line says so."""
        ablation = getattr(self.policy, "ablation", None)
        if ablation is not None and ablation.active:
            warnings.warn(
                f"policy.ablation={str(ablation)!r} is ignored by learn(): rollouts and updates run the "
                "network unablated (predict() and EvalCallback apply it)",
                stacklevel=2,
            )
        with self.cpu_settings(training=True):
            return super().learn(
                total_timesteps,
                callback=callback,
                log_interval=log_interval,
                tb_log_name=tb_log_name,
                reset_num_timesteps=reset_num_timesteps,
                progress_bar=progress_bar,
            )

    def cpu_settings(self, training: bool = False):
        """The CPU settings this model runs under (a context manager; nothing for feed-forward policies):
        flush-to-zero unless ``flush_denormal=False``, and in training on the CPU the block cache unless
        ``keep_freed_memory=False`` (:mod:`sb3_spikeplastic.snn.cpu_settings`)."""
        if not self.recurrent:
            return contextlib.nullcontext()
        return spiking_cpu_settings(
            flush_denormal=getattr(self, "flush_denormal", True),
            cache_blocks=training and self.device.type == "cpu" and getattr(self, "keep_freed_memory", True),
        )

    def save(self, path, exclude=None, include=None) -> None:
        """SB3's ``save``; a spiking policy's ``ablation`` (if any) goes into the saved ``policy_kwargs``, so that
        :meth:`load` rebuilds it with the model."""
        if isinstance(self.policy, SpikePlasticPolicy):
            kwargs = {k: v for k, v in self.policy_kwargs.items() if k != "ablation"}
            if self.policy.ablation.active:
                kwargs["ablation"] = str(self.policy.ablation)
            self.policy_kwargs = kwargs
        super().save(path, exclude=exclude, include=include)

    # --------------------------------------------------------------------------------------------------------------

    def collect_rollouts(
        self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer, n_rollout_steps: int
    ) -> bool:
        if not self.recurrent:
            return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        n_steps = 0
        if rollout_buffer.full:
            # The previous rollout, now trained on, joins the observation statistics; a rollout and its
            # re-evaluation in training always see the same ones.
            self.policy.update_observation_statistics(rollout_buffer.observations)
        rollout_buffer.reset()
        callback.on_rollout_start()
        state = self._last_network_state
        step = self._rollout_step()
        while n_steps < n_rollout_steps:
            if n_steps % self.bptt_steps == 0:
                rollout_buffer.add_snapshot(state)
            with torch.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)
                starts = torch.as_tensor(self._last_episode_starts, dtype=torch.float32, device=self.device)
                masks = np.stack(env.env_method("action_masks")) if self.use_action_masks else None
                actions, values, log_probs, state, out = step(
                    obs_tensor,
                    state,
                    starts,
                    action_masks=None if masks is None else torch.as_tensor(masks, device=self.device),
                )
            actions = actions.cpu().numpy()
            new_obs, rewards, dones, infos = env.step(self.policy.clip_actions(actions))
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                self._last_network_state = state
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            if isinstance(self.action_space, spaces.Discrete):
                actions = actions.reshape(-1, 1)
            for idx, done in enumerate(dones):
                if (
                    done
                    and infos[idx].get("terminal_observation") is not None
                    and infos[idx].get("TimeLimit.truncated", False)
                ):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with torch.no_grad():
                        # The post-step state of this env, before the reset the next step will apply.
                        terminal_value = self.policy.value_with_state(terminal_obs, state.select([idx]))[0]
                    rewards[idx] += self.gamma * terminal_value.item()
            rollout_buffer.add(
                self._last_obs, actions, rewards, self._last_episode_starts, values, log_probs, action_masks=masks
            )
            self._last_obs = new_obs
            self._last_episode_starts = dones
        self._last_network_state = state
        with torch.no_grad():
            last_values = self.policy.value_with_state(
                obs_as_tensor(new_obs, self.device),
                state,
                torch.as_tensor(dones, dtype=torch.float32, device=self.device),
            )
        rollout_buffer.compute_returns_and_advantage(last_values=last_values, dones=dones)
        callback.update_locals(locals())  # `out` and `state` reach the callbacks (RolloutActivityCallback)
        callback.on_rollout_end()
        return True

    def _clip_gradients(self) -> Optional[float]:
        """Clip as ``self.grad_clip`` says; returns the global gradient norm before clipping, or ``None`` (and
        the gradients untouched) when that norm is not finite. Each parameter's own norm before clipping is kept in
        ``self._parameter_grad_norms`` (logged as ``train/grad_norm/<parameter>``)."""
        named = [(name, p.grad) for name, p in self.policy.named_parameters() if p.grad is not None]
        grads = [g for _, g in named]
        # One call each for the norms and the scaling (torch's foreach ops), not two per parameter tensor.
        norms = torch.stack(torch._foreach_norm(grads))
        total = torch.linalg.vector_norm(norms).item()
        if not math.isfinite(total):
            return None
        for (name, _), norm in zip(named, norms.tolist()):
            self._parameter_grad_norms.setdefault(name, []).append(norm)
        if self.grad_clip == "global":
            torch._foreach_mul_(grads, min(self.max_grad_norm / (total + 1e-6), 1.0))  # as torch's clip_grad_norm_
        else:
            scales = torch.clamp(self.max_grad_norm / (norms + 1e-6), max=1.0)
            torch._foreach_mul_(grads, scales.tolist())
        return total

    def _minibatch_losses(
        self,
        batch: ChunkSamples,
        evaluate,
        clip_range: float,
        clip_range_vf: Optional[float],
        advantage_stats: Optional[tuple[Tensor, Tensor]] = None,
    ) -> tuple[Tensor, dict[str, float]]:
        """PPO's loss on one minibatch of chunks (or one part of it: ``advantage_stats`` are then the whole
        minibatch's advantage mean and standard deviation) and its statistics (as floats)."""
        values, log_prob, entropy = evaluate(
            batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks
        )
        values = values.flatten()
        advantages = batch.advantages.flatten()
        old_log_prob = batch.old_log_prob.flatten()
        old_values, returns = batch.old_values.flatten(), batch.returns.flatten()
        if self.normalize_advantage and advantage_stats is not None:
            advantages = (advantages - advantage_stats[0]) / (advantage_stats[1] + 1e-8)
        ratio = torch.exp(log_prob - old_log_prob)
        policy_loss = -torch.min(
            advantages * ratio, advantages * torch.clamp(ratio, 1 - clip_range, 1 + clip_range)
        ).mean()
        if clip_range_vf is None:
            values_pred = values
        else:
            values_pred = old_values + torch.clamp(values - old_values, -clip_range_vf, clip_range_vf)
        value_loss = F.mse_loss(returns, values_pred)
        entropy_loss = -torch.mean(entropy) if entropy is not None else -torch.mean(-log_prob)
        loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
        with torch.no_grad():
            log_ratio = log_prob - old_log_prob
            approx_kl_div = torch.mean((torch.exp(log_ratio) - 1) - log_ratio)
        stats = dict(
            policy_loss=policy_loss.item(),
            value_loss=value_loss.item(),
            entropy_loss=entropy_loss.item(),
            clip_fraction=torch.mean((torch.abs(ratio - 1) > clip_range).float()).item(),
            approx_kl=approx_kl_div.item(),
        )
        return loss, stats

    def _update_learning_rate(self, optimizers) -> None:
        """SB3's schedule step, then each parameter group's ``lr_scale`` (see ``SpikePlasticPolicy.alpha_lr_scale``)."""
        super()._update_learning_rate(optimizers)
        for optimizer in optimizers if isinstance(optimizers, list) else [optimizers]:
            for group in optimizer.param_groups:
                group["lr"] *= group.get("lr_scale", 1.0)

    def _pass_size(self) -> Optional[int]:
        """Chunks per forward and backward pass (``None``: the whole minibatch), ``"auto"`` resolved as the
        constructor's docstring says."""
        chunks = getattr(self, "chunks_per_pass", None)
        if chunks != "auto":
            return chunks
        if self.device.type != "cpu":
            return None
        n_chunks = self.batch_size // self.bptt_steps
        per_chunk = self.bptt_steps * self.policy.snn.backward_bytes_per_step()
        fitting = [c for c in range(1, n_chunks + 1) if n_chunks % c == 0 and c * per_chunk <= AUTO_PASS_GRAPH_BYTES]
        largest = max(fitting, default=1)
        return None if largest == n_chunks else largest

    def _update_minibatch(
        self, batch: ChunkSamples, evaluate, clip_range: float, clip_range_vf: Optional[float]
    ) -> tuple[dict[str, float], bool]:
        """One gradient step on one minibatch: its statistics, and ``False`` (no step taken) when the KL early
        stop triggers.

        The minibatch runs in parts of ``chunks_per_pass`` chunks, each part's loss weighted by its share of
        the minibatch, so that the summed gradient is the whole minibatch's. A method of its own so that the
        autograd graphs are gone when it returns: a graph kept alive into the next minibatch (through a ``loss``
        variable, say) can break a CUDA-graph capture there.
        """
        pass_size = self._pass_size()
        parts = batch.split(pass_size) if pass_size else [batch]
        advantages = batch.advantages.flatten()
        stats_of_whole = (advantages.mean(), advantages.std()) if len(advantages) > 1 else None
        self.policy.optimizer.zero_grad()
        stats: dict[str, float] = {}
        for part in parts:
            loss, part_stats = self._minibatch_losses(part, evaluate, clip_range, clip_range_vf, stats_of_whole)
            weight = part.n_chunks / batch.n_chunks
            part_stats["loss"] = loss.item()
            for key, value in part_stats.items():
                stats[key] = stats.get(key, 0.0) + weight * value
            if self.target_kl is not None and len(parts) == 1 and stats["approx_kl"] > 1.5 * self.target_kl:
                return stats, False  # known before any backward pass
            (loss * weight).backward()  # weight 1.0 for a single part: exact
            if part is not parts[-1] and evaluate is self._graphed_evaluation:
                # A replayed backward graph hands autograd its static gradient buffers, and a parameter's first
                # gradient takes its buffer over without a copy: the next part's replay would overwrite it.
                for p in self.policy.parameters():
                    if p.grad is not None:
                        p.grad = p.grad.clone()
        if self.target_kl is not None and stats["approx_kl"] > 1.5 * self.target_kl:
            self.policy.optimizer.zero_grad()
            return stats, False
        grad_norm = self._clip_gradients()
        if grad_norm is None:
            # An overflowing gradient would turn every parameter into NaN (or, clipped, freeze them all): skip
            # the step, count it (train/skipped_steps) and say so once.
            self.policy.optimizer.zero_grad()
            self._skipped_steps += 1
            if not self._warned_nonfinite:
                self._warned_nonfinite = True
                warnings.warn(
                    "non-finite gradient norm: the update step was skipped (counted in train/skipped_steps). "
                    "With plastic layers this usually means the trace's Hebbian loop is self-exciting "
                    "(alpha_init_mean too large for the layer) or bptt_steps is too long.",
                    RuntimeWarning,
                )
            return stats, True
        stats["grad_norm"] = grad_norm
        self.policy.optimizer.step()
        return stats, True

    def train(self) -> None:
        if not self.recurrent:
            return super().train()
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)
        clip_range_vf = None if self.clip_range_vf is None else self.clip_range_vf(self._current_progress_remaining)
        history: dict[str, list[float]] = {
            k: [] for k in ("policy_loss", "value_loss", "entropy_loss", "clip_fraction", "grad_norm", "loss")
        }
        approx_kl_divs: list[float] = []
        continue_training = True
        evaluate = self._training_evaluation()
        self._skipped_steps, self._parameter_grad_norms = 0, {}
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for batch in self.rollout_buffer.get_chunks(self.batch_size // self.bptt_steps):
                stats, stepped = self._update_minibatch(batch, evaluate, clip_range, clip_range_vf)
                approx_kl_divs.append(stats.pop("approx_kl"))
                for key, value in stats.items():
                    history[key].append(value)
                if not stepped:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl_divs[-1]:.2f}")
                    break
            self._n_updates += 1
            if not continue_training:
                break
        explained_var = explained_variance(self.rollout_buffer.values.flatten(), self.rollout_buffer.returns.flatten())
        self.logger.record("train/entropy_loss", np.mean(history["entropy_loss"]))
        self.logger.record("train/policy_gradient_loss", np.mean(history["policy_loss"]))
        self.logger.record("train/value_loss", np.mean(history["value_loss"]))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(history["clip_fraction"]))
        if history["loss"]:
            self.logger.record("train/loss", history["loss"][-1])
        self.logger.record("train/explained_variance", explained_var)
        if history["grad_norm"]:
            self.logger.record("train/grad_norm", float(np.median(history["grad_norm"])))
        # Which tensor a growing norm comes from (through the plastic traces, the input layer's first): files and
        # TensorBoard only, the console table stays short.
        for name, norms in self._parameter_grad_norms.items():
            self.logger.record(f"train/grad_norm/{name}", float(np.median(norms)), exclude="stdout")
        self.logger.record("train/skipped_steps", self._skipped_steps)
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", torch.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        self.logger.record("train/chunks_per_pass", self._pass_size() or self.batch_size // self.bptt_steps)
        if clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)
