"""The compiled layer interval's interface (``srm_interval.cpp``): NamedTuples mirroring the op's C++ structs, and
the functions that call the ops.

The op schemas are positional underneath (``TORCH_LIBRARY`` needs that): each struct of tensors travels as one
``Tensor?[]`` / ``Tensor[]``, ordered by its fields, and the constants and the rule's form as the schema's named
scalars. On this side the functions below are the only code that knows an order: they flatten the NamedTuples into
the op's arguments and rebuild them from its results (:func:`forward`, :func:`backward`). The training path keeps
what autograd only passes on in the op's order, never indexed: :func:`run_forward` returns the residuals as the op's
list for :func:`saved`, and :func:`backward_saved` takes the gradients of the outputs as autograd hands them to a node
and returns the op's gradients as autograd takes them back. The C++ side orders each struct in its ``fields()``
(``op_fields.h``). ``srm_interval_fields`` returns those field names, so that a test holds the two sides to the same
order.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

from torch import Tensor

__all__ = [
    "IntervalConstants",
    "IntervalGradients",
    "IntervalInputs",
    "IntervalOutputs",
    "IntervalResiduals",
    "NO_RULE",
    "RuleForm",
    "backward",
    "backward_saved",
    "forward",
    "named",
    "run_forward",
    "saved",
]


class RuleForm(NamedTuple):
    """How the compiled op evaluates a built-in rule's terms, op for op as
    :meth:`~sb3_spikeplastic.snn.plasticity.PlasticityRule.hebbian_terms` (``RuleForm`` in ``srm_interval.cpp``).

    :param oja: the Oja forms (subtract the trace's prediction).
    :param bcm: the BCM presynaptic term and sliding threshold.
    :param modulation: 0 unmodulated, 1 :math:`M = W_m r_{post}`, 2 :math:`M = \\tanh(W_m r_{post})`.
    """

    oja: bool
    bcm: bool
    modulation: int


#: the form passed where the op does not update the trace (static layers, rules of one's own)
NO_RULE = RuleForm(False, False, 0)


class IntervalConstants(NamedTuple):
    """What the op takes besides the tensors that change from call to call, fixed per layer, interval length, dtype
    and device (computed once, not on every network step; ``IntervalConstants`` in ``srm_interval.cpp``).

    :param psp_rows: the alpha-filter operator's PSP rows ``(L, L + 2)``
        (:func:`~sb3_spikeplastic.snn.neurons.alpha_filter_operator`; the op reads the filter's recurrence constants
        off them and its end-state rows).
    :param end_rows: its end-state rows ``(2, L + 2)``.
    :param filter_first: whether the layer filters its spikes before the product (``n_in <= n_out``).
    :param d: the refractory filter's decay (:func:`~sb3_spikeplastic.snn.neurons.spike_constants`).
    :param kappa: its gain.
    :param theta: the threshold.
    :param width: the surrogate's width.
    :param scale: the surrogate's scale.
    :param e_max: the rule's trace bound.
    :param carry_state: whether the carried PSP state is multiplied beside the spikes
        (:meth:`~sb3_spikeplastic.snn.layers.PlasticSRMLayer.carries_state`).
    """

    psp_rows: Tensor
    end_rows: Tensor
    filter_first: bool
    d: float
    kappa: float
    theta: float
    width: float
    scale: float
    e_max: float
    carry_state: bool


class IntervalInputs(NamedTuple):
    """The op's tensors, ``None`` where absent (``IntervalInputs`` in ``srm_interval.cpp``).

    :param x: presynaptic spikes ``(B, L, n_in)``.
    :param h1: the PSP filter's state ``(B, n_in)``.
    :param h2: the PSP filter's second state.
    :param ref_h1: the refractory filter's state ``(B, n_out)``.
    :param ref_h2: its second state.
    :param trace: the trace ``E`` ``(B, n_out, n_in)`` (plastic layers).
    :param phi: the BCM threshold ``(B, n_in)``.
    :param p_first: the oldest pending update's ``p`` ``(B, n_out)`` (the deferred op).
    :param q_first: its ``q`` ``(B, n_in)``.
    :param p_second: the second pending update's ``p``.
    :param q_second: its ``q``.
    :param weight: ``W`` ``(n_out, n_in)``.
    :param alpha: ``alpha`` (plastic layers).
    :param eta: the rule's learning rate (a built-in rule's trace update).
    :param eta_phi: the BCM threshold's rate.
    :param psi: the BCM offset.
    :param w_m: the modulatory weights ``W_m`` (modulated rules).
    """

    x: Tensor
    h1: Tensor
    h2: Tensor
    ref_h1: Tensor
    ref_h2: Tensor
    trace: Optional[Tensor]
    phi: Optional[Tensor]
    p_first: Optional[Tensor]
    q_first: Optional[Tensor]
    p_second: Optional[Tensor]
    q_second: Optional[Tensor]
    weight: Tensor
    alpha: Optional[Tensor]
    eta: Optional[Tensor]
    eta_phi: Optional[Tensor]
    psi: Optional[Tensor]
    w_m: Optional[Tensor]


#: The gradient of each of :class:`IntervalInputs`, named as the input; ``None`` for inputs not given or without
#: gradient (the refractory state; ``x``, ``h1`` and ``h2`` unless the rows' gradients were asked for).
IntervalGradients = NamedTuple("IntervalGradients", [(name, Optional[Tensor]) for name in IntervalInputs._fields])


class IntervalOutputs(NamedTuple):
    """What an interval produced (``IntervalOutputs`` in ``srm_interval.cpp``; ``None`` where it does not apply).
    The backward ops take the gradients of the outputs in the same NamedTuple.

    :param spikes: ``(B, L, n_out)``.
    :param membrane: ``(B, L, n_out)``.
    :param h1: the PSP filter's state at the interval's end.
    :param h2: its second state.
    :param ref_h1: the refractory filter's state at the interval's end.
    :param ref_h2: its second state.
    :param r_pre: the input's mean rate ``(B, n_in)``.
    :param r_post: the spikes' mean rate ``(B, n_out)``.
    :param trace: the updated trace (the deferred op: the trace it used, where it wrote it out).
    :param phi: the updated BCM threshold.
    :param p_next: the deferred op's own update, ``p`` ``(B, n_out)``, for the next interval.
    :param q_next: its ``q`` ``(B, n_in)``.
    """

    spikes: Optional[Tensor]
    membrane: Optional[Tensor]
    h1: Optional[Tensor]
    h2: Optional[Tensor]
    ref_h1: Optional[Tensor]
    ref_h2: Optional[Tensor]
    r_pre: Optional[Tensor]
    r_post: Optional[Tensor]
    trace: Optional[Tensor]
    phi: Optional[Tensor]
    p_next: Optional[Tensor]
    q_next: Optional[Tensor]


class IntervalResiduals(NamedTuple):
    """What the backward op needs from the forward op besides the inputs (``IntervalResiduals`` in
    ``srm_interval.cpp``).

    :param product_in: the rows the product took (filtered or raw spikes, with the carried PSP state unless apart).
    :param carried: the carried PSP state ``(B, 2, n_in)`` when the product took it apart from the spikes.
    :param surrogate: the surrogate gradient of the membrane (empty unless asked for).
    :param p: the trace step's postsynaptic factor (after the Oja term).
    :param pre: its presynaptic factor.
    :param m: the modulatory signal (modulated rules).
    :param r_pre: the input's mean rate.
    :param r_post: the spikes' mean rate.
    """

    product_in: Tensor
    carried: Optional[Tensor]
    surrogate: Tensor
    p: Optional[Tensor]
    pre: Optional[Tensor]
    m: Optional[Tensor]
    r_pre: Tensor
    r_post: Tensor


#: The inputs that the backward ops do not read (the rows and the filters' states), by name: :func:`saved` leaves
#: them out.
_NOT_SAVED = tuple(name in ("x", "h1", "h2", "ref_h1", "ref_h2") for name in IntervalInputs._fields)

#: How many of :func:`saved`'s tensors are inputs (the residuals follow them).
_SAVED_INPUTS = len(IntervalInputs._fields)

#: ``named(struct, tensors)``: the NamedTuple ``struct`` of ``tensors`` in its fields' order (an op's result list, or
#: autograd's tuple of a flattened struct): ``_make`` without its length check, which the op's schema makes.
named = tuple.__new__


def run_forward(
    ops: Any,
    inputs: IntervalInputs,
    constants: IntervalConstants,
    form: RuleForm,
    need_surrogate: bool,
    write_trace: Optional[bool] = None,
) -> tuple[IntervalOutputs, list[Tensor]]:
    """:func:`forward`'s outputs, and its residuals as the op returns them: a list for :func:`saved`, which is the
    only reader of their order."""
    if write_trace is None:
        outputs, residuals = ops.srm_interval_forward(list(inputs), *constants, *form, need_surrogate)
    else:
        outputs, residuals = ops.srm_interval_deferred_forward(
            list(inputs), *constants, *form, need_surrogate, write_trace
        )
    return named(IntervalOutputs, outputs), residuals


def forward(
    ops: Any,
    inputs: IntervalInputs,
    constants: IntervalConstants,
    form: RuleForm,
    need_surrogate: bool,
    write_trace: Optional[bool] = None,
) -> tuple[IntervalOutputs, IntervalResiduals]:
    """One interval: ``srm_interval_forward``, or with ``write_trace`` given ``srm_interval_deferred_forward`` (the
    pending updates in ``inputs`` applied in the product's pass, the interval's own returned as ``p_next, q_next``,
    the trace it used written out only with ``write_trace``). ``need_surrogate``: compute the surrogate gradient
    (training)."""
    outputs, residuals = run_forward(ops, inputs, constants, form, need_surrogate, write_trace)
    return outputs, IntervalResiduals._make(residuals)


def saved(inputs: IntervalInputs, residuals: list[Tensor]) -> tuple[Optional[Tensor], ...]:
    """What :func:`backward_saved` reads of an interval, as one tuple for ``save_for_backward``: the inputs that the
    backward op reads (``None`` for the others), then the residuals of :func:`run_forward`."""
    return (*[None if dropped else t for t, dropped in zip(inputs, _NOT_SAVED)], *residuals)


def backward_saved(
    ops: Any,
    grad_outputs: tuple[Optional[Tensor], ...],
    saved_tensors: tuple[Optional[Tensor], ...],
    constants: IntervalConstants,
    form: RuleForm,
    need_rows: bool,
    write_trace: Optional[bool] = None,
) -> list[Optional[Tensor]]:
    """:func:`backward` from the tensors :func:`saved` kept and the gradients of the outputs in their order (as
    autograd hands them to a node), returning the op's gradients in the inputs' order (as autograd takes them)."""
    inputs, residuals = list(saved_tensors[:_SAVED_INPUTS]), list(saved_tensors[_SAVED_INPUTS:])
    if write_trace is None:
        return ops.srm_interval_backward(list(grad_outputs), residuals, inputs, *constants, *form, need_rows)
    return ops.srm_interval_deferred_backward(
        list(grad_outputs), residuals, inputs, *constants, *form, need_rows, write_trace
    )


def backward(
    ops: Any,
    grad_outputs: IntervalOutputs,
    residuals: IntervalResiduals,
    inputs: IntervalInputs,
    constants: IntervalConstants,
    form: RuleForm,
    need_rows: bool,
    write_trace: Optional[bool] = None,
) -> IntervalGradients:
    """The gradients of :func:`forward`'s inputs from those of its outputs (``None`` read as zero); ``inputs`` need
    only the parameters, the trace, the BCM threshold and the pending updates. ``need_rows``: also the gradients of
    ``x``, ``h1`` and ``h2``."""
    if write_trace is None:
        gradients = ops.srm_interval_backward(
            list(grad_outputs), list(residuals), list(inputs), *constants, *form, need_rows
        )
    else:
        gradients = ops.srm_interval_deferred_backward(
            list(grad_outputs), list(residuals), list(inputs), *constants, *form, need_rows, write_trace
        )
    return IntervalGradients._make(gradients)
