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
from ._fast import interval
from ._fast.interval import NO_RULE
from .functional import LayerState
from .fused_interval import interval_inputs
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
    if spikes_in.dim() != 3 or not _fast.cpu_float_operands(spikes_in):
        return None  # before the layers: a GPU step stands aside at once
    dtype, device = spikes_in.dtype, spikes_in.device
    calls = []
    operands = [spikes_in]
    for layer, state in zip(network.layers, layer_states):
        parameters = layer.interval_parameters(network.steps, dtype, device)
        plastic = parameters.alpha is not None
        if (plastic and parameters.form is None) or state.plastic.pending is not None:
            return None  # a rule of one's own runs its step in Python; pending updates need the deferred op
        operands += [parameters.weight, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2]
        if plastic:
            operands += [parameters.alpha, state.plastic.trace]
        calls.append((state, parameters))
    if not _fast.cpu_float_operands(*operands):
        return None
    x, rates, new_states = spikes_in, [], []
    input_rate = None
    for state, parameters in calls:
        form = parameters.form
        inputs = interval_inputs(x, state, parameters, form)
        out, _ = interval.run_forward(ops, inputs, parameters.constants, form or NO_RULE, False)
        if form is None or hold_plastic:
            plastic = state.plastic
        else:
            plastic = PlasticState(out.trace, (out.phi,) if form.bcm else ())
        new_states.append(
            LayerState(AlphaFilterState(out.h1, out.h2), AlphaFilterState(out.ref_h1, out.ref_h2), plastic)
        )
        rates.append(out.r_post)
        if input_rate is None:
            input_rate = out.r_pre
        x = out.spikes
    return tuple(rates), input_rate, tuple(new_states)
