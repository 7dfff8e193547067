"""Differentiable plasticity and neuromodulation rules (SpikePropamine §2.2–2.3) and their registry.

A plastic layer's efficacy is :math:`W + \\alpha \\odot E(t)`; ``W`` and ``alpha`` are learned between rollouts and
the trace ``E`` (one per environment, zero at episode start) is updated every :math:`\\Delta\\tau` network steps from
the interval's firing rates :math:`r_{pre}` (presynaptic, shape ``(batch, n_in)``) and :math:`r_{post}`
(postsynaptic, ``(batch, n_out)``), then clipped to :math:`[-E_{max}, E_{max}]`.

The rule math is a set of pure functions (:func:`dp_oja_update`, ...). A rule *module* holds one layer's learned
local parameters (:math:`\\eta`, :math:`\\psi`, :math:`W_m`, ...) and maps ``(r_pre, r_post, state) -> state``;
the per-environment state (:class:`PlasticState`) is always passed in and returned, never stored.

Users add rules by subclassing :class:`PlasticityRule` and decorating it with :func:`register_rule`; the name
is then accepted everywhere a rule name is (``policy_kwargs=dict(rule="my-rule")``).
"""

from __future__ import annotations

import math
from typing import Callable, ClassVar, NamedTuple, Optional

import torch
from torch import Tensor, nn

from . import _fast
from ._fast.interval import RuleForm


class HebbianTerms(NamedTuple):
    r"""The factors of a rule's trace update :math:`E' = (1-\eta)E + \eta\,(post - [E\,pre]) \otimes pre`.

    :param post: postsynaptic factor ``(B, n_out)`` (``r_post``, or ``M * r_post`` for the modulated rules).
    :param pre: presynaptic factor ``(B, n_in)`` (``r_pre``, or ``r_beta`` for the BCM rules).
    :param subtract_prediction: the Oja forms: subtract the trace's prediction ``E pre`` from ``post``.
    :param extra: the rule's new extra state (BCM: ``(phi',)``).
    """

    post: Tensor
    pre: Tensor
    subtract_prediction: bool
    extra: tuple[Tensor, ...] = ()


class PlasticState(NamedTuple):
    r"""Per-environment plastic state of one layer.

    :param trace: the synaptic trace ``E``, shape ``(batch, n_out, n_in)`` (``(batch, 0)`` for rules without one).
    :param extra: rule-specific state tensors with a leading batch axis (BCM: ``(phi,)``), reset with ``E``.
    :param pending: trace updates not applied yet, oldest first, each ``(p, q)`` with shapes ``(batch, n_out)`` and
        ``(batch, n_in)`` (:class:`HebbianTerms`' ``post`` and ``pre``, the prediction already subtracted): each
        makes the trace :math:`\mathrm{clip}((1-\eta) E + (\eta p) \otimes q)`. Only the states inside
        :meth:`~sb3_spikeplastic.snn.network.SpikingPlasticNetwork.forward_sequence` have them (the next interval
        applies them in its own pass over ``E``; one or two, so that only every other trace is stored); ``None``
        everywhere else.
    """

    trace: Tensor
    extra: tuple[Tensor, ...] = ()
    pending: Optional[tuple[tuple[Tensor, Tensor], ...]] = None


# ---------------------------------------------------------------------------------------------------------------
# Pure rule math. Shapes: E (B, n_out, n_in), r_pre (B, n_in), r_post / M (B, n_out); eta a scalar tensor.


def decay_and_add_outer(E: Tensor, eta: Tensor, post: Tensor, pre: Tensor) -> Tensor:
    r""":math:`(1-\eta)E + \eta\, post \otimes pre`, the shape every rule's update takes.

    One ``addcmul`` with ``eta`` folded into the (small) postsynaptic vector: the trace-sized arrays are the
    training step's main cost, and this makes two passes over them instead of four.
    """
    return torch.addcmul(E * (1 - eta), (eta * post).unsqueeze(-1), pre.unsqueeze(-2))


def hebbian_update(E: Tensor, eta: Tensor, terms: HebbianTerms) -> Tensor:
    """The update every built-in rule shares, from its :class:`HebbianTerms` (no clipping)."""
    post = oja_postsynaptic_term(E, terms.pre, terms.post) if terms.subtract_prediction else terms.post
    return decay_and_add_outer(E, eta, post, terms.pre)


