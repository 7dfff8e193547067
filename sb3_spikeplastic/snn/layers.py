"""A fully connected layer of SRM neurons whose synapses are plastic: efficacy :math:`W + \\alpha \\odot E`.

Within one plasticity interval the efficacy is constant and the network is feed-forward, so a layer processes
the whole interval at once: one (batched) matrix product for the synaptic input, a Toeplitz product for the PSP
filter, and only the element-wise threshold/refractory recursion runs step by step (SpikePropamine §2.2 with
SLAYER's SRM neuron).
"""

from __future__ import annotations

import collections
import math
from typing import NamedTuple, Optional

import torch
from torch import Tensor, nn

from . import _fast
from .neurons import (
    AlphaFilterState,
    SRMParameters,
    alpha_filter_operator,
    alpha_kernel_sum,
    spike_constants,
    srm_spikes,
)
from .plasticity import CompiledForm, PlasticityRule, PlasticState, compiled_form


#: a plastic layer that does not filter first multiplies its carried PSP state beside an interval's spikes (instead of
#: copying both into one block of rows) from this many spike values per environment on: the copy it saves then costs
#: more than the few small ops it adds (the paper network's input layer has 50 x 600, the CPU entry's 10 x 170)
CARRY_MIN_ROW_VALUES = 4096


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


class _FusedOutputs(NamedTuple):
    """What ``srm_interval_forward`` returns, in its order (``_fast/srm_interval.cpp``; empty tensors where an
    output does not apply): the interval's eight outputs, the updated trace and BCM threshold, then what the
    backward pass needs."""

    spikes: Tensor
    membrane: Tensor
    h1: Tensor
    h2: Tensor
    ref_h1: Tensor
    ref_h2: Tensor
    r_pre: Tensor
    r_post: Tensor
    trace: Tensor
    phi: Tensor
    product_in: Tensor
    surrogate: Tensor
    p: Tensor
    pre: Tensor
    m: Tensor
    carried: Tensor


#: What ``srm_interval_deferred_forward`` returns, in its order: as :class:`_FusedOutputs`, with the trace the
#: interval used (empty unless written) and the update it leaves pending, ``(p_next, q_next)``, before ``carried``.
_DeferredOutputs = collections.namedtuple("_DeferredOutputs", [*_FusedOutputs._fields[:-1], "p_next", "q_next",
                                                               "carried"])


#: the outputs of an interval, the first eight of both ops' (spikes, membrane, PSP and refractory states, rates)
INTERVAL_OUTPUTS = 8


class _IntervalConstants(NamedTuple):
    """What the fused interval op takes besides the tensors that change from call to call, fixed per layer,
    interval length, dtype and device (computed once, not on every network step).

    :param filters: the alpha-filter operator's PSP rows and end-state rows (:meth:`PlasticSRMLayer._psp_filter`;
        the op reads the filter's recurrence constants off them).
    :param filter_first: :attr:`PlasticSRMLayer.filter_first`.
    :param spike: ``(d, kappa, theta, width, scale)`` (:func:`~sb3_spikeplastic.snn.neurons.spike_constants`).
    :param e_max: the rule's trace bound.
    :param form: the rule's :class:`~sb3_spikeplastic.snn.plasticity.CompiledForm`; ``None`` when the op does not update
        the trace (static layers, rules of one's own).
    :param carry_state: :meth:`PlasticSRMLayer.carries_state` for this interval length.
    """

    filters: tuple[Tensor, Tensor, Tensor]
    filter_first: bool
    spike: tuple[float, float, float, float, float]
    e_max: float
    form: Optional[CompiledForm]
    carry_state: bool

    @property
    def rule_flags(self) -> tuple[bool, int]:
        """``(oja, modulation)`` as the op takes them."""
        return (self.form.oja, self.form.modulation) if self.form is not None else (False, 0)


