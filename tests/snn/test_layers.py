"""The CPU layer interval, with a built-in rule's trace update, as one compiled op each way
(``fused_interval._FusedInterval``, ``_fast/srm_interval.cpp``) against the eager layer: the same spikes, the
membrane and states to float rounding (the op filters by the alpha filter's recurrence, ``_fast/alpha_filter.cpp``),
and the gradients of the eager graph."""

import pytest
import torch

from sb3_spikeplastic.snn import _fast, layers
from sb3_spikeplastic.snn._fast import interval
from sb3_spikeplastic.snn.fused_interval import _FusedInterval, interval_inputs
from sb3_spikeplastic.snn.layers import PlasticSRMLayer
from sb3_spikeplastic.snn.network import tensor_leaves
from sb3_spikeplastic.snn.neurons import SRMParameters, alpha_filter_operator, slayer_surrogate
from sb3_spikeplastic.snn.plasticity import DPOjaRule, compiled_form, get_rule_class

pytestmark = pytest.mark.skipif(_fast.load_ops() is None, reason="compiled ops unavailable")


class ShiftedOja(DPOjaRule):
    """A user's rule built on a built-in one with other terms: it must run its own ``hebbian_terms``."""

    def hebbian_terms(self, r_pre, r_post, state):
        terms = super().hebbian_terms(r_pre, r_post, state)
        return terms._replace(post=terms.post + 0.5)


def make_layer(rule: str, n_in: int, n_out: int, dtype=torch.float64) -> PlasticSRMLayer:
    torch.manual_seed(0)
    name, _, form = rule.partition("+")
    cls = ShiftedOja if name == "shifted-oja" else get_rule_class(name)
    kwargs = {"modulation": form or "linear"} if name.startswith("ndp-") else {}  # "ndp-oja": the paper's form
    layer_rule = cls(n_in, n_out, **kwargs) if cls.has_trace else cls(n_in, n_out)
    if hasattr(layer_rule, "psi"):  # a nonzero BCM offset, so that its gradient path is exercised
        layer_rule.psi.data.normal_(0.0, 0.1)
    # Large weights and alpha: many spikes, and the trace changes the efficacy noticeably.
    return PlasticSRMLayer(n_in, n_out, layer_rule, SRMParameters(tau_s=2.0), w_init_std=3.0, alpha_init_std=5.0).to(
        dtype
    )


