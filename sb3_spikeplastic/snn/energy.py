"""The energy of a spiking plastic policy per environment step: synaptic events, the plasticity's own work, and
an estimate in joules from per-operation costs.

A spike delivered to a synapse is one accumulate (AC: the weight added to the membrane), counted as synaptic
operations (SynOps; :func:`synaptic_operations`). A plastic synapse also works every
plasticity interval whether or not anything fired: the trace update of the built-in rules,
:math:`E' = (1 - \\eta) E + \\eta\\, (\\mathrm{post} - [E\\,\\mathrm{pre}]) \\otimes \\mathrm{pre}`, is per synapse
one multiply-accumulate (MAC) for the decay, one for the Hebbian product, one more for the Oja rules' prediction
:math:`E\\,\\mathrm{pre}`, and the efficacy :math:`W + \\alpha \\odot E` one more; a neuromodulated rule computes
:math:`M = W_m r_{post}`, :math:`n_{out}^2` MACs per layer, or from a signal outside the network :math:`G\\,m`,
:math:`n_{out} k` (per-neuron terms, the clip and the tanh are left out:
they are O(n) or comparisons). Costs per operation: Horowitz (2014), "Computing's energy problem (and what we can
do about it)", ISSCC, 45 nm, 32-bit floating point: an add 0.9 pJ, a multiply 3.7 pJ, so an AC 0.9 pJ and a MAC
4.6 pJ, the figures the SNN literature uses to compare spiking and dense networks (e.g. Rathi & Roy, 2021).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import torch
from torch import Tensor

from .network import NetworkOutput, SpikingPlasticNetwork
from .plasticity import builtin_form

#: energy of one accumulate and of one multiply-accumulate, 32-bit float, 45 nm (Horowitz, 2014), in picojoules
AC_PJ = 0.9
MAC_PJ = 4.6


def trace_update_macs(rule) -> Optional[int]:
    """Multiply-accumulates per plastic synapse and trace update of a built-in rule: decay, Hebbian product and the
    efficacy, plus the prediction ``E pre`` for the Oja rules; ``None`` for a rule whose terms are not known here (a
    rule of one's own)."""
    form = builtin_form(rule)
    if form is None:
        return None
    return 3 + int(form.oja)


def plasticity_operations(network) -> Optional[list[float]]:
    """MACs of each layer's plasticity per environment step and environment: ``T / interval`` updates, each
    :func:`trace_update_macs` per synapse plus the modulatory signal's (``n_out^2`` for the learned one); 0 for a
    static layer.
    ``None`` if a plastic layer's rule is not a built-in one."""
    updates = network.steps // network.interval
    per_layer = []
    for layer in network.layers:
        if not layer.plastic:
            per_layer.append(0.0)
            continue
        macs = trace_update_macs(layer.rule)
        if macs is None:
            return None
        modulation = layer.rule.modulation_macs()
        per_layer.append(float(updates * (macs * layer.n_in * layer.n_out + modulation)))
    return per_layer


def energy_estimate(synops: Sequence[float], plasticity_macs: Optional[Sequence[float]]) -> dict[str, float]:
    """Energy per environment step in nanojoules: ``synops_nj`` (SynOps x :data:`AC_PJ`), ``plasticity_nj``
    (plasticity MACs x :data:`MAC_PJ`, NaN when unknown) and their sum ``total_nj``."""
    synaptic = sum(synops) * AC_PJ / 1000.0
    plastic = float("nan") if plasticity_macs is None else sum(plasticity_macs) * MAC_PJ / 1000.0
    return {"synops_nj": synaptic, "plasticity_nj": plastic, "total_nj": synaptic + plastic}


def spike_counts(out: NetworkOutput, steps: int) -> Tensor:
    """Spikes per environment step and environment, averaged over the batch: ``(n_layers + 1,)``, the input
    population first, then the hidden layers and the output population.

    :param out: one environment step's output (with ``input_rate``).
    :param steps: network steps per environment step ``T`` (the rates are means over them).
    """
    return torch.stack([r.sum(-1).mean() for r in (out.input_rate, *out.rates)]) * steps


def spike_counts_per_env(out: NetworkOutput, steps: int) -> Tensor:
    """Spikes of each environment of the batch in one environment step, ``(batch, n_layers + 1)``, populations in
    the order of :func:`spike_counts` (whose value is their mean over the batch).

    :param out: one environment step's output (with ``input_rate``).
    :param steps: network steps per environment step ``T``.
    """
    batch = out.action.shape[0]
    return torch.stack([r.reshape(batch, -1).sum(-1) for r in (out.input_rate, *out.rates)], -1) * steps


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
    block (a forward hook: evaluation code, ``model.predict`` and rollouts are measured unchanged), and each
    environment's spikes since its last episode ended (:meth:`episode`: the energy of one episode).

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
        self._env_sums: Optional[Tensor] = None

    def _hook(self, module, inputs, output) -> None:
        out = output[0]
        batch = out.action.shape[0]
        counts = spike_counts(out, self.network.steps).detach() * batch
        self._sums = counts if self._sums is None else self._sums + counts
        self.env_steps += batch
        per_env = spike_counts_per_env(out, self.network.steps).detach().double()
        # Each row is one environment of a vectorised evaluation: a batch of another size starts the rows anew.
        fresh = self._env_sums is None or self._env_sums.shape != per_env.shape
        self._env_sums = per_env if fresh else self._env_sums + per_env

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
        estimate ``energy_nj`` (:func:`sb3_spikeplastic.snn.energy.energy_estimate`)."""
        if not self.env_steps:
            raise RuntimeError("no environment step was measured")
        spikes = self._sums.double().cpu() / self.env_steps
        synops = synaptic_operations(spikes, self.network.sizes)
        plastic = plasticity_operations(self.network)
        return {
            "spikes_per_step": spikes.tolist(),
            "synops_per_step": synops.tolist(),
            "total_spikes_per_step": float(spikes[1:].sum()),
            "total_synops_per_step": float(synops.sum()),
            "plasticity_macs_per_step": plastic,
            "total_plasticity_macs_per_step": None if plastic is None else float(sum(plastic)),
            "energy_nj": energy_estimate(synops.tolist(), plastic),
        }

    def episode(self, env: int, length: int) -> dict[str, float]:
        """The energy of the episode environment ``env`` (the row of the batch) has just ended, and its spikes
        cleared for the next one: ``synops`` (the episode's synaptic operations), ``plasticity_macs`` (its trace
        updates, :func:`plasticity_operations` per step times ``length``; NaN for a rule of one's own) and
        ``energy_nj`` (:func:`energy_estimate` of both).

        :param env: the environment's index in the batch of every forward pass.
        :param length: the episode's environment steps.
        """
        if self._env_sums is None:
            raise RuntimeError("no environment step was measured")
        spikes = self._env_sums[env].cpu().clone()  # a copy: the row is cleared next
        self._env_sums[env] = 0.0
        synops = synaptic_operations(spikes, self.network.sizes).tolist()
        plastic = plasticity_operations(self.network)
        plastic = None if plastic is None else [macs * length for macs in plastic]
        return {
            "synops": float(sum(synops)),
            "plasticity_macs": float("nan") if plastic is None else float(sum(plastic)),
            "energy_nj": energy_estimate(synops, plastic)["total_nj"],
        }
