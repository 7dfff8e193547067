"""One environment step of the whole network without autograd on the CPU: every layer's compiled interval op
(``_fast/srm_interval.cpp``) called in one loop, without the layers' modules in between.

Rollouts, ``predict``, evaluation and the robustness protocol run the network one step at a time without gradients.
Through the layers' modules each interval passes a dispatch, a check of its operands and several NamedTuples; on the
small CPU networks that Python costs about as much as the ops (a 3-layer step of one environment: ~2x the ops'
time). :func:`compiled_step` calls the op that the module would call (``srm_interval_forward`` without the surrogate)
with the same operands, so spikes, rates and states are bit-identical to the module path (tested).

It applies where every layer's interval runs compiled (CPU float tensors, built-in rules or static layers, one
plasticity interval per environment step), gradients are off, and the state has no pending updates.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from . import _fast
from ._fast.interval import NO_RULE, IntervalOutputs, named
from .functional import LayerState
from .neurons import AlphaFilterState
from .plasticity import PlasticState

__all__ = ["compiled_step"]


def compiled_step(
    network, spikes_in: Tensor, layer_states: Sequence[LayerState], hold_plastic: bool = False
) -> Optional[tuple[tuple[Tensor, ...], Tensor, tuple[LayerState, ...]]]:
    """Each layer's rate ``(batch, n)``, the input rate and the new layer states of one step of ``network`` on the
    input spikes ``spikes_in`` ``(batch, T, n_in)`` from ``layer_states``; with ``hold_plastic`` every layer keeps
    the plastic state it came in with. ``None`` where it does not apply (see the module docstring)."""
    ops = _fast.interval_ops()
    if ops is None or torch.is_grad_enabled() or network.interval != network.steps:
        return None
    dtype, device = spikes_in.dtype, spikes_in.device
    calls = []
    operands = [spikes_in]
    for layer, state in zip(network.layers, layer_states):
        _, constants, form = layer._interval(network.steps, dtype, device)
        plastic = layer.alpha is not None
        if (plastic and form is None) or state.plastic.pending is not None:
            return None  # a rule of one's own runs its step in Python; pending updates need the deferred op
        operands += [layer.weight, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2]
        if plastic:
            operands += [layer.alpha, state.plastic.trace]
        calls.append((layer, state, constants, form))
    if spikes_in.dim() != 3 or not _fast.cpu_float_operands(*operands):
        return None
    x, rates, new_states = spikes_in, [], []
    input_rate = None
    for layer, state, constants, form in calls:
        rule = layer.rule
        bcm = form is not None and form.bcm
        # The operands in IntervalInputs' order, as fused_interval.interval_inputs builds them.
        inputs = [
            x,
            state.psp.h1,
            state.psp.h2,
            state.refractory.h1,
            state.refractory.h2,
            state.plastic.trace if layer.alpha is not None else None,
            state.plastic.extra[0] if bcm else None,
            None,
            None,
            None,
            None,
            layer.weight,
            layer.alpha,
            rule.eta if form is not None else None,
            rule.eta_phi if bcm else None,
            rule.psi if bcm else None,
            rule.w_m if form is not None and form.modulation else None,
        ]
        outputs, _ = ops.srm_interval_forward(inputs, *constants, *(form or NO_RULE), False)
        out = named(IntervalOutputs, outputs)
        if form is None or hold_plastic:
            plastic = state.plastic
        else:
            plastic = PlasticState(out.trace, (out.phi,) if bcm else ())
        new_states.append(
            LayerState(AlphaFilterState(out.h1, out.h2), AlphaFilterState(out.ref_h1, out.ref_h2), plastic)
        )
        rates.append(out.r_post)
        if input_rate is None:
            input_rate = out.r_pre
        x = out.spikes
    return tuple(rates), input_rate, tuple(new_states)