def run_intervals(
    layer, fused: bool, monkeypatch, dtype=torch.float64, batch=4, length=6, intervals=3, rates_only=False, defer=False
):
    """Chain ``intervals`` intervals from the initial state (``defer``: with the trace updates deferred, the last one
    applied at the end); return every output, the final state and the
    gradients of a loss that reads the spikes, the carried PSP state and the trace, or (``rates_only``) only the
    output rates, as the decoder reads the output layer's: then autograd passes no gradient for the spikes, the
    input rates and the final state."""
    with monkeypatch.context() as patch:
        if not fused:
            patch.setattr(_FusedInterval, "applies", staticmethod(lambda *args: False))
        generator = torch.Generator().manual_seed(1)
        # Inputs with a gradient, as a hidden layer's are (they come from the previous layer's spikes).
        spikes_in = (torch.rand(intervals, batch, length, layer.n_in, generator=generator) < 0.4).to(dtype)
        spikes_in.requires_grad_()
        weights = torch.randn(intervals, batch, length, layer.n_out, generator=generator, dtype=dtype)
        state = layer.initial_state(batch, dtype)
        outputs, loss = [], 0.0
        for k in range(intervals):
            out, state = layer(spikes_in[k] * 1.0, state, defer_update=defer)
            outputs.append(out)
            if rates_only:
                loss = loss + (out.rate * weights[k, :, 0]).sum()
            else:
                loss = loss + (out.spikes * weights[k]).sum()
        if layer.plastic:
            state = state._replace(plastic=layer.rule.apply_pending(state.plastic))
        if not rates_only:
            loss = loss + (0.3 * state.psp.h1 + 0.7 * state.psp.h2).sum()
        if layer.plastic and not rates_only:
            loss = loss + 5.0 * state.plastic.trace.sum() + sum(3.0 * x.sum() for x in state.plastic.extra)
        params = list(layer.parameters())
        grads = torch.autograd.grad(loss, params + [spikes_in], allow_unused=True)
    return outputs, state, grads


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("length", [1, 2, 7, 50])
@pytest.mark.parametrize("states", [True, False], ids=["states", "no-states"])
def test_alpha_filter_recurrence_equals_the_operator(dtype, length, states):
    """The recurrence (``alpha_filter_rows``) and its adjoint against the operator's product ``M [z; a; b]`` and
    ``M^T [dpsp; d_end]``, computed in float64 from the same inputs; rows as a strided view (a slice of a larger block
    of rows), widths with a tail after the kernel's 64-column blocks, constants read off the operator as the op
    reads them."""
    ops = _fast.load_ops()
    generator = torch.Generator().manual_seed(length)
    op = alpha_filter_operator(length, 5.0, 1.0, dtype)
    d = float(op[length, length - 2] if length >= 2 else op[length, length])
    g = float(op[0, length + 1])
    batch, width = 3, 130
    block = torch.randn(batch, length + 3, width, generator=generator, dtype=torch.float64)
    z = block[:, 1 : length + 1].to(dtype)  # a view: its batch stride is not length * width
    a, b = (
        torch.randn(2, batch, width, generator=generator, dtype=torch.float64)
        if states
        else torch.zeros(2, batch, width, dtype=torch.float64)
    )
    psp, end = ops.alpha_filter_rows(z, a.to(dtype) if states else None, b.to(dtype) if states else None, d, g)
    op64 = op.double()
    expected = op64 @ torch.cat([z.double(), a.unsqueeze(1), b.unsqueeze(1)], 1)
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-5, atol=2e-5)
    torch.testing.assert_close(psp.double(), expected[:, :length], **tol)
    torch.testing.assert_close(end.double(), expected[:, length:], **tol)
    assert float(torch.cat([psp, end], 1).abs().max()) > 0.5  # (with L = 1 and no state only the end is nonzero)

    d_psp = torch.randn(batch, length, width, generator=generator, dtype=torch.float64)
    d_end = torch.randn(batch, 2, width, generator=generator, dtype=torch.float64)
    dz, d_state = ops.alpha_filter_rows_adjoint(d_psp.to(dtype), d_end[:, 0].to(dtype), d_end[:, 1].to(dtype), d, g)
    expected = op64.t() @ torch.cat([d_psp, d_end], 1)
    torch.testing.assert_close(dz.double(), expected[:, :length], **tol)
    torch.testing.assert_close(d_state.double(), expected[:, length:], **tol)
    dz, d_state = ops.alpha_filter_rows_adjoint(d_psp.to(dtype), None, None, d, g)
    expected = op64.t() @ torch.cat([d_psp, torch.zeros_like(d_end)], 1)
    torch.testing.assert_close(torch.cat([dz, d_state], 1).double(), expected, **tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("length", [1, 7, 50])
def test_alpha_filter_end_state_and_mean_in_one_pass(dtype, length):
    """``alpha_filter_end_and_mean`` (a layer that multiplies its spikes before filtering: its next PSP state and
    ``r_pre``): the end state of the full recurrence bit for bit, and ``z.mean(1)``, exactly for binary spikes (their
    sums are exact) and to rounding otherwise; rows as a strided view, a column tail after 64-column blocks."""
    ops = _fast.load_ops()
    generator = torch.Generator().manual_seed(100 + length)
    op = alpha_filter_operator(length, 5.0, 1.0, dtype)
    d = float(op[length, length - 2] if length >= 2 else op[length, length])
    g = float(op[0, length + 1])
    batch, width = 3, 130
    a, b = torch.randn(2, batch, width, generator=generator, dtype=dtype)
    for binary in (True, False):
        block = torch.rand(batch, length + 3, width, generator=generator, dtype=dtype)
        z = (block < 0.1).to(dtype)[:, 1 : length + 1] if binary else block[:, 1 : length + 1]
        end, mean = ops.alpha_filter_end_and_mean(z, a, b, d)
        assert torch.equal(end, ops.alpha_filter_rows(z, a, b, d, g)[1])
        if binary:
            assert torch.equal(mean, z.mean(1))
        else:
            torch.testing.assert_close(mean, z.mean(1), rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=0)
    end, _ = ops.alpha_filter_end_and_mean(z, None, None, d)
    assert torch.equal(end, ops.alpha_filter_rows(z, None, None, d, g)[1])


@pytest.mark.parametrize(
    "rule",
    ["dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-oja+tanh", "ndp-bcm", "ndp-bcm+tanh", "static", "shifted-oja"],
)
@pytest.mark.parametrize("n_in, n_out", [(30, 20), (20, 30)], ids=["product-first", "filter-first"])
@pytest.mark.parametrize("carry", [False, True], ids=["rows", "carried-state"])
def test_fused_interval_equals_eager_layer(rule, n_in, n_out, carry, monkeypatch):
    """The fused interval against the eager layer; ``carried-state``: with the PSP state multiplied beside the spikes
    (``PlasticSRMLayer.carries_state``, here for small layers too), in both."""
    monkeypatch.setattr(layers, "CARRY_MIN_ROW_VALUES", 0 if carry else layers.CARRY_MIN_ROW_VALUES)
    layer = make_layer(rule, n_in, n_out)
    assert layer.carries_state(6) == (carry and n_in > n_out and rule != "static")
    fused_out, fused_state, fused_grads = run_intervals(layer, True, monkeypatch)
    eager_out, eager_state, eager_grads = run_intervals(layer, False, monkeypatch)
    assert type(fused_out[0].spikes.grad_fn).__name__ == "_FusedIntervalBackward"
    # The op updates a built-in rule's trace; other rules update it themselves, after the op.
    fused_update = type(fused_state.plastic.trace.grad_fn).__name__ == "_FusedIntervalBackward"
    assert fused_update == (rule not in ("static", "shifted-oja"))
    assert type(eager_out[0].spikes.grad_fn).__name__ != "_FusedIntervalBackward"
    assert sum(float(o.spikes.detach().sum()) for o in eager_out) > 0

    # The op filters by the alpha filter's recurrence, the eager layer by its operator: equal to float rounding, and
    # the same spikes (no membrane lies within rounding of the threshold here).
    def close(a, b):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)

    for a, b in zip(fused_out, eager_out):
        assert torch.equal(a.spikes, b.spikes) and torch.equal(a.rate, b.rate)
        assert torch.equal(a.input_rate, b.input_rate)
        close(a.membrane, b.membrane)
    for a, b in zip(fused_state.psp + fused_state.refractory, eager_state.psp + eager_state.refractory):
        close(a, b)
    for a, b in zip(fused_state.plastic[:2], eager_state.plastic[:2]):  # the trace, and the BCM threshold
        if isinstance(a, tuple):
            assert len(a) == len(b)
            for x, y in zip(a, b):
                close(x, y)
        else:
            close(a, b)
    for a, b in zip(fused_grads, eager_grads):
        assert (a is None) == (b is None)
        if a is not None:
            assert float(b.abs().max()) > 0
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("rule", ["dp-oja", "ndp-bcm+tanh", "static"])
@pytest.mark.parametrize("n_in, n_out", [(30, 20), (20, 30)], ids=["product-first", "filter-first"])
def test_gradients_when_the_loss_reads_only_the_rates(rule, n_in, n_out, monkeypatch):
    """The outputs the loss does not reach get no gradient tensor (the op reads them as zero): the gradients are
    still the eager graph's."""
    layer = make_layer(rule, n_in, n_out)
    _, _, fused = run_intervals(layer, True, monkeypatch, rates_only=True)
    _, _, eager = run_intervals(layer, False, monkeypatch, rates_only=True)
    for a, b in zip(fused, eager):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert float(fused[0].abs().max()) > 0