class PlasticSRMLayer(nn.Module):
    """SRM layer with plastic synapses.

    .. math::
        u(t) = (W + \\alpha \\odot E)\\,(\\varepsilon * s_{in})(t) + (\\nu * s)(t), \\qquad s(t) = H(u(t) - \\vartheta)

    and, after each interval, ``E <- clip(F(r_pre, r_post, E), ±E_max)`` by the layer's rule.

    :param n_in: presynaptic neurons.
    :param n_out: neurons of this layer.
    :param rule: the layer's plasticity rule module (``StaticRule`` for fixed weights).
    :param neuron: SRM constants.
    :param w_init_mean: mean of the initial ``W``.
    :param w_init_std: standard deviation of the initial ``W``.
    :param alpha_init_mean: mean of the initial ``alpha`` (ignored by rules without a trace).
    :param alpha_init_std: standard deviation of the initial ``alpha``.
    """

    def __init__(self, n_in: int, n_out: int, rule: PlasticityRule, neuron: SRMParameters = SRMParameters(),
                 w_init_mean: float = 0.0, w_init_std: float = 1.0, alpha_init_mean: float = 0.0,
                 alpha_init_std: float = 1.0):
        super().__init__()
        if (rule.n_in, rule.n_out) != (n_in, n_out):
            raise ValueError(f"rule sized ({rule.n_in}, {rule.n_out}) does not fit layer ({n_in}, {n_out})")
        self.n_in, self.n_out, self.neuron, self.rule = n_in, n_out, neuron, rule
        self.weight = nn.Parameter(w_init_mean + w_init_std * torch.randn(n_out, n_in))
        self.alpha = nn.Parameter(alpha_init_mean + alpha_init_std * torch.randn(n_out, n_in)) if rule.has_trace else None
        self._filters: dict[tuple, tuple] = {}
        self._constants: dict[tuple, _IntervalConstants] = {}

    @property
    def plastic(self) -> bool:
        return self.alpha is not None

    def initial_state(self, batch: int, dtype: torch.dtype = torch.float32, device=None) -> LayerState:
        def zeros(n):
            return torch.zeros(batch, n, dtype=dtype, device=device)

        return LayerState(
            AlphaFilterState(zeros(self.n_in), zeros(self.n_in)),
            AlphaFilterState(zeros(self.n_out), zeros(self.n_out)),
            self.rule.initial_state(batch, dtype, device),
        )

    def efficacy(self, trace: Tensor) -> Tensor:
        """:math:`W + \\alpha \\odot E`, per environment ``(batch, n_out, n_in)``; just ``W`` for a static layer."""
        if self.alpha is None:
            return self.weight
        return torch.addcmul(self.weight, self.alpha, trace)

    def project(self, x: Tensor, trace: Tensor, efficacy_left: bool = False) -> Tensor:
        """The synaptic product :math:`x_b (W + \\alpha \\odot E_b)^T` of presynaptic rows ``x (batch, L, n_in)``.

        On CPU the compiled op of :mod:`sb3_spikeplastic.snn._fast` builds the efficacy of a few environments at a
        time (the ``(batch, n_out, n_in)`` efficacy and its gradient are never materialised). The eager path multiplies
        with the efficacy on the left when ``efficacy_left`` (so that its gradient comes out in its own
        ``(n_out, n_in)`` layout, not transposed: cheaper when ``n_in > n_out``; a plastic layer's only), else on the
        right.
        """
        if self.alpha is not None:
            fused = _fast.plastic_linear(x, self.weight, self.alpha, trace)
            if fused is not None:
                return fused
        w_eff = self.efficacy(trace)
        # A static layer's weight is shared, so its gradient comes out in its own layout either way; x W^T is also the
        # compiled interval's product, which gives the same values only in the same form (BLAS libraries need not sum
        # a product and its transpose in the same order).
        if efficacy_left and self.alpha is not None:
            return (w_eff @ x.transpose(-1, -2)).transpose(-1, -2)
        return x @ w_eff.transpose(-1, -2)

    def _psp_filter(self, length: int, dtype, device) -> tuple[Tensor, Tensor, Tensor]:
        """:func:`~sb3_spikeplastic.snn.neurons.alpha_filter_operator` for ``length`` steps, and its PSP rows and
        end-state rows as contiguous blocks."""
        key = (length, dtype, device)
        if key not in self._filters:
            op = alpha_filter_operator(length, self.neuron.tau_s, self.neuron.dt, dtype, device)
            self._filters[key] = (op, op[:length].contiguous(), op[length:].contiguous())
        return self._filters[key]

    def forward(self, spikes_in: Tensor, state: LayerState, monitor: bool = False,
                defer_update: bool = False) -> tuple[LayerOutput, LayerState]:
        """Run one plasticity interval of presynaptic spikes ``(batch, L, n_in)``.

        With ``monitor`` the output also carries the interval's neuromodulatory signal (computed once more, so
        it is off on the training path). The spikes come from :meth:`interval`, then ``E`` is updated from the
        interval's rates and acts from the next interval on. On the CPU both run as one compiled op each way, one
        autograd node when training (:class:`_FusedInterval`; other rules than the built-in ones run their
        :meth:`~sb3_spikeplastic.snn.plasticity.PlasticityRule.step` after it).

        With ``defer_update`` (a built-in rule on the CPU, without ``monitor``) the update is returned as the state's
        :attr:`~sb3_spikeplastic.snn.plasticity.PlasticState.pending` instead, and the next interval applies it in its
        own pass over ``E`` (:class:`_DeferredInterval`): the same values, one pass over the trace fewer each way.
        Every other such interval leaves the update before it pending too and passes its input trace on unchanged,
        so that a sequence stores half of its traces. Pending updates in ``state`` are always applied first.
        """
        ops = _fast.interval_ops()
        form = None
        fused = ops is not None and _FusedInterval.applies(self, spikes_in, state)
        if fused:
            constants = self._interval_constants(spikes_in.shape[1], spikes_in.dtype, spikes_in.device)
            form = constants.form
        pending = state.plastic.pending if self.plastic else None
        if form is not None and (defer_update or pending is not None) and not monitor:
            # Every other trace is stored: an interval with one update pending leaves it pending with its own and
            # passes its input trace on; the next one applies both and writes the trace out.
            write = pending is not None and (len(pending) == 2 or not defer_update)
            *outputs, trace, phi, p, q = _DeferredInterval.run_layer(self, constants, spikes_in, state, ops, write)
            kept = () if write or pending is None else pending
            plastic = PlasticState(trace, (phi,) if form.bcm else (), (*kept, (p, q)))
            if not defer_update:
                plastic = self.rule.apply_pending(plastic)
            return self._output(outputs, state, plastic, monitor)
        if pending is not None:
            state = state._replace(plastic=self.rule.apply_pending(state.plastic))
        if fused:
            *outputs, trace, phi = _FusedInterval.run_layer(self, constants, spikes_in, state, ops)
        else:
            synaptic, psp_state = self.interval(spikes_in, state.psp, state.plastic.trace)
            spikes, membrane, refractory = srm_spikes(synaptic, state.refractory, self.neuron)
            outputs = (spikes, membrane, *psp_state, *refractory, spikes_in.mean(1), spikes.mean(1))
        if form is not None:  # the op updated the trace
            plastic = PlasticState(trace, (phi,) if form.bcm else ())
        else:
            plastic = self.rule.step(outputs[6], outputs[7], state.plastic) if self.plastic else state.plastic
        return self._output(outputs, state, plastic, monitor)

    def _output(self, outputs: list, state: LayerState, plastic: PlasticState,
                monitor: bool) -> tuple[LayerOutput, LayerState]:
        spikes, membrane, h1, h2, ref_h1, ref_h2, r_pre, r_post = outputs
        psp_state, refractory = AlphaFilterState(h1, h2), AlphaFilterState(ref_h1, ref_h2)
        modulation = self.rule.modulation(r_post) if monitor and self.plastic else None
        return LayerOutput(spikes, membrane, modulation, r_post, r_pre), LayerState(psp_state, refractory, plastic)

    def interval(self, spikes_in: Tensor, psp: AlphaFilterState, trace: Tensor) -> tuple[Tensor, AlphaFilterState]:
        """The synaptic input of one interval ``(batch, L, n_out)`` and the PSP state carried out of it.

        The synaptic input ``K (S W_eff^T)`` (plus the decayed carried PSP) is associated so that the Toeplitz
        product ``K`` runs over the narrower side: ``(K S) W_eff^T`` when ``n_in <= n_out`` (e.g. the 64 -> 600
        output layer), ``K (S W_eff^T)`` otherwise (e.g. the 600 -> 64 input layer). Both equal filtering the
        presynaptic spikes first, because the filter is linear and ``W_eff`` is constant within the interval.
        """
        length = spikes_in.shape[1]
        operator, psp_rows, end_rows = self._psp_filter(length, spikes_in.dtype, spikes_in.device)
        if self.filter_first:
            # The interval's spikes and the carried PSP state (h1, h2) as L + 2 rows: one product filters them all.
            rows = torch.cat([spikes_in, psp.h1.unsqueeze(1), psp.h2.unsqueeze(1)], 1)
            filtered = operator @ rows  # (B, L + 2, n_in): the PSP of each step, then the end state
            return self.project(filtered[:, :length], trace), AlphaFilterState(filtered[:, length],
                                                                               filtered[:, length + 1])
        # The carried state rides along in the product: projecting h1 and h2 on their own would cost two
        # trace-sized outer products (and their sum) in the backward pass.
        if self.carries_state(length):  # beside the spikes, as the fused interval does (see carries_state)
            carried = torch.stack([psp.h1, psp.h2], 1)
            projected = _fast.plastic_linear(spikes_in, self.weight, self.alpha, trace, carried)
            if projected is not None:  # else (no compiled op: a GPU) the rows as below
                end = end_rows[:, :length] @ spikes_in + end_rows[:, length:] @ carried
                return psp_rows @ projected, AlphaFilterState(end[:, 0], end[:, 1])
        rows = torch.cat([spikes_in, psp.h1.unsqueeze(1), psp.h2.unsqueeze(1)], 1)
        end = end_rows @ rows
        return psp_rows @ self.project(rows, trace, efficacy_left=True), AlphaFilterState(end[:, 0], end[:, 1])

    def carries_state(self, length: int) -> bool:
        """Whether an interval of ``length`` steps multiplies the carried PSP state beside its spikes (a plastic
        layer that does not filter first, with at least :data:`CARRY_MIN_ROW_VALUES` spike values per environment),
        instead of copying both into one block of ``L + 2`` rows for the product."""
        return self.alpha is not None and not self.filter_first and length * self.n_in >= CARRY_MIN_ROW_VALUES

    def _interval_constants(self, length: int, dtype, device) -> _IntervalConstants:
        """The fused op's fixed arguments for intervals of ``length`` steps (cached)."""
        key = (length, dtype, device)
        if key not in self._constants:
            form = compiled_form(self.rule) if self.plastic else None
            self._constants[key] = _IntervalConstants(self._psp_filter(length, dtype, device)[1:], self.filter_first,
                                                      spike_constants(self.neuron), self.rule.e_max, form,
                                                      self.carries_state(length))
        return self._constants[key]

    @property
    def filter_first(self) -> bool:
        """Whether :meth:`interval` filters the presynaptic spikes before the product (``n_in <= n_out``)."""
        return self.n_in <= self.n_out


