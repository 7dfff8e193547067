"""The compiled ops' named interfaces: the Python NamedTuples that mirror the C++ structs and the ops' schemas list
their fields in the same order (a reorder on one side fails here), and :func:`_fast.dispatch` is the one place that
picks the compiled op or the eager code."""

import pytest
import torch

from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn._fast import interval, kernels

pytestmark = pytest.mark.skipif(_fast.load_ops() is None, reason="compiled ops unavailable")


def schema(name: str):
    return getattr(_fast.load_ops(), name).default._schema


@pytest.mark.parametrize(
    "struct",
    [interval.IntervalInputs, interval.IntervalGradients, interval.IntervalOutputs, interval.IntervalResiduals],
    ids=lambda s: s.__name__,
)
def test_interval_structs_have_the_cpp_field_order(struct):
    assert _fast.load_ops().srm_interval_fields(struct.__name__) == list(struct._fields)


def test_interval_gradients_are_named_as_the_inputs():
    assert interval.IntervalGradients._fields == interval.IntervalInputs._fields


@pytest.mark.parametrize(
    "op, tensors, flags",
    [
        ("srm_interval_forward", ["inputs"], ["need_surrogate"]),
        ("srm_interval_deferred_forward", ["inputs"], ["need_surrogate", "write_trace"]),
        ("srm_interval_backward", ["grad_outputs", "residuals", "inputs"], ["need_rows"]),
        ("srm_interval_deferred_backward", ["grad_outputs", "residuals", "inputs"], ["need_rows", "write_trace"]),
    ],
)
def test_interval_op_arguments_in_the_order_the_python_side_flattens_them(op, tensors, flags):
    """``interval.forward`` / ``backward`` pass the tensor lists, then ``*constants, *form``, then the flags."""
    names = [argument.name for argument in schema(op).arguments]
    assert names == [*tensors, *interval.IntervalConstants._fields, *interval.RuleForm._fields, *flags]


@pytest.mark.parametrize(
    "op, outputs",
    [
        ("srm_loop", kernels.SpikeLoopOutputs),
        ("trace_step_forward", kernels.TraceStepOutputs),
        ("trace_step_backward", kernels.TraceStepGradients),
        ("plastic_linear_forward", kernels.ProductOutputs),
        ("plastic_linear_backward", kernels.ProductGradients),
    ],
)
def test_small_ops_return_what_their_named_tuples_name(op, outputs):
    assert [r.name for r in schema(op).returns] == list(outputs._fields)


@pytest.mark.parametrize(
    "op, gradients",
    [
        ("trace_step_forward", kernels.TraceStepGradients),
        ("plastic_linear_forward", kernels.ProductGradients),
    ],
)
def test_gradients_are_named_as_the_forward_operands(op, gradients):
    """The backward op's outputs are the gradients of the forward op's leading arguments (those that have one)."""
    names = [a.name for a in schema(op).arguments]
    assert names[: len(gradients._fields)] == list(gradients._fields)


def test_dispatch_runs_the_compiled_op_where_it_applies_else_the_eager_code(monkeypatch):
    calls = []
    kernel = _fast.Kernel("probe", lambda x: x.dim() == 1, lambda ops, x: calls.append("compiled") or x + 1)

    def eager(x):
        calls.append("eager")
        return x + 1

    assert torch.equal(_fast.dispatch(kernel, eager, torch.zeros(3)), torch.ones(3))
    assert torch.equal(_fast.dispatch(kernel, eager, torch.zeros(2, 3)), torch.ones(2, 3))
    monkeypatch.setenv(_fast.NO_COMPILE_ENV, "1")
    _fast.dispatch(kernel, eager, torch.zeros(3))
    assert calls == ["compiled", "eager", "eager"]
    assert _fast.compiled(kernel, torch.zeros(3)) is None