def test_first_layer_inputs_without_gradient(monkeypatch):
    """The input layer's spikes are samples: no input gradient is computed, the parameters' still are."""
    layer = make_layer("dp-oja", 30, 20)
    state = layer.initial_state(3, torch.float64)
    spikes_in = (torch.rand(3, 5, 30) < 0.4).double()
    out, state = layer(spikes_in, state)
    # Only the spikes, rates and the trace carry a gradient: the membrane and refractory state never do, the PSP
    # state not without one of the input spikes.
    assert out.spikes.requires_grad and state.plastic.trace.requires_grad
    assert not any(x.requires_grad for x in (out.membrane, *state.refractory, *state.psp, out.input_rate))
    loss = out.spikes.sum() + state.plastic.trace.sum()
    fused = torch.autograd.grad(loss, list(layer.parameters()))
    with monkeypatch.context() as patch:
        patch.setattr(_FusedInterval, "applies", staticmethod(lambda *args: False))
        state = layer.initial_state(3, torch.float64)
        out, state = layer(spikes_in, state)
        eager = torch.autograd.grad(out.spikes.sum() + state.plastic.trace.sum(), list(layer.parameters()))
    for a, b in zip(fused, eager):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_rollout_path_matches_training_path():
    """Without autograd the layer runs the same op (no node): identical spikes and states."""
    layer = make_layer("dp-oja", 20, 30, torch.float32)
    spikes_in = (torch.rand(4, 6, 20) < 0.4).float()
    with torch.no_grad():
        out_a, state_a = layer(spikes_in, layer.initial_state(4))
    out_b, state_b = layer(spikes_in, layer.initial_state(4))
    assert out_a.spikes.grad_fn is None and out_b.spikes.grad_fn is not None
    assert torch.equal(out_a.spikes, out_b.spikes) and torch.equal(out_a.membrane, out_b.membrane)
    assert torch.equal(state_a.plastic.trace, state_b.plastic.trace.detach())


def test_float32_gradients_agree(monkeypatch):
    """In float32 the fused gradients agree with the eager float32 ones to float rounding."""
    layer = make_layer("ndp-oja", 30, 20, torch.float32)
    _, _, fused = run_intervals(layer, True, monkeypatch, dtype=torch.float32)
    _, _, eager = run_intervals(layer, False, monkeypatch, dtype=torch.float32)
    for a, b in zip(fused, eager):
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


