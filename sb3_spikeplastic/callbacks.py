"""Training callbacks of ``sb3-spikeplastic train``: atomic checkpoints with pruning, the best model written
atomically, a progress bar that counts wall time and a one-line summary every tenth of the run."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from stable_baselines3.common.callbacks import BaseCallback

from .run_folder import checkpoint_statistics, save_model, save_vecnormalize


class AtomicCheckpoint(BaseCallback):
    """Every ``save_freq`` calls, ``rl_model_<steps>_steps.zip`` and its ``VecNormalize`` statistics, each written
    atomically; only the latest ``keep`` checkpoints stay.

    :param save_freq: calls (rollout steps of the vectorised env) between checkpoints
    :param save_dir: folder of the checkpoints
    :param keep: checkpoints kept, the oldest removed first (0: all)
    """

    def __init__(self, save_freq: int, save_dir: Path, keep: int = 0):
        super().__init__()
        self.save_freq, self.save_dir, self.keep = save_freq, Path(save_dir), keep
        self.saved: list[Path] = []

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            path = self.save_dir / f"rl_model_{self.num_timesteps}_steps.zip"
            venv = self.model.get_vec_normalize_env()
            if venv is not None:  # statistics first: a checkpoint's zip never exists without them
                save_vecnormalize(venv, checkpoint_statistics(path))
            self.saved.append(save_model(self.model, path))
            while self.keep and len(self.saved) > self.keep:
                old = self.saved.pop(0)
                old.unlink(missing_ok=True)
                checkpoint_statistics(old).unlink(missing_ok=True)
        return True


class SaveBest(BaseCallback):
    """Called by ``EvalCallback`` on a new best mean reward: ``best_model.zip``, written atomically.

    :param path: where the best model goes
    """

    def __init__(self, path: Path):
        super().__init__()
        self.path = Path(path)

    def _on_step(self) -> bool:
        save_model(self.model, self.path)
        return True


class WallClockProgress(BaseCallback):
    """A progress bar over environment steps whose rate is steps per second of wall time, updates included (SB3's
    bar moves only during rollouts, so its rate is the rollout's alone); it stops at the run's total."""

    def _on_training_start(self) -> None:
        from tqdm.auto import tqdm

        self.remaining = self.locals["total_timesteps"] - self.model.num_timesteps
        self.bar = tqdm(total=self.remaining, unit="step", unit_scale=True, smoothing=0, dynamic_ncols=True)

    def _on_step(self) -> bool:
        # The last rollout may run past the total (whole rollouts of n_envs x n_steps); the bar does not.
        self.bar.update(min(self.training_env.num_envs, self.remaining - self.bar.n))
        return True

    def _on_training_end(self) -> None:
        self.bar.close()


class TrainingSummary(BaseCallback):
    """One line at the first rollout end past every ``every`` environment steps, and at the end: the mean return
    and success rate of the last 100 episodes (SB3's episode buffers: the Monitor's raw returns) and the
    environment steps per second of wall time since the start, updates included.

    :param every: environment steps between lines
    """

    def __init__(self, every: int):
        super().__init__()
        self.every = max(int(every), 1)

    def _on_training_start(self) -> None:
        self.start_steps, self.start_time = self.model.num_timesteps, time.perf_counter()
        self.next_line, self.written_at = self.start_steps + self.every, None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        if self.model.num_timesteps >= self.next_line:
            self._write()
            while self.next_line <= self.model.num_timesteps:
                self.next_line += self.every

    def _on_training_end(self) -> None:
        if self.written_at != self.model.num_timesteps:
            self._write()

    def summary(self) -> str:
        steps = self.model.num_timesteps
        parts = [f"{steps:>11,} steps"]
        if self.model.ep_info_buffer:
            parts.append(f"return {np.mean([info['r'] for info in self.model.ep_info_buffer]):.4g}")
        if self.model.ep_success_buffer:
            parts.append(f"success {np.mean(self.model.ep_success_buffer):.2f}")
        rate = (steps - self.start_steps) / max(time.perf_counter() - self.start_time, 1e-9)
        parts.append(f"{rate:,.0f} steps/s")
        return " | ".join(parts)

    def _write(self) -> None:
        from tqdm.auto import tqdm

        tqdm.write(self.summary())  # above a progress bar, if one is shown
        self.written_at = self.model.num_timesteps
