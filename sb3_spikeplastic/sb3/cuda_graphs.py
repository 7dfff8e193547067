"""CUDA-graph replay of the rollout step and of the training pass (a minibatch's forward and backward).

On a GPU the spiking network is bound by the host, not the device: a chunk of 32 environment steps issues ~10k
small kernels forward and backward, each costing ~10-25 us of Python and launch overhead against ~1-3 us of GPU
work (measured on an H100: 94 ms of host time for 9.5 ms of kernels per 8 steps). CUDA graphs
(:func:`torch.cuda.make_graphed_callables` for training, :class:`torch.cuda.CUDAGraph` for the rollout step)
record the kernels once and replay them, so the per-step cost falls to the GPU's.

Replays run the very kernels the eager pass runs, on the same inputs, so values and gradients are the same as
eager PyTorch on the GPU (tested); only the rollout's action sampling draws other random numbers (the graph's
generator offsets), from the same distribution. Capture needs code that never waits for the device: the
network's resets multiply unconditionally (``sync_free``), observations are checked before the graph, and
``torch.distributions``' argument validation (a host-side check) is off while capturing.

If a capture fails anyway, the pass runs eagerly from then on, and the device's random generator is put back as it
was before the capture (PyTorch would otherwise leave it marked as capturing, and every later random op in the
process would raise "Offset increment outside graph capture").
"""

from __future__ import annotations

import contextlib
import gc
import warnings
from typing import Callable, Iterator, Optional

import torch
from torch import Tensor, nn

from ..snn.network import NetworkOutput, NetworkState, map_tensors, tensor_leaves


def flatten_state(state: NetworkState) -> tuple[list[Tensor], Callable[[list[Tensor]], NetworkState]]:
    """The state's tensors in a fixed order and a function that rebuilds a state of that structure from them."""

    def rebuild(tensors: list[Tensor]) -> NetworkState:
        replacements = iter(tensors)
        return map_tensors(lambda _: next(replacements), state)

    return tensor_leaves(state), rebuild


def _release_last_distribution(policy: nn.Module) -> None:
    """Drop the distribution SB3's ``action_dist`` keeps from its last use: after an eager training pass it holds
    that pass's autograd graph alive, which can make the next capture fail."""
    if hasattr(policy.action_dist, "distribution"):
        policy.action_dist.distribution = None


@contextlib.contextmanager
def _capturable(policy: nn.Module) -> Iterator[None]:
    """Around a capture: no stale autograd graph from the policy's last distribution, no argument validation in
    ``torch.distributions`` (it asks the device whether the arguments are valid: a synchronisation), and no
    garbage collection (collecting another model's CUDA graphs destroys them, which invalidates a capture under
    way: seen with several models in one process)."""
    _release_last_distribution(policy)
    validate = torch.distributions.Distribution._validate_args
    torch.distributions.Distribution.set_default_validate_args(False)
    collecting = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()
        torch.distributions.Distribution.set_default_validate_args(validate)


@contextlib.contextmanager
def _generator_released_on_failure(device: torch.device) -> Iterator[None]:
    """If the capture inside fails, take ``device``'s default CUDA generator out of capture mode.

    A capture marks the generator's state as capturing and a successful end unmarks it; a capture that is
    invalidated (an op that cannot be captured) raises when it ends, before the unmarking, and every later random
    op on the device, a replay of an earlier graph included, would raise "Offset increment outside graph
    capture". A one-op capture that ends well unmarks the same state (keeping its seed and offset).
    """
    try:
        yield
    except BaseException:
        if device.type == "cuda":
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                torch.rand(1, device=device)
        raise


def _capture_failed(exc: Exception, what: str) -> str:
    """Warn once that a capture failed and ``what`` runs eagerly; returns the error's one-line description."""
    error = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
    warnings.warn(
        f"sb3_spikeplastic: CUDA-graph capture failed ({error}); {what} runs eagerly, with the same results, slower.",
        RuntimeWarning,
        stacklevel=3,
    )
    return error


class _SequenceEvaluation(nn.Module):
    """``policy._evaluate_sequence`` on flat tensor arguments, as a module (so that its parameters are graphed)."""

    def __init__(self, policy: nn.Module, rebuild, n_leaves: int, masked: bool):
        super().__init__()
        self.policy, self.rebuild, self.n_leaves, self.masked = policy, rebuild, n_leaves, masked

    def forward(self, obs: Tensor, actions: Tensor, starts: Tensor, *rest: Tensor):
        state = self.rebuild(list(rest[: self.n_leaves]))
        masks = rest[self.n_leaves] if self.masked else None
        values, log_prob, entropy, _ = self.policy._evaluate_sequence(
            obs, actions, starts, state, masks, sync_free=True
        )
        return values, log_prob, entropy