class _FusedInterval(torch.autograd.Function):
    """One layer interval on the CPU as a single autograd node: :meth:`PlasticSRMLayer.interval`, the spike
    recursion, the surrogate, both mean rates and, for a built-in rule (``form``), the trace update with the rule's
    terms, in one compiled op forward and one backward (``_fast/srm_interval.cpp``, where the backward pass is
    written out; the trace-sized gradients of the product and of the update are summed in one pass).

    The forward op runs the eager layer's and rule's ops and kernels in the same order, except that it filters by
    the alpha filter's recurrence (``_fast/alpha_filter.cpp``) where the eager layer multiplies by its operator, so
    membrane, states and the new trace equal the eager layer's to float rounding (spikes then only differ where the
    membrane lies within rounding of the threshold); the gradients are those of the eager graph (tested for every
    built-in rule) up to the surrogate, which the spike loop computes with an exponential of its own (within 2 ulp
    of :func:`~sb3_spikeplastic.snn.neurons.slayer_surrogate` in float32). Eager autograd builds ~15 nodes per layer
    and interval, whose overhead dominates the small CPU networks' training step.
    """

    @staticmethod
    def applies(layer: "PlasticSRMLayer", spikes_in: Tensor, state: LayerState) -> bool:
        tensors = [layer.weight, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2]
        if layer.alpha is not None:
            tensors += [layer.alpha, state.plastic.trace]
        return spikes_in.dim() == 3 and _fast.cpu_float_operands(spikes_in, *tensors)

    @staticmethod
    def run_layer(layer: "PlasticSRMLayer", constants: _IntervalConstants, spikes_in: Tensor, state: LayerState,
                  ops) -> list:
        """Spikes, membrane, PSP state, refractory state, ``r_pre``, ``r_post``, then the new trace and BCM
        threshold (``None`` when the op does not update them): one autograd node when training, the op alone
        without autograd (rollouts)."""
        inputs = _FusedInterval.arguments(layer, constants, spikes_in, state, ops)
        if torch.is_grad_enabled():
            return _FusedInterval.apply(*inputs)
        return _FusedInterval.outputs(_FusedInterval.run(*inputs, need_surrogate=False), constants.form)

    @staticmethod
    def arguments(layer: "PlasticSRMLayer", constants: _IntervalConstants, spikes_in: Tensor, state: LayerState,
                  ops) -> tuple:
        """The arguments of :meth:`run` (and of ``apply``) for one interval of ``layer``."""
        rule, form = layer.rule, constants.form
        bcm = form is not None and form.bcm
        return (spikes_in, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2, layer.weight,
                layer.alpha, state.plastic.trace if layer.alpha is not None else None,
                state.plastic.extra[0] if bcm else None, rule.eta if form is not None else None,
                rule.eta_phi if bcm else None, rule.psi if bcm else None,
                rule.w_m if form is not None and form.modulation else None, constants, ops)

    @staticmethod
    def run(spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, phi, eta, eta_phi, psi, w_m,
            constants: _IntervalConstants, ops, need_surrogate=True) -> _FusedOutputs:
        """The forward op's outputs."""
        oja, modulation = constants.rule_flags
        return _FusedOutputs._make(ops.srm_interval_forward(
            spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, phi, eta, eta_phi, psi, w_m, *constants.filters,
            constants.filter_first, *constants.spike, constants.e_max, oja, modulation, need_surrogate,
            constants.carry_state))

    @staticmethod
    def outputs(out: _FusedOutputs, form: Optional[CompiledForm]) -> list:
        """The outputs of :meth:`run_layer`: ``None`` for the new trace and BCM threshold where the op left them
        empty."""
        return [*out[:INTERVAL_OUTPUTS], out.trace if form is not None else None,
                out.phi if form is not None and form.bcm else None]

    @staticmethod
    def forward(ctx, spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, phi, eta, eta_phi, psi, w_m,
                constants, ops):
        out = _FusedInterval.run(spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, phi, eta, eta_phi, psi, w_m,
                                 constants, ops)
        ctx.save_for_backward(out.product_in, out.carried, weight, alpha, trace, out.surrogate, out.p, out.pre, out.m,
                              out.r_pre, out.r_post, phi, eta, eta_phi, psi, w_m)
        ctx.constants, ctx.ops = constants, ops
        ctx.mark_non_differentiable(*_constant_outputs(ctx, out))
        # Outputs the loss does not reach (the membrane, the output layer's spikes, unused rates, the final trace)
        # get None, which the op reads as zero, instead of a zero-filled tensor of their size.
        ctx.set_materialize_grads(False)
        return tuple(_FusedInterval.outputs(out, constants.form))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, d_spikes, _d_membrane, d_h1, d_h2, _d_ref_h1, _d_ref_h2, d_r_pre, d_r_post, d_trace, d_phi):
        (product_in, carried, weight, alpha, trace, surrogate, p, pre, m, r_pre, r_post, phi, eta, eta_phi, psi,
         w_m) = ctx.saved_tensors
        constants = ctx.constants
        oja, modulation = constants.rule_flags
        need_rows = any(ctx.needs_input_grad[:3])
        grads = ctx.ops.srm_interval_backward(
            d_spikes, d_h1, d_h2, d_r_pre, d_r_post, d_trace, d_phi, product_in, carried, weight, alpha, trace,
            surrogate, p, pre, m if modulation else None, r_pre, r_post, phi, eta, eta_phi, psi, w_m,
            *constants.filters, constants.filter_first, need_rows, constants.e_max, oja, modulation)
        d_x, d_h1, d_h2, d_w, d_alpha, d_trace, d_phi, d_eta_phi, d_psi, d_eta, d_w_m = grads
        if not need_rows:
            d_x = d_h1 = d_h2 = None
        plastic, bcm = alpha is not None, phi is not None  # the op's gradients are empty tensors where these are not
        return (d_x, d_h1, d_h2, None, None, d_w, d_alpha if plastic else None, d_trace if plastic else None,
                d_phi if bcm else None, d_eta if eta is not None else None, d_eta_phi if bcm else None,
                d_psi if bcm else None, d_w_m if w_m is not None else None, None, None)