def test_float32_surrogate_within_two_ulp_of_slayer_surrogate():
    """The op computes the surrogate in its spike loop with an exponential of its own (vectorised): within 2 ulp of
    ``neurons.slayer_surrogate`` from the threshold to membranes so far from it that ``exp`` underflows. The rates
    it counts in the same loop equal ``spikes.mean(1)``."""
    layer = make_layer("dp-oja", 20, 300, torch.float32)
    with torch.no_grad():
        layer.weight.mul_(100.0)  # membranes up to thousands of mV from the threshold
    spikes_in = (torch.rand(4, 50, 20, generator=torch.Generator().manual_seed(2)) < 0.4).float()
    parameters = layer.interval_parameters(50, torch.float32, spikes_in.device)
    form = compiled_form(layer.rule)
    with torch.no_grad():
        outputs, residuals = interval.forward(
            _fast.interval_ops(),
            interval_inputs(spikes_in, layer.initial_state(4), parameters, form),
            parameters.constants,
            form,
            need_surrogate=True,
        )
    membrane, surrogate = outputs.membrane, residuals.surrogate
    assert torch.equal(outputs.r_post, outputs.spikes.mean(1))  # counted in the same loop
    width = layer.neuron.tau_rho * layer.neuron.theta
    distance = (membrane - layer.neuron.theta).abs() / width
    assert distance.min() < 0.1 and distance.max() > 87.3  # near the threshold and past exp's float32 range
    reference = slayer_surrogate(membrane, layer.neuron)
    torch.testing.assert_close(surrogate, reference, rtol=2 * 2.0**-23, atol=2e-39)


def test_disabled_compilation_uses_the_eager_layer(monkeypatch):
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    layer = make_layer("dp-oja", 30, 20)
    out, _ = layer((torch.rand(2, 5, 30) < 0.4).double().requires_grad_(), layer.initial_state(2, torch.float64))
    assert type(out.spikes.grad_fn).__name__ != "_FusedIntervalBackward"


@pytest.mark.parametrize("rule", ["dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-oja+tanh", "ndp-bcm+tanh"])
@pytest.mark.parametrize("n_in, n_out", [(30, 20), (20, 30)], ids=["product-first", "filter-first"])
@pytest.mark.parametrize("rates_only", [False, True], ids=["all-outputs", "rates-only"])
@pytest.mark.parametrize("intervals, carry", [(3, False), (4, False), (4, True)], ids=["3", "4", "4-carried-state"])
def test_deferred_trace_update_equals_immediate(rule, n_in, n_out, rates_only, intervals, carry, monkeypatch):
    """Intervals that defer their trace update to the next interval's pass over ``E`` (the training sequences')
    give the same spikes, states and final trace bit for bit as intervals that update at their end, and the same
    gradients to float rounding, for every built-in rule and both product orders. Four intervals end with two
    updates pending (the second passed its input trace on unwritten), three with one."""
    monkeypatch.setattr(layers, "CARRY_MIN_ROW_VALUES", 0 if carry else layers.CARRY_MIN_ROW_VALUES)
    layer = make_layer(rule, n_in, n_out)
    deferred_out, deferred_state, deferred_grads = run_intervals(
        layer, True, monkeypatch, rates_only=rates_only, defer=True, intervals=intervals
    )
    out, state, grads = run_intervals(layer, True, monkeypatch, rates_only=rates_only, intervals=intervals)
    assert type(deferred_out[1].spikes.grad_fn).__name__ == "_DeferredIntervalBackward"
    assert deferred_state.plastic.pending is None
    for a, b in zip(deferred_out, out):
        assert torch.equal(a.spikes, b.spikes) and torch.equal(a.membrane, b.membrane) and torch.equal(a.rate, b.rate)
    for a, b in zip(tensor_leaves(deferred_state), tensor_leaves(state)):
        assert torch.equal(a, b)
    for a, b in zip(deferred_grads, grads):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_deferred_sequence_stores_every_other_trace():
    """In a training sequence every other interval passes its input trace on unwritten (its update and the one before
    stay pending), so that the graph keeps half of the traces; the next interval writes the trace with both
    applied."""
    layer = make_layer("ndp-oja", 30, 20)
    spikes_in = (torch.rand(5, 4, 6, 30, generator=torch.Generator().manual_seed(3)) < 0.4).double()
    state = layer.initial_state(4, torch.float64)
    storages, pending = [], []
    for k in range(5):
        _, state = layer(spikes_in[k], state, defer_update=True)
        storages.append(state.plastic.trace.untyped_storage().data_ptr())
        pending.append(len(state.plastic.pending))
    assert pending == [1, 2, 1, 2, 1]
    assert storages[1] == storages[0] and storages[3] == storages[2]
    assert len(set(storages)) == 3
