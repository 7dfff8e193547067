"""The energy of a spiking plastic policy per environment step: synaptic events, the plasticity's own work, and
an estimate in joules from per-operation costs.

A spike delivered to a synapse is one accumulate (AC: the weight added to the membrane), counted as synaptic
operations (SynOps; :func:`sb3_spikeplastic.monitoring.synaptic_operations`). A plastic synapse also works every
plasticity interval whether or not anything fired: the trace update of the built-in rules,
:math:`E' = (1 - \\eta) E + \\eta\\, (\\mathrm{post} - [E\\,\\mathrm{pre}]) \\otimes \\mathrm{pre}`, is per synapse
one multiply-accumulate (MAC) for the decay, one for the Hebbian product, one more for the Oja rules' prediction
:math:`E\\,\\mathrm{pre}`, and the efficacy :math:`W + \\alpha \\odot E` one more; a neuromodulated rule computes
:math:`M = W_m r_{post}`, :math:`n_{out}^2` MACs per layer (per-neuron terms, the clip and the tanh are left out:
they are O(n) or comparisons). Costs per operation: Horowitz (2014), "Computing's energy problem (and what we can
do about it)", ISSCC, 45 nm, 32-bit floating point: an add 0.9 pJ, a multiply 3.7 pJ, so an AC 0.9 pJ and a MAC
4.6 pJ, the figures the SNN literature uses to compare spiking and dense networks (e.g. Rathi & Roy, 2021).
"""

from __future__ import annotations

from typing import Optional, Sequence

from .plasticity import compiled_form

#: energy of one accumulate and of one multiply-accumulate, 32-bit float, 45 nm (Horowitz, 2014), in picojoules
AC_PJ = 0.9
MAC_PJ = 4.6


def trace_update_macs(rule) -> Optional[int]:
    """Multiply-accumulates per plastic synapse and trace update of a built-in rule: decay, Hebbian product and the
    efficacy, plus the prediction ``E pre`` for the Oja rules; ``None`` for a rule whose terms are not known here (a
    rule of one's own)."""
    form = compiled_form(rule)
    if form is None:
        return None
    return 3 + int(form.oja)


def plasticity_operations(network) -> Optional[list[float]]:
    """MACs of each layer's plasticity per environment step and environment: ``T / interval`` updates, each
    :func:`trace_update_macs` per synapse plus ``n_out^2`` for the modulatory signal; 0 for a static layer.
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
        modulation = layer.n_out**2 if layer.rule.modulated else 0
        per_layer.append(float(updates * (macs * layer.n_in * layer.n_out + modulation)))
    return per_layer


def energy_estimate(synops: Sequence[float], plasticity_macs: Optional[Sequence[float]]) -> dict[str, float]:
    """Energy per environment step in nanojoules: ``synops_nj`` (SynOps x :data:`AC_PJ`), ``plasticity_nj``
    (plasticity MACs x :data:`MAC_PJ`, NaN when unknown) and their sum ``total_nj``."""
    synaptic = sum(synops) * AC_PJ / 1000.0
    plastic = float("nan") if plasticity_macs is None else sum(plasticity_macs) * MAC_PJ / 1000.0
    return {"synops_nj": synaptic, "plasticity_nj": plastic, "total_nj": synaptic + plastic}