class GraphedSequenceEvaluation:
    """Drop-in for ``policy.evaluate_actions_sequence`` in training (returns ``values, log_prob, entropy``) that
    replays CUDA graphs, captured once per input signature (shapes, dtypes, masks or not).

    The outputs are the graph's static buffers, overwritten by the next replay: use them (loss, ``backward``)
    before the next call, as the PPO update does. If a capture fails, one :class:`RuntimeWarning` is issued
    and every later call runs eagerly (the same values, slower).

    :param policy: the :class:`~sb3_spikeplastic.sb3.policy.SpikePlasticPolicy` (on a CUDA device).
    """

    def __init__(self, policy: nn.Module):
        self.policy = policy
        self._graphed: dict[tuple, Callable] = {}
        self.error: Optional[str] = None

    def __call__(
        self,
        obs: Tensor,
        actions: Tensor,
        episode_starts: Tensor,
        state: NetworkState,
        action_masks: Optional[Tensor] = None,
    ):
        if self.error is not None:
            return self.policy.evaluate_actions_sequence(obs, actions, episode_starts, state, action_masks)[:3]
        # The observation check waits for the device, so it runs here, before the graph.
        obs = self.policy._preprocess(obs.flatten(0, 1)).view(obs.shape)
        leaves, rebuild = flatten_state(state)
        args = (obs, actions, episode_starts, *leaves, *(() if action_masks is None else (action_masks,)))
        key = tuple((a.shape, a.dtype) for a in args)
        graphed = self._graphed.get(key)
        if graphed is None:
            try:
                graphed = self._capture(args, rebuild, len(leaves), action_masks is not None)
            except Exception as exc:  # an op that cannot be captured, out of memory, ...
                self.error = _capture_failed(exc, "training")
                return self.policy.evaluate_actions_sequence(obs, actions, episode_starts, state, action_masks)[:3]
            self._graphed[key] = graphed
        return graphed(*args)

    def _capture(self, args: tuple, rebuild, n_leaves: int, masked: bool) -> Callable:
        module = _SequenceEvaluation(self.policy, rebuild, n_leaves, masked)
        with _capturable(self.policy), _generator_released_on_failure(args[0].device):
            return torch.cuda.make_graphed_callables(module, tuple(a.detach() for a in args), allow_unused_input=True)


class GraphedRolloutStep:
    """Drop-in for ``policy.step`` in rollouts (same arguments and returns) that replays a CUDA graph, captured
    once per input signature (batch, masks or not, ``deterministic``). Outputs are copies, safe to keep.

    If a capture fails, one :class:`RuntimeWarning` is issued and every later call runs eagerly.

    :param policy: the :class:`~sb3_spikeplastic.sb3.policy.SpikePlasticPolicy` (on a CUDA device).
    """

    def __init__(self, policy: nn.Module):
        self.policy = policy
        self._graphs: dict[tuple, tuple] = {}
        self.error: Optional[str] = None

    @torch.no_grad()
    def __call__(
        self,
        obs: Tensor,
        state: NetworkState,
        episode_start: Tensor,
        deterministic: bool = False,
        action_masks: Optional[Tensor] = None,
    ):
        if self.error is not None:
            return self.policy.step(obs, state, episode_start, deterministic, action_masks)
        obs = self.policy._preprocess(obs)  # waits for the device: outside the graph
        leaves, rebuild = flatten_state(state)
        inputs = [
            obs,
            episode_start.to(obs.device, torch.float32),
            *leaves,
            *(() if action_masks is None else (action_masks,)),
        ]
        key = (tuple((t.shape, t.dtype) for t in inputs), bool(deterministic))
        entry = self._graphs.get(key)
        if entry is None:
            try:
                entry = self._capture(inputs, rebuild, len(leaves), action_masks is not None, bool(deterministic))
            except Exception as exc:
                self.error = _capture_failed(exc, "the rollout")
                return self.policy.step(obs, state, episode_start, deterministic, action_masks)
            self._graphs[key] = entry
        graph, static_inputs, static_outputs = entry
        for target, value in zip(static_inputs, inputs):
            target.copy_(value)
        graph.replay()
        return map_tensors(torch.clone, static_outputs)

    def _run(self, static_inputs: list[Tensor], rebuild, n_leaves: int, masked: bool, deterministic: bool):
        obs, starts, *rest = static_inputs
        masks = rest[n_leaves] if masked else None
        actions, values, log_prob, new_state, out = self.policy._step(
            obs, rebuild(rest[:n_leaves]), starts, deterministic, masks, sync_free=True
        )
        # Only what rollouts use: the record is None outside monitoring.
        return actions, values, log_prob, new_state, NetworkOutput(out.action, out.rates, None, out.input_rate)

    def _capture(self, inputs: list[Tensor], rebuild, n_leaves: int, masked: bool, deterministic: bool) -> tuple:
        static_inputs = [t.clone() for t in inputs]
        with _capturable(self.policy), _generator_released_on_failure(inputs[0].device):
            # Warm-up on a side stream (lazy allocations, cached filter matrices, cuBLAS handles), as PyTorch
            # requires before capturing.
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(3):
                    self._run(static_inputs, rebuild, n_leaves, masked, deterministic)
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_outputs = self._run(static_inputs, rebuild, n_leaves, masked, deterministic)
        return graph, static_inputs, static_outputs
