"""One plasticity interval of a plastic SRM layer as pure functions: input spikes, state and parameters in, outputs
and new state out, in eager PyTorch (its inner ops take the compiled kernels where they apply, through
:func:`sb3_spikeplastic.snn._fast.dispatch`).

Within one plasticity interval the efficacy is constant and the network is feed-forward, so a layer processes the
whole interval at once: one (batched) matrix product for the synaptic input, a Toeplitz product for the PSP filter,
and only the element-wise threshold/refractory recursion runs step by step (SpikePropamine §2.2 with SLAYER's SRM
neuron). :class:`~sb3_spikeplastic.snn.layers.PlasticSRMLayer` holds the parameters and per-length constants and runs
:func:`interval_step`, or the compiled interval (:mod:`sb3_spikeplastic.snn.fused_interval`) where it applies.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

import torch
from torch import Tensor

from . import _fast
from ._fast.interval import IntervalConstants, RuleForm
from .neurons import AlphaFilterState, SRMParameters, srm_spikes
from .plasticity import PlasticityRule, PlasticState

__all__ = [
    "CARRIED_PRODUCT",
    "IntervalParameters",
    "LayerOutput",
    "LayerState",
    "efficacy",
    "interval_result",
    "interval_step",
    "project",
    "synaptic_input",
]


class LayerState(NamedTuple):
    """Per-environment state of one layer, all with a leading batch axis.

    :param psp: alpha-filter state of the layer's *presynaptic* spikes ``(batch, n_in)`` each.
    :param refractory: refractory-filter state of the layer's own spikes ``(batch, n_out)`` each.
    :param plastic: the trace ``E`` and rule state.
    """

    psp: AlphaFilterState
    refractory: AlphaFilterState
    plastic: PlasticState


class LayerOutput(NamedTuple):
    """What a layer produced over one interval: ``spikes`` and ``membrane`` ``(batch, L, n_out)``, the
    neuromodulatory signal of the interval's plasticity update (``None`` for unmodulated rules), and the
    interval's mean spike rates ``rate`` (``(batch, n_out)``, the rule's :math:`r_{post}`) and ``input_rate``
    (``(batch, n_in)``, :math:`r_{pre}`)."""

    spikes: Tensor
    membrane: Tensor
    modulation: Optional[Tensor]
    rate: Tensor
    input_rate: Tensor


class IntervalParameters(NamedTuple):
    """What an interval of ``L`` steps reads besides its input spikes and state.

    :param weight: ``W`` ``(n_out, n_in)``.
    :param alpha: the plasticity coefficients ``(n_out, n_in)``; ``None`` for a static layer.
    :param rule: the layer's plasticity rule (its parameters, update and modulation).
    :param neuron: the SRM constants.
    :param operator: the alpha filter's ``(L + 2, L + 2)`` operator
        (:func:`~sb3_spikeplastic.snn.neurons.alpha_filter_operator`).
    :param constants: its PSP and end-state rows, the spike loop's constants, the trace bound and the product's
        form for this length (the compiled op's constants too).
    :param form: the rule's :func:`~sb3_spikeplastic.snn.plasticity.compiled_form` (``None`` for a static layer and
        for rules the compiled op does not update; the eager step does not read it).
    """

    weight: Tensor
    alpha: Optional[Tensor]
    rule: PlasticityRule
    neuron: SRMParameters
    operator: Tensor
    constants: IntervalConstants
    form: Optional[RuleForm]


def efficacy(weight: Tensor, alpha: Optional[Tensor], trace: Tensor) -> Tensor:
    """:math:`W + \\alpha \\odot E`, per environment ``(batch, n_out, n_in)``; just ``W`` for a static layer."""
    if alpha is None:
        return weight
    return torch.addcmul(weight, alpha, trace)


def project(x: Tensor, trace: Tensor, weight: Tensor, alpha: Optional[Tensor], efficacy_left: bool = False) -> Tensor:
    """The synaptic product :math:`x_b (W + \\alpha \\odot E_b)^T` of presynaptic rows ``x (batch, L, n_in)``.

    On CPU the compiled op (:data:`~sb3_spikeplastic.snn._fast.PLASTIC_LINEAR`) builds the efficacy of a few
    environments at a time (the ``(batch, n_out, n_in)`` efficacy and its gradient are never materialised). The eager
    ops multiply with the efficacy on the left when ``efficacy_left`` (so that its gradient comes out in its own
    ``(n_out, n_in)`` layout, not transposed: cheaper when ``n_in > n_out``; a plastic layer's only), else on the
    right. A static layer's weight is shared, so its gradient comes out in its own layout either way; ``x W^T`` is
    also the compiled interval's product, which gives the same values only in the same form (BLAS libraries need not
    sum a product and its transpose in the same order).
    """
    if alpha is None:
        return x @ weight.transpose(-1, -2)
    eager = _efficacy_left_product if efficacy_left else _efficacy_right_product
    return _fast.dispatch(_fast.PLASTIC_LINEAR, eager, x, weight, alpha, trace)


def _efficacy_right_product(x: Tensor, weight: Tensor, alpha: Tensor, trace: Tensor) -> Tensor:
    return x @ efficacy(weight, alpha, trace).transpose(-1, -2)


def _efficacy_left_product(x: Tensor, weight: Tensor, alpha: Tensor, trace: Tensor) -> Tensor:
    return (efficacy(weight, alpha, trace) @ x.transpose(-1, -2)).transpose(-1, -2)


def synaptic_input(
    spikes_in: Tensor, psp: AlphaFilterState, trace: Tensor, parameters: IntervalParameters
) -> tuple[Tensor, AlphaFilterState]:
    """The synaptic input of one interval ``(batch, L, n_out)`` and the PSP state carried out of it.

    The synaptic input ``K (S W_eff^T)`` (plus the decayed carried PSP) is associated so that the Toeplitz
    product ``K`` runs over the narrower side: ``(K S) W_eff^T`` when ``n_in <= n_out`` (e.g. the 64 -> 600
    output layer), ``K (S W_eff^T)`` otherwise (e.g. the 600 -> 64 input layer). Both equal filtering the
    presynaptic spikes first, because the filter is linear and ``W_eff`` is constant within the interval.
    """
    length = spikes_in.shape[1]
    constants = parameters.constants
    if constants.filter_first:
        # The interval's spikes and the carried PSP state (h1, h2) as L + 2 rows: one product filters them all.
        rows = torch.cat([spikes_in, psp.h1.unsqueeze(1), psp.h2.unsqueeze(1)], 1)
        filtered = parameters.operator @ rows  # (B, L + 2, n_in): the PSP of each step, then the end state
        return (
            project(filtered[:, :length], trace, parameters.weight, parameters.alpha),
            AlphaFilterState(filtered[:, length], filtered[:, length + 1]),
        )
    # The carried state rides along in the product: projecting h1 and h2 on their own would cost two
    # trace-sized outer products (and their sum) in the backward pass.
    if constants.carry_state:  # beside the spikes, as the fused interval does (PlasticSRMLayer.carries_state)
        return _fast.dispatch(CARRIED_PRODUCT, _rows_synaptic_input, spikes_in, psp, trace, parameters)
    return _rows_synaptic_input(spikes_in, psp, trace, parameters)


def _rows_synaptic_input(
    spikes_in: Tensor, psp: AlphaFilterState, trace: Tensor, parameters: IntervalParameters
) -> tuple[Tensor, AlphaFilterState]:
    """:func:`synaptic_input` of a layer that multiplies before it filters: the spikes and the carried PSP state as
    one block of ``L + 2`` rows."""
    constants = parameters.constants
    rows = torch.cat([spikes_in, psp.h1.unsqueeze(1), psp.h2.unsqueeze(1)], 1)
    end = constants.end_rows @ rows
    projected = project(rows, trace, parameters.weight, parameters.alpha, efficacy_left=True)
    return constants.psp_rows @ projected, AlphaFilterState(end[:, 0], end[:, 1])


def _carried_applies(spikes_in: Tensor, psp: AlphaFilterState, trace: Tensor, parameters: IntervalParameters) -> bool:
    return (
        _fast.PLASTIC_LINEAR.applies(spikes_in, parameters.weight, parameters.alpha, trace)
        and _fast.cpu_float_operands(spikes_in, psp.h1, psp.h2)
        and psp.h1.shape == psp.h2.shape == (spikes_in.shape[0], spikes_in.shape[2])
    )


def _carried_synaptic_input(
    ops: Any, spikes_in: Tensor, psp: AlphaFilterState, trace: Tensor, parameters: IntervalParameters
) -> tuple[Tensor, AlphaFilterState]:
    """:func:`_rows_synaptic_input` with the carried PSP state multiplied beside the spikes in the compiled product's
    pass over the trace, instead of copied with them into one block of rows."""
    length, constants = spikes_in.shape[1], parameters.constants
    carried = torch.stack([psp.h1, psp.h2], 1)
    projected = _fast.PLASTIC_LINEAR.run(ops, spikes_in, parameters.weight, parameters.alpha, trace, carried)
    end = constants.end_rows[:, :length] @ spikes_in + constants.end_rows[:, length:] @ carried
    return constants.psp_rows @ projected, AlphaFilterState(end[:, 0], end[:, 1])


#: the compiled product of the spikes with the carried PSP state beside them (:func:`synaptic_input` of a layer that
#: carries its state, :meth:`~sb3_spikeplastic.snn.layers.PlasticSRMLayer.carries_state`)
CARRIED_PRODUCT = _fast.Kernel("plastic_linear", _carried_applies, _carried_synaptic_input)


def interval_step(
    spikes_in: Tensor,
    state: LayerState,
    parameters: IntervalParameters,
    monitor: bool = False,
    defer_update: bool = False,
    modulator: Optional[Tensor] = None,
) -> tuple[LayerOutput, LayerState]:
    r"""One plasticity interval of presynaptic spikes ``(batch, L, n_in)``: the layer's outputs and next state.

    .. math::
        u(t) = (W + \alpha \odot E)\,(\varepsilon * s_{in})(t) + (\nu * s)(t), \qquad s(t) = H(u(t) - \vartheta),

    .. math::
        r_{pre} = \frac{1}{L} \sum_t s_{in}(t), \qquad r_{post} = \frac{1}{L} \sum_t s(t), \qquad
        E' = \mathrm{clip}(F(r_{pre}, r_{post}, E), \pm E_{max}),

    with :math:`\varepsilon` the PSP (alpha) kernel, :math:`\nu` the refractory kernel, :math:`H` the Heaviside step
    (its gradient SLAYER's surrogate) and :math:`F` the layer's rule (:meth:`PlasticityRule.step`), whose new trace
    acts from the next interval on. Pending updates in ``state`` (:attr:`PlasticState.pending`) are applied first.

    :param monitor: also return the interval's neuromodulatory signal (computed once more).
    :param defer_update: a request that only the compiled interval takes (it leaves the update pending, with the
        same values); this step applies every update at once.
    :param modulator: the signal from outside the network ``(batch, k)`` of a rule that
        :attr:`~sb3_spikeplastic.snn.plasticity.PlasticityRule.takes_modulator` (``None`` for the others).
    """
    rule, plastic = parameters.rule, parameters.alpha is not None
    if plastic and state.plastic.pending is not None:
        state = state._replace(plastic=rule.apply_pending(state.plastic))
    synaptic, psp = synaptic_input(spikes_in, state.psp, state.plastic.trace, parameters)
    spikes, membrane, refractory = srm_spikes(synaptic, state.refractory, parameters.neuron)
    r_pre, r_post = spikes_in.mean(1), spikes.mean(1)
    new_plastic = rule.step(r_pre, r_post, state.plastic, modulator) if plastic else state.plastic
    return interval_result(
        spikes, membrane, psp, refractory, r_pre, r_post, new_plastic, parameters, monitor, modulator
    )


def interval_result(
    spikes: Tensor,
    membrane: Tensor,
    psp: AlphaFilterState,
    refractory: AlphaFilterState,
    r_pre: Tensor,
    r_post: Tensor,
    plastic: PlasticState,
    parameters: IntervalParameters,
    monitor: bool,
    modulator: Optional[Tensor] = None,
) -> tuple[LayerOutput, LayerState]:
    """An interval's :class:`LayerOutput` and :class:`LayerState` from its parts (the eager and the compiled step's
    alike); with ``monitor`` the output carries the rule's neuromodulatory signal of ``r_post`` (and ``modulator``)."""
    modulation = parameters.rule.modulation(r_post, modulator) if monitor and parameters.alpha is not None else None
    return LayerOutput(spikes, membrane, modulation, r_post, r_pre), LayerState(psp, refractory, plastic)