def hebbian_trace_step(E: Tensor, eta: Tensor, terms: HebbianTerms, e_max: float) -> Tensor:
    """:func:`hebbian_update` followed by the clip to :math:`[-E_{max}, E_{max}]`.

    On CPU this runs the fused, compiled op of :mod:`sb3_spikeplastic.snn._fast` (one pass over the trace forward and
    one backward instead of ~20 eager ones); elsewhere, or when it is unavailable, the eager ops, which give the
    same values to float rounding.
    """
    return _fast.dispatch(
        _fast.TRACE_STEP, _trace_step_eager, E, terms.post, terms.pre, eta, e_max, terms.subtract_prediction
    )


def _trace_step_eager(E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Tensor:
    """:func:`hebbian_trace_step` in eager ops, with the compiled op's arguments (:data:`~._fast.TRACE_STEP`)."""
    return hebbian_update(E, eta, HebbianTerms(post, pre, oja)).clamp(-e_max, e_max)


def dp_linear_update(E: Tensor, r_pre: Tensor, r_post: Tensor, eta: Tensor) -> Tensor:
    """Linear-decay DP rule (paper eq. 6): :math:`E' = (1-\\eta)E + \\eta\\, r_{post} \\otimes r_{pre}`."""
    return decay_and_add_outer(E, eta, r_post, r_pre)


def oja_postsynaptic_term(E: Tensor, r_pre: Tensor, post: Tensor) -> Tensor:
    """The bracket of the paper's Oja forms, :math:`post - E\\,r_{pre}`, shape ``(B, n_out)``."""
    return post - (E @ r_pre.unsqueeze(-1)).squeeze(-1)


def dp_oja_update(E: Tensor, r_pre: Tensor, r_post: Tensor, eta: Tensor) -> Tensor:
    """DP-Oja (paper eq. 7, as written): :math:`E' = (1-\\eta)E + \\eta\\,(r_{post} - E r_{pre}) \\otimes r_{pre}`.

    Textbook Oja subtracts :math:`y^2 w` (the decay scales with the postsynaptic rate squared); the paper's form
    subtracts the trace's own prediction :math:`E r_{pre}` of the postsynaptic rate instead. We follow the paper.
    """
    return decay_and_add_outer(E, eta, oja_postsynaptic_term(E, r_pre, r_post), r_pre)


def bcm_presynaptic_term(r_pre: Tensor, phi: Tensor, psi: Tensor) -> Tensor:
    """:math:`r_\\beta = r_{pre} \\odot (r_{pre} - (\\phi + \\psi))` (paper eq. 9).

    Textbook BCM puts the sliding threshold on the *postsynaptic* rate; the paper's form slides it on the
    presynaptic side, with a learned offset ``psi``. We follow the paper.
    """
    return r_pre * (r_pre - (phi + psi))


def bcm_threshold_update(phi: Tensor, r_pre: Tensor, eta_phi: Tensor) -> Tensor:
    """Sliding threshold EMA (paper eq. 10, :math:`\\omega` = identity):
    :math:`\\phi' = (1-\\eta_\\phi)\\phi + \\eta_\\phi r_{pre}`."""
    return (1 - eta_phi) * phi + eta_phi * r_pre


def dp_bcm_update(E: Tensor, r_beta: Tensor, r_post: Tensor, eta: Tensor) -> Tensor:
    """DP-BCM (paper eq. 8): :math:`E' = (1-\\eta)E + \\eta\\, r_{post} \\otimes r_\\beta`."""
    return decay_and_add_outer(E, eta, r_post, r_beta)


def ndp_oja_update(E: Tensor, r_pre: Tensor, r_post: Tensor, modulation: Tensor, eta: Tensor) -> Tensor:
    """NDP-Oja (paper eq. 11): :math:`E' = (1-\\eta)E + \\eta\\,(M \\odot r_{post} - E r_{pre}) \\otimes r_{pre}`."""
    return decay_and_add_outer(E, eta, oja_postsynaptic_term(E, r_pre, modulation * r_post), r_pre)


def ndp_bcm_update(E: Tensor, r_beta: Tensor, r_post: Tensor, modulation: Tensor, eta: Tensor) -> Tensor:
    """NDP-BCM (paper eq. 13): :math:`E' = (1-\\eta)E + \\eta\\,(M \\odot r_{post}) \\otimes r_\\beta`."""
    return decay_and_add_outer(E, eta, modulation * r_post, r_beta)


MODULATION_FORMS = ("linear", "tanh")


def modulatory_signal(w_m: Tensor, r_post: Tensor, form: str = "tanh") -> Tensor:
    """Neuromodulatory signal of a layer: :math:`M = \\tanh(W_m r_{post})` (``form="tanh"``, the default) or the
    paper's eq. 12 as written, :math:`M = W_m r_{post}` (``form="linear"``).

    The bound is a stabiliser, not the paper's equation: unbounded, ``M`` lets Hebbian positive feedback drive
    gradients through the trace to 1e11+ and the HalfCheetah policy does not learn (``docs/halfcheetah.md``).
    """
    m = r_post @ w_m.T
    return torch.tanh(m) if form == "tanh" else m


#: the modulation source of a rule whose signal comes from its own layer's rates (:func:`modulatory_signal`)
LEARNED_SOURCE = "learned"


def external_modulatory_signal(
    modulator: Tensor,
    gains: Tensor,
    bias: Tensor,
    form: str = "tanh",
    w_m: Optional[Tensor] = None,
    r_post: Optional[Tensor] = None,
) -> Tensor:
    r"""Neuromodulatory signal from a signal outside the layer (a reward, a TD error...):
    :math:`M = f(G\,m + b\,[+\,W_m r_{post}])`, :math:`f` = ``tanh`` or the identity (``form``).

    The paper's discussion proposes this extension, "a pre-defined global signal ... an online reward signal
    emulating dopaminergic neurons"; the learned per-neuron gains ``G`` and offsets ``b`` let each neuron read the
    signal with its own sign and size (Backpropamine, Miconi et al., 2019, uses one learned gain per network).

    :param modulator: the signal ``m`` per environment ``(..., k)``.
    :param gains: ``G`` ``(n_out, k)``.
    :param bias: ``b`` ``(n_out,)``.
    :param form: ``"tanh"`` or ``"linear"``.
    :param w_m: ``W_m`` to add the learned term :math:`W_m r_{post}` (``None``: the external term alone).
    :param r_post: the postsynaptic rates ``(..., n_out)`` (with ``w_m``).
    """
    m = torch.addmm(bias, modulator.flatten(0, -2), gains.T).view(*modulator.shape[:-1], -1)
    if w_m is not None:
        m = m + r_post @ w_m.T
    return torch.tanh(m) if form == "tanh" else m


# ---------------------------------------------------------------------------------------------------------------
# Rule modules and registry.

RULES: dict[str, type["PlasticityRule"]] = {}


def register_rule(name: str, *, override: bool = False) -> Callable[[type["PlasticityRule"]], type["PlasticityRule"]]:
    """Class decorator that registers a :class:`PlasticityRule` subclass under ``name``.

    :param name: the name accepted by ``policy_kwargs=dict(rule=name)`` and ``--rule``.
    :param override: allow replacing an existing registration (otherwise a duplicate name is an error).
    """

    def decorator(cls: type[PlasticityRule]) -> type[PlasticityRule]:
        if not (isinstance(cls, type) and issubclass(cls, PlasticityRule)):
            raise TypeError(f"register_rule({name!r}) expects a PlasticityRule subclass, got {cls!r}")
        if name in RULES and not override:
            raise ValueError(f"plasticity rule {name!r} is already registered (pass override=True to replace it)")
        cls.name = name
        RULES[name] = cls
        return cls

    return decorator


def available_rules() -> tuple[str, ...]:
    """Names of all registered rules."""
    return tuple(RULES)


def get_rule_class(name: str) -> type["PlasticityRule"]:
    """The rule class registered as ``name``; an unknown name is a one-line error listing the accepted ones."""
    try:
        return RULES[name]
    except KeyError:
        raise ValueError(f"unknown rule {name!r}; accepted: {', '.join(RULES)}") from None


def _logit(p: float, name: str = "rate") -> float:
    if not 0.0 < p < 1.0:
        raise ValueError(f"{name}={p!r} must lie in (0, 1)")
    return math.log(p / (1 - p))


class PlasticityRule(nn.Module):
    r"""Base class of a plasticity rule for one layer: its learned local parameters and its update.

    Subclasses implement either :meth:`hebbian_terms` (rules of the form
    :math:`(1-\eta)E + \eta\,(post - [E\,pre]) \otimes pre`, as all built-in rules are; :meth:`step` then runs the
    fused update) or :meth:`update` (any equation, without clipping), and, if they keep state besides ``E``,
    :meth:`initial_extra_state`. :meth:`step` applies one update and the clip to ``±e_max``.

    A rule that takes its neuromodulation from outside the network (a reward, a TD error:
    :mod:`sb3_spikeplastic.sb3.modulation`) accepts ``modulation_source`` in its constructor, sets
    :attr:`takes_modulator`, and receives the signal as the ``modulator`` argument of :meth:`hebbian_terms` /
    :meth:`update` / :meth:`modulation` (``(batch, k)``, one value per environment and channel for the whole
    environment step). The NDP rules do (:class:`NDPOjaRule`).

    :param n_in: presynaptic neurons.
    :param n_out: postsynaptic neurons.
    :param e_max: trace clip bound :math:`E_{max}` (applied after every update).
    :param eta_init: initial plasticity rate :math:`\eta \in (0, 1)`; learned as ``sigmoid(eta_logit)``.
    """

    name: ClassVar[str] = ""
    #: whether the rule keeps a trace ``E`` (``False`` only for the fixed-weight baseline)
    has_trace: ClassVar[bool] = True
    #: whether the rule takes a neuromodulatory signal (reported by monitoring)
    modulated: ClassVar[bool] = False
    #: default mean of the plasticity coefficients ``alpha`` of the layers using this rule. The trace lives on the
    #: scale of products of rates in spikes/ms (|E| ~ 0.003-0.03), so ``alpha`` must start large and positive for
    #: the plastic term to matter at all (measured: zero-mean alpha learned no better than the static network).
    alpha_init_mean: ClassVar[float] = 10.0

    def __init__(self, n_in: int, n_out: int, e_max: float = 1.0, eta_init: float = 0.05):
        super().__init__()
        if e_max <= 0 or not math.isfinite(e_max):
            raise ValueError(f"e_max must be a positive finite number, got {e_max!r}")
        self.n_in, self.n_out, self.e_max = n_in, n_out, float(e_max)
        if self.has_trace:
            self.eta_logit = nn.Parameter(torch.tensor(_logit(eta_init, "eta_init")))

    @property
    def eta(self) -> Tensor:
        """The plasticity rate :math:`\\eta = \\sigma(\\eta_{logit}) \\in (0, 1)`."""
        return torch.sigmoid(self.eta_logit)

    def initial_extra_state(self, batch: int, dtype: torch.dtype, device) -> tuple[Tensor, ...]:
        """Rule-specific state at episode start (default: none)."""
        return ()

    def initial_state(self, batch: int, dtype: torch.dtype = torch.float32, device=None) -> PlasticState:
        """Zero trace and initial rule state for ``batch`` environments."""
        shape = (batch, self.n_out, self.n_in) if self.has_trace else (batch, 0)
        return PlasticState(
            torch.zeros(shape, dtype=dtype, device=device), self.initial_extra_state(batch, dtype, device)
        )

    @property
    def takes_modulator(self) -> bool:
        """Whether the rule's updates read a signal from outside the network (the ``modulator`` argument)."""
        return False

    def hebbian_terms(self, r_pre: Tensor, r_post: Tensor, state: PlasticState, *modulator: Tensor) -> HebbianTerms:
        """The factors of the update for rules of the shared Hebbian form (see the class docstring); ``modulator``
        only for rules that :attr:`takes_modulator`."""
        raise NotImplementedError(f"{type(self).__name__} implements neither hebbian_terms nor update")

    def update(self, r_pre: Tensor, r_post: Tensor, state: PlasticState, *modulator: Tensor) -> PlasticState:
        """The rule's equation: the state after one interval with rates ``r_pre``, ``r_post`` (no clipping).

        The default evaluates :meth:`hebbian_terms` with the eager ops (:func:`hebbian_update`)."""
        terms = self.hebbian_terms(r_pre, r_post, state, *modulator)
        return PlasticState(hebbian_update(state.trace, self.eta, terms), terms.extra)

    def modulation(self, r_post: Tensor, modulator: Optional[Tensor] = None) -> Optional[Tensor]:
        """The neuromodulatory signal for these rates (``None`` for unmodulated rules)."""
        return None

    def step(
        self, r_pre: Tensor, r_post: Tensor, state: PlasticState, modulator: Optional[Tensor] = None
    ) -> PlasticState:
        """One plasticity update followed by the clip of ``E`` to ``[-e_max, e_max]``; ``modulator`` ``(batch, k)``
        for rules that :attr:`takes_modulator` (and only for them)."""
        if not self.has_trace:
            return state
        given = () if modulator is None else (modulator,)
        if type(self).update is PlasticityRule.update:
            terms = self.hebbian_terms(r_pre, r_post, state, *given)
            return PlasticState(hebbian_trace_step(state.trace, self.eta, terms, self.e_max), terms.extra)
        new = self.update(r_pre, r_post, state, *given)
        return PlasticState(new.trace.clamp(-self.e_max, self.e_max), new.extra)

    def modulation_macs(self) -> int:
        """Multiply-accumulates per update that the neuromodulatory signal costs (0 for unmodulated rules)."""
        return 0

    def apply_pending(self, state: PlasticState) -> PlasticState:
        """The state with its pending updates (:attr:`PlasticState.pending`) applied by :func:`hebbian_trace_step`,
        oldest first: the trace :meth:`step` would have given."""
        if state.pending is None:
            return state
        trace = state.trace
        for p, q in state.pending:
            trace = hebbian_trace_step(trace, self.eta, HebbianTerms(p, q, False), self.e_max)
        return PlasticState(trace, state.extra)

    def extra_repr(self) -> str:
        return f"n_in={self.n_in}, n_out={self.n_out}, e_max={self.e_max}"


@register_rule("static")
class StaticRule(PlasticityRule):
    """No plasticity: a fixed-weight SNN, the paper's baseline. Keeps no trace."""

    has_trace = False
    alpha_init_mean = 0.0


@register_rule("dp-linear")
class DPLinearRule(PlasticityRule):
    """Linear-decay differentiable plasticity, :func:`dp_linear_update`. Learned: :math:`\\eta`."""

    def hebbian_terms(self, r_pre, r_post, state):
        return HebbianTerms(r_post, r_pre, False)


@register_rule("dp-oja")
class DPOjaRule(PlasticityRule):
    """Differentiable Oja's rule as written in the paper, :func:`dp_oja_update`. Learned: :math:`\\eta`."""

    def hebbian_terms(self, r_pre, r_post, state):
        return HebbianTerms(r_post, r_pre, True)


class _BCMRule(PlasticityRule):
    """Shared parameters and state of the BCM rules: sliding threshold ``phi`` (state) with rate ``eta_phi`` and
    learned offset ``psi``.

    :param eta_phi_init: initial :math:`\\eta_\\phi \\in (0, 1)` (learned as a sigmoid).
    """

    # r_beta is a product of two rates (~1e-3), an order of magnitude below the Oja/linear traces.
    alpha_init_mean = 30.0

    def __init__(self, n_in: int, n_out: int, e_max: float = 1.0, eta_init: float = 0.05, eta_phi_init: float = 0.05):
        super().__init__(n_in, n_out, e_max, eta_init)
        self.eta_phi_logit = nn.Parameter(torch.tensor(_logit(eta_phi_init, "eta_phi_init")))
        self.psi = nn.Parameter(torch.zeros(n_in))

    @property
    def eta_phi(self) -> Tensor:
        return torch.sigmoid(self.eta_phi_logit)

    def initial_extra_state(self, batch, dtype, device):
        return (torch.zeros(batch, self.n_in, dtype=dtype, device=device),)

    def presynaptic(self, r_pre: Tensor, state: PlasticState) -> tuple[Tensor, Tensor]:
        """``(r_beta, phi')``: ``r_beta`` uses ``phi`` before its own update."""
        (phi,) = state.extra
        return bcm_presynaptic_term(r_pre, phi, self.psi), bcm_threshold_update(phi, r_pre, self.eta_phi)


@register_rule("dp-bcm")
class DPBCMRule(_BCMRule):
    """Differentiable BCM as written in the paper, :func:`dp_bcm_update`. Learned: :math:`\\eta, \\eta_\\phi, \\psi`."""

    def hebbian_terms(self, r_pre, r_post, state):
        r_beta, phi = self.presynaptic(r_pre, state)
        return HebbianTerms(r_post, r_beta, False, (phi,))


class _ModulatedMixin:
    r"""The neuromodulatory signal's parameters and form: learned modulatory weights
    :math:`W_m \in R^{n_{out} \times n_{out}}` (``modulation_source="learned"``, :func:`modulatory_signal`), or
    per-neuron gains ``G`` ``(n_out, k)`` and offsets ``b`` for a signal from outside the network
    (:func:`external_modulatory_signal`), with ``W_m`` beside them if ``learned_modulation``."""

    modulated = True

    def _init_modulation(
        self,
        n_out: int,
        wm_init_gain: float,
        wm_init_std: float,
        modulation: str,
        modulation_source: str,
        modulation_channels: int,
        learned_modulation: Optional[bool],
    ) -> None:
        if modulation not in MODULATION_FORMS:
            raise ValueError(f"unknown modulation form {modulation!r}; accepted: {', '.join(MODULATION_FORMS)}")
        if not isinstance(modulation_source, str) or not modulation_source:
            raise ValueError(f"modulation_source={modulation_source!r} must be a source name such as 'reward'")
        if isinstance(modulation_channels, bool) or not isinstance(modulation_channels, int) or modulation_channels < 1:
            raise ValueError(f"modulation_channels={modulation_channels!r} must be a positive integer")
        external = modulation_source != LEARNED_SOURCE
        if learned_modulation is None:
            learned_modulation = not external
        if not (external or learned_modulation):
            raise ValueError("learned_modulation=False needs an external modulation_source (e.g. 'reward')")
        self.modulation_form, self.modulation_source = modulation, modulation_source
        # Starting near gain * identity makes M ~ r_post: the rule begins close to its DP form.
        self.w_m = (
            nn.Parameter(wm_init_gain * torch.eye(n_out) + wm_init_std * torch.randn(n_out, n_out))
            if learned_modulation
            else None
        )
        if external:
            # The channels' mean gain is wm_init_gain: M ~ f(gain * m) in every neuron at the start.
            k = modulation_channels
            self.modulator_gains = nn.Parameter(wm_init_gain / k + wm_init_std * torch.randn(n_out, k))
            self.modulator_bias = nn.Parameter(torch.zeros(n_out))

    @property
    def takes_modulator(self) -> bool:
        return self.modulation_source != LEARNED_SOURCE

    def modulation(self, r_post: Tensor, modulator: Optional[Tensor] = None) -> Tensor:
        if not self.takes_modulator:
            return modulatory_signal(self.w_m, r_post, self.modulation_form)
        if modulator is None:
            raise ValueError(
                f"rule {self.name!r} with modulation_source={self.modulation_source!r} needs a modulator "
                "(batch, channels) on every update; none was passed"
            )
        return external_modulatory_signal(
            modulator, self.modulator_gains, self.modulator_bias, self.modulation_form, self.w_m, r_post
        )

    def modulation_macs(self) -> int:
        learned = self.n_out**2 if self.w_m is not None else 0
        return learned + (self.n_out * self.modulator_gains.shape[1] if self.takes_modulator else 0)


@register_rule("ndp-oja")
class NDPOjaRule(_ModulatedMixin, PlasticityRule):
    r"""Neuromodulated Oja (paper eqs. 11–12), :func:`ndp_oja_update`. Learned: :math:`\eta, W_m` (``G, b`` for an
    external signal).

    :param wm_init_gain: ``W_m`` starts at ``wm_init_gain * I + N(0, wm_init_std^2)``; an external signal's gains
        ``G`` at ``wm_init_gain / k + N(0, wm_init_std^2)``.
    :param wm_init_std: see ``wm_init_gain``.
    :param modulation: ``"tanh"`` (the default: :math:`M = \tanh(W_m r_{post})`, bounded, a stabiliser) or
        ``"linear"`` (the paper as written, :math:`M = W_m r_{post}`; its gradients explode on HalfCheetah).
    :param modulation_source: ``"learned"`` (the paper, :func:`modulatory_signal`) or the name of a signal from
        outside the network, which the network's forward then takes as its ``modulator``
        (:mod:`sb3_spikeplastic.sb3.modulation`: ``"reward"``, ``"td-error"``, sources of one's own):
        :math:`M = f(G\,m + b)`, :func:`external_modulatory_signal`.
    :param modulation_channels: ``k``, the external signal's channels.
    :param learned_modulation: add the learned term :math:`W_m r_{post}` to the external one (``None``: only for
        ``"learned"``).
    """

    def __init__(
        self,
        n_in,
        n_out,
        e_max=1.0,
        eta_init=0.05,
        wm_init_gain=1.0,
        wm_init_std=0.1,
        modulation="tanh",
        modulation_source=LEARNED_SOURCE,
        modulation_channels=1,
        learned_modulation=None,
    ):
        super().__init__(n_in, n_out, e_max, eta_init)
        self._init_modulation(
            n_out, wm_init_gain, wm_init_std, modulation, modulation_source, modulation_channels, learned_modulation
        )

    def hebbian_terms(self, r_pre, r_post, state, *modulator):
        return HebbianTerms(self.modulation(r_post, *modulator) * r_post, r_pre, True)


@register_rule("ndp-bcm")
class NDPBCMRule(_ModulatedMixin, _BCMRule):
    r"""Neuromodulated BCM (paper eqs. 13–16), :func:`ndp_bcm_update`. Learned: :math:`\eta, \eta_\phi, \psi, W_m`
    (``G, b`` for an external signal).

    Parameters as :class:`_BCMRule` and :class:`NDPOjaRule`.
    """

    def __init__(
        self,
        n_in,
        n_out,
        e_max=1.0,
        eta_init=0.05,
        eta_phi_init=0.05,
        wm_init_gain=1.0,
        wm_init_std=0.1,
        modulation="tanh",
        modulation_source=LEARNED_SOURCE,
        modulation_channels=1,
        learned_modulation=None,
    ):
        super().__init__(n_in, n_out, e_max, eta_init, eta_phi_init)
        self._init_modulation(
            n_out, wm_init_gain, wm_init_std, modulation, modulation_source, modulation_channels, learned_modulation
        )

    def hebbian_terms(self, r_pre, r_post, state, *modulator):
        r_beta, phi = self.presynaptic(r_pre, state)
        return HebbianTerms(self.modulation(r_post, *modulator) * r_post, r_beta, False, (phi,))


_COMPILED_FORMS = {
    DPLinearRule: (False, False),
    DPOjaRule: (True, False),
    DPBCMRule: (False, True),
    NDPOjaRule: (True, False),
    NDPBCMRule: (False, True),
}


def builtin_form(rule: PlasticityRule) -> Optional[RuleForm]:
    """A built-in rule's terms as a :class:`~sb3_spikeplastic.snn._fast.interval.RuleForm` (its Oja and BCM forms and
    its modulation); ``None`` for any other rule, subclasses of the built-in ones included (they may change the
    terms)."""
    flags = _COMPILED_FORMS.get(type(rule))
    if flags is None:
        return None
    modulation = 1 + MODULATION_FORMS.index(rule.modulation_form) if rule.modulated else 0
    return RuleForm(*flags, modulation)


def compiled_form(rule: PlasticityRule) -> Optional[RuleForm]:
    """How the compiled layer op (``_fast/srm_interval.cpp``) evaluates a built-in rule's terms, op for op as
    :meth:`PlasticityRule.hebbian_terms` (:func:`builtin_form`); ``None`` for the rules that then run
    :meth:`PlasticityRule.step` as written: any other rule, and those that take an external modulator (the op forms
    :math:`M` from :math:`W_m r_{post}` only)."""
    return None if rule.takes_modulator else builtin_form(rule)
