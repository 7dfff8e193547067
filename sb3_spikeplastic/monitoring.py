"""What the spiking network is doing, as TensorBoard scalars (``snn/``, ``plasticity/``).

:class:`RolloutActivity` accumulates per-layer statistics over a rollout (cheap: the rates are computed
anyway) and records them, with the traces' state at the rollout's end, through SB3's logger.
"""

from __future__ import annotations

import torch
from stable_baselines3.common.logger import Logger

from .network import NetworkOutput, NetworkState, SpikingPlasticNetwork


class RolloutActivity:
    """Running per-layer statistics of a rollout.

    Recorded per layer ``i``: ``snn/layer{i}/spike_rate`` (spikes per neuron per ms), ``snn/layer{i}/silent_fraction``
    (neurons that did not fire during an environment step), and for plastic layers ``plasticity/layer{i}/eta``,
    ``trace_abs_mean`` and ``trace_clip_fraction`` (synapses with ``|E| >= 0.99 E_max``) over the environments'
    traces at the end of the rollout, and for neuromodulated rules ``modulation_mean`` / ``modulation_std`` of
    :math:`M = W_m r_{post}` over the rollout's steps.

    :param network: the policy's network.
    """

    def __init__(self, network: SpikingPlasticNetwork):
        self.network = network
        self.reset()

    def reset(self) -> None:
        n = len(self.network.layers)
        self.steps = 0
        self.rate = [0.0] * n
        self.silent = [0.0] * n
        self.mod_sum = [0.0] * n
        self.mod_sq = [0.0] * n

    @torch.no_grad()
    def add(self, out: NetworkOutput) -> None:
        """Accumulate one rollout step's rates (all environments)."""
        self.steps += 1
        for i, (layer, r) in enumerate(zip(self.network.layers, out.rates)):
            self.rate[i] += r.mean().item()
            self.silent[i] += (r == 0).float().mean().item()
            if layer.plastic and layer.rule.modulated:
                m = layer.rule.modulation(r)
                self.mod_sum[i] += m.mean().item()
                self.mod_sq[i] += m.pow(2).mean().item()

    @torch.no_grad()
    def record(self, logger: Logger, state: NetworkState) -> None:
        """Write the statistics of the rollout and of the final traces to ``logger``."""
        if self.steps == 0:
            return
        for i, (layer, layer_state) in enumerate(zip(self.network.layers, state.layers)):
            logger.record(f"snn/layer{i}/spike_rate", self.rate[i] / self.steps)
            logger.record(f"snn/layer{i}/silent_fraction", self.silent[i] / self.steps)
            if not layer.plastic:
                continue
            rule, trace = layer.rule, layer_state.plastic.trace
            logger.record(f"plasticity/layer{i}/eta", rule.eta.item())
            logger.record(f"plasticity/layer{i}/trace_abs_mean", trace.abs().mean().item())
            logger.record(f"plasticity/layer{i}/trace_clip_fraction", (trace.abs() >= 0.99 * rule.e_max).float().mean().item())
            if rule.modulated:
                mean = self.mod_sum[i] / self.steps
                logger.record(f"plasticity/layer{i}/modulation_mean", mean)
                logger.record(f"plasticity/layer{i}/modulation_std", max(self.mod_sq[i] / self.steps - mean**2, 0.0) ** 0.5)
