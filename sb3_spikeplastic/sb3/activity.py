"""The spiking network's TensorBoard scalars of every rollout (``snn/``, ``plasticity/``).

:class:`RolloutActivity` accumulates per-layer statistics over a rollout (cheap: the rates are computed anyway) and
records them, with the traces' state at the rollout's end, through SB3's logger; :class:`RolloutActivityCallback`
does this for every rollout (:class:`sb3_spikeplastic.PPO` adds it to ``learn`` for spiking policies, as SB3's
algorithms record their own ``train/`` scalars).
"""

from __future__ import annotations

from typing import Optional

import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from torch import Tensor

from ..snn.energy import synaptic_operations
from ..snn.network import NetworkOutput, NetworkState, SpikingPlasticNetwork


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
        self._unsummed: list[tuple[Optional[Tensor], ...]] = []  # (modulator, input_rate, *rates) of the latest steps

    @torch.no_grad()
    def add(self, out: NetworkOutput) -> None:
        """Accumulate one rollout step's rates (all environments)."""
        self.steps += 1
        self._unsummed.append((out.modulator, out.input_rate, *out.rates))
        if len(self._unsummed) >= self.BATCH_STEPS:
            self._sum_up()

    def _sum_up(self) -> None:
        """Add the kept steps' statistics to the sums, each population's steps stacked ``(k, batch, n)``."""
        if not self._unsummed:
            return
        k = len(self._unsummed)
        modulators, input_rates, *layer_rates = [list(column) for column in zip(*self._unsummed)]
        modulator = None if modulators[0] is None else torch.stack(modulators)
        self._unsummed = []
        rates = [torch.stack(column) for column in layer_rates]
        if input_rates[0] is not None:  # spike_counts of every step, summed
            spikes = torch.stack([r.sum(-1).mean(-1).sum() for r in (torch.stack(input_rates), *rates)])
            spikes = spikes * self.network.steps
            self._spikes = spikes if self._spikes is None else self._spikes + spikes
        rows = []
        for layer, r in zip(self.network.layers, rates):
            if layer.plastic and layer.rule.modulated:
                m = layer.rule.modulation(r, modulator if layer.rule.takes_modulator else None)
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
            logger.record(
                f"plasticity/layer{i}/trace_clip_fraction", (trace.abs() >= 0.99 * rule.e_max).float().mean().item()
            )
            if rule.modulated:
                logger.record(f"plasticity/layer{i}/modulation_mean", modulation)
                logger.record(f"plasticity/layer{i}/modulation_std", max(modulation_sq - modulation**2, 0.0) ** 0.5)


class RolloutActivityCallback(BaseCallback):
    """:class:`RolloutActivity` of every rollout of a spiking policy, recorded at the rollout's end.

    It reads the rollout loop's variables that :class:`sb3_spikeplastic.PPO` hands to its callbacks: ``out`` (the
    step's :class:`~sb3_spikeplastic.snn.network.NetworkOutput`) and ``state`` (the network state). For other policies
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
