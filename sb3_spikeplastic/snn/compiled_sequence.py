"""A training sequence of the whole network as one autograd node on the CPU: every layer's compiled interval ops
(``_fast/srm_interval.cpp``) called in a loop, forward and backward, without a node per layer and step.

:meth:`~sb3_spikeplastic.snn.network.SpikingPlasticNetwork.forward_sequence` runs ``L`` environment steps of
``n_layers`` layer intervals each. Through the layers' modules every interval is an autograd node of its own
(:mod:`sb3_spikeplastic.snn.fused_interval`), and on the small CPU networks the Python around those nodes (module
calls, dispatch, named tuples, the nodes' own bookkeeping) costs about as much as the ops. :class:`_CompiledSequence`
calls the same ops with the same operands in the same order, so its rates are bit-identical; its backward pass calls
the same backward ops in the order autograd ran them, routing each gradient to where its tensor came from (an
earlier interval's output, through the resets' ``state * (1 - episode_start)``), and adds the parameters'
gradients up in autograd's order: the gradients are bit-identical too (tested).

It applies where every layer's interval runs compiled (CPU float tensors, built-in rules or static layers, one
plasticity interval per environment step), the rules read no modulator from outside the network, every parameter
takes a gradient, the initial state carries none and has no pending updates, and only the per-step outputs are
needed (not the final state).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Sequence

import torch
from torch import Tensor

from . import _fast
from ._fast import interval
from ._fast.interval import NO_RULE, IntervalConstants, IntervalInputs, IntervalOutputs, RuleForm

__all__ = ["compiled_sequence_rates"]

_IN = {name: i for i, name in enumerate(IntervalInputs._fields)}
_OUT = {name: i for i, name in enumerate(IntervalOutputs._fields)}
#: the parameter fields of :class:`IntervalInputs`, whose gradients go to the layer's parameters
_PARAMETER_FIELDS = ("weight", "alpha", "eta", "eta_phi", "psi", "w_m")
#: the state fields of :class:`IntervalInputs` that an interval reads from the layer's state
_STATE_FIELDS = ("h1", "h2", "ref_h1", "ref_h2", "trace", "phi")
#: the fields of the rule's rates, passed per interval
_RATE_FIELDS = ("eta", "eta_phi")
#: where each state field comes from among an interval's outputs
_STATE_OUTPUT = {name: _OUT[name] for name in _STATE_FIELDS}


class _LayerPlan(NamedTuple):
    """What the loop needs of one layer: its constants, its rule's form (``None``: static), its parameters in
    :data:`_PARAMETER_FIELDS` order (``None`` where absent, and for the rates ``eta`` and ``eta_phi``, which every
    interval computes from their logits anew, as the layer does: :data:`_RATE_FIELDS`), its rule, and whether the rows'
    gradients are needed (every layer after the first: its input spikes carry a gradient)."""

    constants: IntervalConstants
    form: Optional[RuleForm]
    parameters: tuple[Optional[Tensor], ...]
    rule: Any
    need_rows: bool

    def rates(self) -> list[Tensor]:
        """The rule's rates for one interval (``eta``, and ``eta_phi`` for BCM), each a node of its own: their
        gradients reach the logits one interval at a time, in autograd's order, as through the layer."""
        if self.form is None:
            return []
        return [self.rule.eta, self.rule.eta_phi] if self.form.bcm else [self.rule.eta]

    def rates_fields(self) -> tuple[str, ...]:
        """The :class:`IntervalInputs` fields of :meth:`rates`."""
        return () if self.form is None else _RATE_FIELDS if self.form.bcm else _RATE_FIELDS[:1]


class _Call(NamedTuple):
    """One interval call of the forward loop, for the backward one: the layer, the step, whether it was the
    deferred op (and whether it wrote its trace out), where each input came from (a source per
    :class:`IntervalInputs` field) and how many tensors it saved."""

    layer: int
    deferred: bool
    write: Optional[bool]
    sources: tuple
    n_saved: int


def _plan(network, steps: int, dtype, device) -> Optional[list[_LayerPlan]]:
    plans = []
    for i, layer in enumerate(network.layers):
        _, constants, form = layer._interval(steps, dtype, device)
        if layer.plastic and form is None:
            return None  # a rule of one's own (or an external modulator): its step runs in Python
        rule = layer.rule
        parameters = (
            layer.weight,
            layer.alpha,
            None,
            None,
            rule.psi if form is not None and form.bcm else None,
            rule.w_m if form is not None and form.modulation else None,
        )
        if not all(p.requires_grad for p in [*parameters, *rule.parameters()] if p is not None):
            return None
        plans.append(_LayerPlan(constants, form, parameters, rule, i > 0))
    return plans


