"""The rollout buffer of recurrent spiking plastic policies: SB3's ``RolloutBuffer`` plus one network-state
snapshot per truncated-BPTT chunk and the action masks of the rollout, sampled as minibatches of whole chunks
(after sb3-contrib's ``RecurrentRolloutBuffer``, which stores a state per step instead)."""

from __future__ import annotations

from typing import Generator, NamedTuple, Optional

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from torch import Tensor

from ..snn.network import NetworkState, map_tensors


def check_chunking(bptt_steps: int, n_steps: int, batch_size: Optional[int] = None) -> None:
    """``ValueError`` unless ``bptt_steps`` >= 1 divides the rollout length and the minibatch (in transitions)."""
    if bptt_steps < 1:
        raise ValueError(f"bptt_steps must be >= 1, got {bptt_steps}")
    if n_steps % bptt_steps:
        raise ValueError(f"n_steps={n_steps} must be a multiple of bptt_steps={bptt_steps}")
    if batch_size is not None and batch_size % bptt_steps:
        raise ValueError(f"batch_size={batch_size} (transitions) must be a multiple of bptt_steps={bptt_steps}")


class ChunkSamples(NamedTuple):
    """A minibatch of whole chunks, time-major ``(L, n_chunks, ...)``, and the chunks' start states."""

    observations: Tensor
    actions: Tensor
    old_values: Tensor
    old_log_prob: Tensor
    advantages: Tensor
    returns: Tensor
    episode_starts: Tensor
    states: NetworkState
    action_masks: Optional[Tensor] = None

    @property
    def n_chunks(self) -> int:
        return self.observations.shape[1]

    def split(self, chunks: int) -> list["ChunkSamples"]:
        """The minibatch as consecutive parts of ``chunks`` chunks each (the last may be smaller)."""
        parts = []
        for start in range(0, self.n_chunks, chunks):
            part = slice(start, start + chunks)
            sequences = [
                x[:, part]
                for x in (
                    self.observations,
                    self.actions,
                    self.old_values,
                    self.old_log_prob,
                    self.advantages,
                    self.returns,
                    self.episode_starts,
                )
            ]
            parts.append(
                ChunkSamples(
                    *sequences,
                    self.states.select(part),
                    None if self.action_masks is None else self.action_masks[:, part],
                )
            )
        return parts


class ChunkRolloutBuffer(RolloutBuffer):
    """SB3's rollout buffer plus one network-state snapshot per ``chunk_len`` steps and environment, and (for
    ``Discrete`` actions) the action masks the rollout used.

    :param chunk_len: steps per chunk (``bptt_steps``); must divide ``buffer_size``.
    Other parameters as :class:`~stable_baselines3.common.buffers.RolloutBuffer`.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space,
        action_space,
        device="auto",
        gae_lambda=1.0,
        gamma=0.99,
        n_envs=1,
        chunk_len: int = 32,
    ):
        check_chunking(chunk_len, buffer_size)
        self.chunk_len = chunk_len
        self.n_actions = int(action_space.n) if isinstance(action_space, spaces.Discrete) else 0
        super().__init__(buffer_size, observation_space, action_space, device, gae_lambda, gamma, n_envs)

    def reset(self) -> None:
        super().reset()
        self.snapshots: list[NetworkState] = []
        self.action_masks = np.ones((self.buffer_size, self.n_envs, self.n_actions), dtype=bool)
        self.masked = False

    def add(self, *args, action_masks: Optional[np.ndarray] = None, **kwargs) -> None:
        """SB3's ``add``, plus the step's action masks ``(n_envs, n_actions)`` (``None``: every action open)."""
        if action_masks is not None:
            self.action_masks[self.pos] = action_masks
            self.masked = True
        super().add(*args, **kwargs)

    def add_snapshot(self, state: NetworkState) -> None:
        """Store the state entering step ``self.pos`` (must be a chunk start)."""
        if self.pos != len(self.snapshots) * self.chunk_len:
            raise RuntimeError(f"snapshot at step {self.pos} is not at the start of chunk {len(self.snapshots)}")
        self.snapshots.append(state.detach())

    def snapshot_nbytes(self) -> int:
        return sum(s.nbytes() for s in self.snapshots)

    def get_chunks(self, chunks_per_batch: int) -> Generator[ChunkSamples, None, None]:
        """Shuffled minibatches of ``chunks_per_batch`` whole chunks."""
        if not self.full:
            raise RuntimeError("the rollout buffer is not full")
        n_chunks = self.buffer_size // self.chunk_len
        total = n_chunks * self.n_envs
        # Snapshots stacked to (n_chunks, n_envs, ...) then flattened to chunk index c * n_envs + e.
        states = map_tensors(lambda x: x.flatten(0, 1), NetworkState.stack(self.snapshots))
        offsets = np.arange(self.chunk_len)[:, None]
        order = np.random.permutation(total)
        for start in range(0, total, chunks_per_batch):
            idx = order[start : start + chunks_per_batch]
            times = (idx // self.n_envs)[None, :] * self.chunk_len + offsets  # (L, n)
            envs = np.broadcast_to(idx % self.n_envs, times.shape)

            def take(arr: np.ndarray) -> Tensor:
                return self.to_torch(arr[times, envs])

            yield ChunkSamples(
                take(self.observations),
                take(self.actions),
                take(self.values),
                take(self.log_probs),
                take(self.advantages),
                take(self.returns),
                take(self.episode_starts),
                states.select(torch.as_tensor(idx, device=states.noise_key.device)),
                take(self.action_masks).bool() if self.masked else None,
            )