class _DeferredInterval(torch.autograd.Function):
    """:class:`_FusedInterval` with the trace update deferred (``srm_interval_deferred_*`` in
    ``_fast/srm_interval.cpp``): the op first applies the state's pending updates ``clip((1 - eta) E + (eta p) (x)
    q)``, oldest first, in the pass over ``E`` that builds the efficacy, and returns its own update as ``(p, q)`` for
    the next interval, where :class:`_FusedInterval` passes over ``E`` once more for it. The trace it used is written
    out only with ``write``; otherwise the input trace is passed on (one of the updates stays pending), and the
    interval that writes recomputes the one between in registers, forward and backward: a sequence stores every other
    trace. Outputs as :meth:`_FusedInterval.run_layer`'s, the trace being the one written or the input passed on,
    then ``p`` and ``q``; the same values as :class:`_FusedInterval`'s bit for bit, gradients equal to float rounding
    (tested).
    """

    @staticmethod
    def run_layer(layer: "PlasticSRMLayer", constants: _IntervalConstants, spikes_in: Tensor,
                  state: LayerState, ops, write: bool) -> list:
        rule, form = layer.rule, constants.form
        bcm = form.bcm
        pending = [x for pair in state.plastic.pending or () for x in pair]
        p0, q0, p1, q1 = pending + [None] * (4 - len(pending))
        inputs = (spikes_in, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2, layer.weight,
                  layer.alpha, state.plastic.trace, p0, q0, p1, q1, state.plastic.extra[0] if bcm else None, rule.eta,
                  rule.eta_phi if bcm else None, rule.psi if bcm else None, rule.w_m if form.modulation else None,
                  constants, ops, write)
        if torch.is_grad_enabled():
            return list(_DeferredInterval.apply(*inputs))
        return _DeferredInterval.outputs(_DeferredInterval.run(*inputs, need_surrogate=False), state.plastic.trace,
                                         bcm)

    @staticmethod
    def run(spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, p0, q0, p1, q1, phi, eta, eta_phi, psi, w_m,
            constants: _IntervalConstants, ops, write: bool, need_surrogate=True) -> _DeferredOutputs:
        oja, modulation = constants.rule_flags
        return _DeferredOutputs._make(ops.srm_interval_deferred_forward(
            spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, p0, q0, p1, q1, phi, eta, eta_phi, psi, w_m,
            *constants.filters, constants.filter_first, *constants.spike, constants.e_max, oja, modulation,
            need_surrogate, write, constants.carry_state))

    @staticmethod
    def outputs(out: _DeferredOutputs, trace: Tensor, bcm: bool) -> list:
        """The 8 outputs of the interval, the trace passed on (the one written, else the input ``trace``), the BCM
        threshold (``None`` unless BCM), ``p`` and ``q``."""
        written = out.trace.numel() > 0
        return [*out[:INTERVAL_OUTPUTS], out.trace if written else trace, out.phi if bcm else None, out.p_next,
                out.q_next]

    @staticmethod
    def forward(ctx, spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, p0, q0, p1, q1, phi, eta, eta_phi, psi,
                w_m, constants, ops, write):
        out = _DeferredInterval.run(spikes_in, h1, h2, ref_h1, ref_h2, weight, alpha, trace, p0, q0, p1, q1, phi, eta,
                                    eta_phi, psi, w_m, constants, ops, write)
        ctx.save_for_backward(out.product_in, out.carried, weight, alpha, trace, p0, q0, p1, q1, out.surrogate, out.p,
                              out.pre, out.m, out.r_pre, out.r_post, phi, eta, eta_phi, psi, w_m)
        ctx.constants, ctx.ops, ctx.write = constants, ops, write
        ctx.mark_non_differentiable(*_constant_outputs(ctx, out))
        ctx.set_materialize_grads(False)
        # A trace passed on unwritten is the input itself: autograd returns it as a view with this node's history,
        # so that its gradient comes back here and is added in the row pass, not in a pass of its own.
        return tuple(_DeferredInterval.outputs(out, trace, phi is not None))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, d_spikes, _d_membrane, d_h1, d_h2, _d_ref_h1, _d_ref_h2, d_r_pre, d_r_post, d_trace, d_phi,
                 d_p, d_q):
        (product_in, carried, weight, alpha, trace, p0, q0, p1, q1, surrogate, p, pre, m, r_pre, r_post, phi, eta,
         eta_phi, psi, w_m) = ctx.saved_tensors
        constants = ctx.constants
        oja, modulation = constants.rule_flags
        need_rows = any(ctx.needs_input_grad[:3])
        grads = ctx.ops.srm_interval_deferred_backward(
            d_spikes, d_h1, d_h2, d_r_pre, d_r_post, d_trace, d_phi, d_p, d_q, product_in, carried, weight, alpha,
            trace, p0, q0, p1, q1, surrogate, p, pre, m if modulation else None, r_pre, r_post, phi, eta, eta_phi, psi,
            w_m, *constants.filters, constants.filter_first, need_rows, constants.e_max, oja, modulation, ctx.write)
        d_x, d_h1, d_h2, d_w, d_alpha, d_trace, d_phi, d_eta_phi, d_psi, d_eta, d_w_m, d_p0, d_q0, d_p1, d_q1 = grads
        if not need_rows:
            d_x = d_h1 = d_h2 = None
        first, second, bcm = p0 is not None, p1 is not None, phi is not None
        return (d_x, d_h1, d_h2, None, None, d_w, d_alpha, d_trace, d_p0 if first else None, d_q0 if first else None,
                d_p1 if second else None, d_q1 if second else None, d_phi if bcm else None, d_eta,
                d_eta_phi if bcm else None, d_psi if bcm else None, d_w_m if w_m is not None else None, None, None,
                None)


def _constant_outputs(ctx, out: _FusedOutputs | _DeferredOutputs) -> list[Tensor]:
    """The fused interval's outputs that carry no gradient: the membrane and the refractory state (as in
    :class:`~sb3_spikeplastic.snn.neurons.SRMSpikeRecursion`), and, when the input spikes and the carried PSP state have
    no gradient (the input layer), the PSP state and ``r_pre``, which depend on those only."""
    constant = [out.membrane, out.ref_h1, out.ref_h2]
    if not any(ctx.needs_input_grad[:3]):
        constant += [out.h1, out.h2, out.r_pre]
    return constant


def fan_in_std(n_in: int, rms_rate: float, neuron: SRMParameters, gain: float) -> float:
    """Initial weight std that puts the membrane's spread at ``gain * theta`` for inputs firing at ``rms_rate``.

    With zero-mean weights, :math:`\\mathrm{std}(u) \\approx \\sigma_W \\sqrt{n_{in}}\\, r_{rms} \\sum_k\\varepsilon(k)`.
    """
    return gain * neuron.theta / (alpha_kernel_sum(neuron.tau_s, neuron.dt) * rms_rate * math.sqrt(n_in))