def compiled_sequence_rates(
    network, spikes_in: Sequence[Tensor], episode_start: Tensor, state
) -> Optional[tuple[list[tuple[Tensor, ...]], list[Tensor]]]:
    """Each step's rates (per layer ``(batch, n)``) and input rate of ``network`` run over the input spikes
    ``spikes_in`` (one ``(batch, T, n_in)`` per step) from ``state``, resetting where ``episode_start`` ``(L, batch)``
    is 1, as one autograd node; ``None`` where it does not apply (see the module docstring)."""
    ops = _fast.interval_ops()
    if ops is None or not torch.is_grad_enabled() or network.interval != network.steps:
        return None
    first = spikes_in[0]
    plans = _plan(network, network.steps, first.dtype, first.device)
    if plans is None:
        return None
    tensors = [first, *(t for layer in state.layers for t in _layer_state_tensors(layer) if t is not None)]
    if any(t.requires_grad for t in tensors) or any(layer.plastic.pending is not None for layer in state.layers):
        return None
    if not _fast.cpu_float_operands(*tensors, *(p for plan in plans for p in plan.parameters if p is not None)):
        return None
    starts = [episode_start[k] if bool(episode_start[k].any()) else None for k in range(len(spikes_in))]
    flat_state = [_layer_state_tensors(layer) for layer in state.layers]
    n_layers = len(plans)
    parameters = [p for plan in plans for p in plan.parameters]
    n_parameters = sum(p is not None for p in parameters)
    rates_per_call = [r for _ in spikes_in for plan in plans for r in plan.rates()]
    outputs = _CompiledSequence.apply(
        (ops, plans, starts, flat_state, n_parameters),
        *spikes_in,
        *(p for p in parameters if p is not None),
        *rates_per_call,
    )
    rates = [tuple(outputs[k * n_layers : (k + 1) * n_layers]) for k in range(len(spikes_in))]
    return rates, list(outputs[len(spikes_in) * n_layers :])


def _layer_state_tensors(layer_state) -> tuple[Optional[Tensor], ...]:
    """A layer state's tensors in :data:`_STATE_FIELDS` order (``None`` where absent)."""
    plastic = layer_state.plastic
    return (
        layer_state.psp.h1,
        layer_state.psp.h2,
        layer_state.refractory.h1,
        layer_state.refractory.h2,
        plastic.trace,
        plastic.extra[0] if plastic.extra else None,
    )


def _reset(value: Optional[Tensor], source, keep: Optional[Tensor], step: int):
    """``value * keep`` (``keep`` shaped to its batch axis) and the source of the product; unchanged without a
    reset."""
    if keep is None or value is None:
        return value, source
    return value * keep.to(value.dtype).view(-1, *([1] * (value.dim() - 1))), ("reset", source, step)


