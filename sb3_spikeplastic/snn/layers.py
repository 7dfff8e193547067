"""A fully connected layer of SRM neurons whose synapses are plastic: efficacy :math:`W + \\alpha \\odot E`.

The module holds the layer's parameters and its constants per interval length; one interval runs as the pure step
:func:`~sb3_spikeplastic.snn.functional.interval_step` (eager PyTorch) or as the compiled op
(:data:`~sb3_spikeplastic.snn.fused_interval.FUSED_INTERVAL`), whichever :func:`~sb3_spikeplastic.snn._fast.dispatch`
picks for the call.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor, nn

from . import _fast
from ._fast.interval import IntervalConstants, RuleForm
from .functional import IntervalParameters, LayerOutput, LayerState, efficacy, interval_step
from .fused_interval import FUSED_INTERVAL
from .neurons import AlphaFilterState, SRMParameters, alpha_filter_operator, alpha_kernel_sum, spike_constants
from .plasticity import PlasticityRule, compiled_form

__all__ = ["CARRY_MIN_ROW_VALUES", "LayerOutput", "LayerState", "PlasticSRMLayer", "fan_in_std"]

#: a plastic layer that does not filter first multiplies its carried PSP state beside an interval's spikes (instead of
#: copying both into one block of rows) from this many spike values per environment on: the copy it saves then costs
#: more than the few small ops it adds (the paper network's input layer has 50 x 600, the CPU entry's 10 x 170)
CARRY_MIN_ROW_VALUES = 4096


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

    def __init__(
        self,
        n_in: int,
        n_out: int,
        rule: PlasticityRule,
        neuron: SRMParameters = SRMParameters(),
        w_init_mean: float = 0.0,
        w_init_std: float = 1.0,
        alpha_init_mean: float = 0.0,
        alpha_init_std: float = 1.0,
    ):
        super().__init__()
        if (rule.n_in, rule.n_out) != (n_in, n_out):
            raise ValueError(f"rule sized ({rule.n_in}, {rule.n_out}) does not fit layer ({n_in}, {n_out})")
        self.n_in, self.n_out, self.neuron, self.rule = n_in, n_out, neuron, rule
        self.weight = nn.Parameter(w_init_mean + w_init_std * torch.randn(n_out, n_in))
        self.alpha = (
            nn.Parameter(alpha_init_mean + alpha_init_std * torch.randn(n_out, n_in)) if rule.has_trace else None
        )
        self._intervals: dict[tuple, tuple[Tensor, IntervalConstants, Optional[RuleForm]]] = {}

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
        return efficacy(self.weight, self.alpha, trace)

    def forward(
        self,
        spikes_in: Tensor,
        state: LayerState,
        monitor: bool = False,
        defer_update: bool = False,
        modulator: Optional[Tensor] = None,
    ) -> tuple[LayerOutput, LayerState]:
        """Run one plasticity interval of presynaptic spikes ``(batch, L, n_in)``
        (:func:`~sb3_spikeplastic.snn.functional.interval_step`).

        With ``monitor`` the output also carries the interval's neuromodulatory signal (computed once more, so
        it is off on the training path). On the CPU the interval runs as one compiled op each way, one autograd node
        when training (:func:`~sb3_spikeplastic.snn.fused_interval.fused_interval_step`). With ``defer_update`` (a
        built-in rule on the CPU, without ``monitor``) the update is returned as the state's
        :attr:`~sb3_spikeplastic.snn.plasticity.PlasticState.pending` instead, and the next interval applies it in
        its own pass over ``E``: the same values, one pass over the trace fewer each way. Pending updates in
        ``state`` are always applied first. ``modulator`` ``(batch, k)``: the signal from outside the network of a
        rule that :attr:`~sb3_spikeplastic.snn.plasticity.PlasticityRule.takes_modulator`.
        """
        parameters = self.interval_parameters(spikes_in.shape[1], spikes_in.dtype, spikes_in.device)
        return _fast.dispatch(
            FUSED_INTERVAL, interval_step, spikes_in, state, parameters, monitor, defer_update, modulator
        )

    def interval_parameters(self, length: int, dtype, device) -> IntervalParameters:
        """What an interval of ``length`` steps reads besides its input and state: the parameters, and the filter's
        operator and constants for this length (cached)."""
        operator, constants, form = self._interval(length, dtype, device)
        return IntervalParameters(self.weight, self.alpha, self.rule, self.neuron, operator, constants, form)

    def _interval(self, length: int, dtype, device) -> tuple[Tensor, IntervalConstants, Optional[RuleForm]]:
        """:func:`~sb3_spikeplastic.snn.neurons.alpha_filter_operator` for ``length`` steps, the interval's
        constants with its PSP rows and end-state rows as contiguous blocks, and the rule's compiled form (cached)."""
        key = (length, dtype, device)
        if key not in self._intervals:
            op = alpha_filter_operator(length, self.neuron.tau_s, self.neuron.dt, dtype, device)
            constants = IntervalConstants(
                op[:length].contiguous(),
                op[length:].contiguous(),
                self.filter_first,
                *spike_constants(self.neuron),
                self.rule.e_max,
                self.carries_state(length),
            )
            form = compiled_form(self.rule) if self.plastic else None
            self._intervals[key] = (op, constants, form)
        return self._intervals[key]

    def _interval_constants(self, length: int, dtype, device) -> IntervalConstants:
        """The interval's constants for ``length`` steps (cached)."""
        return self._interval(length, dtype, device)[1]

    def carries_state(self, length: int) -> bool:
        """Whether an interval of ``length`` steps multiplies the carried PSP state beside its spikes (a plastic
        layer that does not filter first, with at least :data:`CARRY_MIN_ROW_VALUES` spike values per environment),
        instead of copying both into one block of ``L + 2`` rows for the product."""
        return self.alpha is not None and not self.filter_first and length * self.n_in >= CARRY_MIN_ROW_VALUES

    @property
    def filter_first(self) -> bool:
        """Whether the interval filters the presynaptic spikes before the product (``n_in <= n_out``)."""
        return self.n_in <= self.n_out


def fan_in_std(n_in: int, rms_rate: float, neuron: SRMParameters, gain: float) -> float:
    """Initial weight std that puts the membrane's spread at ``gain * theta`` for inputs firing at ``rms_rate``.

    With zero-mean weights,
    :math:`\\mathrm{std}(u) \\approx \\sigma_W \\sqrt{n_{in}}\\, r_{rms} \\sum_k\\varepsilon(k)`.
    """
    return gain * neuron.theta / (alpha_kernel_sum(neuron.tau_s, neuron.dt) * rms_rate * math.sqrt(n_in))