class _CompiledSequence(torch.autograd.Function):
    """The loop of :func:`compiled_sequence_rates` as one autograd node. ``apply(setup, *spikes, *parameters)`` with
    ``setup = (ops, plans, starts, initial state tensors, number of parameters)``, the parameters in the plans'
    order and the rules' rates of every interval (:meth:`_LayerPlan.rates`); returns every step's rates (step-major,
    layer-minor), then every step's input rate (no gradient)."""

    @staticmethod
    def forward(ctx, setup, *tensors):
        ops, plans, starts, initial, n_parameters = setup
        n_steps = len(starts)
        spikes_in = tensors[:n_steps]
        rates_per_call = iter(tensors[n_steps + n_parameters :])
        # The layers' states as values and, beside them, where each came from: ("initial",), an interval's output
        # ("out", call, field) or a reset of either ("reset", source, step).
        values = [list(s) for s in initial]
        sources = [[("initial",)] * len(_STATE_FIELDS) for _ in initial]
        pending: list[list[tuple]] = [[] for _ in initial]  # per layer: (p, q, p source, q source), oldest first
        calls: list[_Call] = []
        saved: list[Optional[Tensor]] = []
        keeps: list[Optional[Tensor]] = []
        rates, input_rates = [], []
        for k in range(n_steps):
            keep = None if starts[k] is None else 1.0 - starts[k].float()
            keeps.append(keep)
            x, x_source = spikes_in[k], ("initial",)
            for i, plan in enumerate(plans):
                if keep is not None:
                    for f in range(len(_STATE_FIELDS)):
                        values[i][f], sources[i][f] = _reset(values[i][f], sources[i][f], keep, k)
                    pending[i] = [_pair(_reset(p, ps, keep, k), _reset(q, qs, keep, k)) for p, q, ps, qs in pending[i]]
                (p1, q1, p1s, q1s), (p2, q2, p2s, q2s) = (*pending[i], (None,) * 4, (None,) * 4)[:2]
                h1, h2, ref_h1, ref_h2, trace, phi = values[i]
                form = plan.form
                weight, alpha, _, _, psi, w_m = plan.parameters
                eta = next(rates_per_call) if form is not None else None
                eta_phi = next(rates_per_call) if form is not None and form.bcm else None
                if alpha is None:
                    trace = None  # a static layer's state holds an empty trace, which its op does not take
                inputs = [x, h1, h2, ref_h1, ref_h2, trace, phi, p1, q1, p2, q2, weight, alpha, eta, eta_phi, psi, w_m]
                input_sources = (x_source, *sources[i], p1s, q1s, p2s, q2s)
                call_index = len(calls)
                if form is not None:
                    write = len(pending[i]) == 2
                    out, residuals = ops.srm_interval_deferred_forward(inputs, *plan.constants, *form, True, write)
                    kept = [] if write or not pending[i] else pending[i]
                    pending[i] = [
                        *kept,
                        (
                            out[_OUT["p_next"]],
                            out[_OUT["q_next"]],
                            ("out", call_index, _OUT["p_next"]),
                            ("out", call_index, _OUT["q_next"]),
                        ),
                    ]
                else:
                    write = None
                    out, residuals = ops.srm_interval_forward(inputs, *plan.constants, *NO_RULE, True)
                for f, name in enumerate(_STATE_FIELDS):
                    produced = out[_STATE_OUTPUT[name]]
                    if name == "trace" and write is False:
                        produced = trace  # the deferred op passes its input trace on
                    if produced is not None:
                        values[i][f], sources[i][f] = produced, ("out", call_index, _STATE_OUTPUT[name])
                step_saved = interval.saved(interval.named(IntervalInputs, inputs), residuals)
                saved.extend(step_saved)
                calls.append(_Call(i, form is not None, write, input_sources[:11], len(step_saved)))
                rates.append(out[_OUT["r_post"]])
                if i == 0:
                    input_rates.append(out[_OUT["r_pre"]])
                x, x_source = out[_OUT["spikes"]], ("out", call_index, _OUT["spikes"])
        ctx.save_for_backward(*saved, *(keep for keep in keeps if keep is not None))
        ctx.setup = (ops, plans, calls, [keep is not None for keep in keeps], n_steps)
        ctx.mark_non_differentiable(*input_rates)
        ctx.set_materialize_grads(False)
        return (*rates, *input_rates)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grad_outputs: Optional[Tensor]):
        ops, plans, calls, has_keep, n_steps = ctx.setup
        saved_all = ctx.saved_tensors
        n_keeps = sum(has_keep)
        saved, keep_tensors = saved_all[: len(saved_all) - n_keeps], iter(saved_all[len(saved_all) - n_keeps :])
        keeps = [next(keep_tensors) if present else None for present in has_keep]
        gradients: dict[tuple, Tensor] = {}
        parameter_grads: list[list[Optional[Tensor]]] = [[None] * len(_PARAMETER_FIELDS) for _ in plans]
        rate_grads: list[Optional[Tensor]] = []  # per interval, last first

        def route(source, gradient: Optional[Tensor]) -> None:
            if gradient is None:
                return
            while source[0] == "reset":
                keep = keeps[source[2]]
                gradient = gradient * keep.to(gradient.dtype).view(-1, *([1] * (gradient.dim() - 1)))
                source = source[1]
            if source[0] == "out":
                previous = gradients.get(source)
                gradients[source] = gradient if previous is None else previous + gradient

        end = len(saved)
        for c in range(len(calls) - 1, -1, -1):
            call = calls[c]
            plan = plans[call.layer]
            call_saved = saved[end - call.n_saved : end]
            end -= call.n_saved
            grad_out = [gradients.pop(("out", c, f), None) for f in range(len(IntervalOutputs._fields))]
            # The rates are the node's outputs in the calls' order (step-major, layer-minor); nothing else reads them.
            grad_out[_OUT["r_post"]] = grad_outputs[c]
            if all(g is None for g in grad_out):
                rate_grads.extend([None] * len(plan.rates_fields()))
                continue
            grads = interval.backward_saved(
                ops,
                tuple(grad_out),
                call_saved,
                plan.constants,
                plan.form if call.deferred else NO_RULE,
                plan.need_rows,
                call.write if call.deferred else None,
            )
            for f, source in enumerate(call.sources):
                route(source, grads[f])
            rate_grads.extend(reversed([grads[_IN[name]] for name in plan.rates_fields()]))
            for j, name in enumerate(_PARAMETER_FIELDS):
                g = grads[_IN[name]]
                if g is not None and name not in _RATE_FIELDS:
                    previous = parameter_grads[call.layer][j]
                    parameter_grads[call.layer][j] = g if previous is None else previous + g
        flat = [
            g for plan, grads in zip(plans, parameter_grads) for p, g in zip(plan.parameters, grads) if p is not None
        ]
        return (None, *([None] * n_steps), *flat, *reversed(rate_grads))


def _pair(first, second):
    """``(p, q, p source, q source)`` from two ``(value, source)`` pairs."""
    return first[0], second[0], first[1], second[1]
