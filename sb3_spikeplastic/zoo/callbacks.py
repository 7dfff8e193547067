"""Training callbacks of ``sb3-spikeplastic train``: atomic checkpoints with pruning, the best model written
atomically, a progress bar that counts wall time, and the terminal's lines: a summary every tenth of the run, one
per evaluation and one saying when ``-n`` is rounded up to whole rollouts."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional, Union

import gymnasium
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.logger import Figure

from .recording import record_episode
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

    def save(self) -> Path:
        """The model now as ``rl_model_<steps>_steps.zip`` and its statistics, each written atomically."""
        path = self.save_dir / f"rl_model_{self.num_timesteps}_steps.zip"
        venv = self.model.get_vec_normalize_env()
        if venv is not None:  # statistics first: a checkpoint's zip never exists without them
            save_vecnormalize(venv, checkpoint_statistics(path))
        return save_model(self.model, path)

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            self.saved.append(self.save())
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


def rollout_size(model) -> int:
    """Environment steps of one rollout: ``n_steps x n_envs`` (SB3's on-policy algorithms train on whole ones)."""
    return getattr(model, "n_steps", 1) * model.n_envs


def steps_to_train(model, total_timesteps: int) -> int:
    """The environment steps that ``model.learn`` takes to reach ``total_timesteps`` from ``model.num_timesteps``:
    whole rollouts (:func:`rollout_size`), so the last one may run past the total."""
    remaining = max(total_timesteps - model.num_timesteps, 0)
    return -(-remaining // rollout_size(model)) * rollout_size(model)


def rounding_note(model, total_timesteps: int) -> Optional[str]:
    """The line that says how far ``-n`` is rounded up to whole rollouts (``None`` when it is not): ``trains
    2,048 steps: -n is rounded up to whole rollouts of n_steps x n_envs = 2,048``."""
    steps = steps_to_train(model, total_timesteps)
    if steps == max(total_timesteps - model.num_timesteps, 0):
        return None
    more = f" (to {model.num_timesteps + steps:,})" if model.num_timesteps else ""
    return (
        f"trains {steps:,} steps{more}: -n is rounded up to whole rollouts of n_steps x n_envs = "
        f"{rollout_size(model):,}"
    )


class WallClockProgress(BaseCallback):
    """A progress bar over environment steps whose rate is steps per second of wall time, updates included (SB3's
    bar moves only during rollouts, so its rate is the rollout's alone); its total is the steps trained, ``-n``
    rounded up to whole rollouts (:func:`steps_to_train`)."""

    def _on_training_start(self) -> None:
        from tqdm.auto import tqdm

        self.remaining = steps_to_train(self.model, self.locals["total_timesteps"])
        self.bar = tqdm(total=self.remaining, unit="step", unit_scale=True, smoothing=0, dynamic_ncols=True)

    def _on_step(self) -> bool:
        self.bar.update(min(self.training_env.num_envs, self.remaining - self.bar.n))
        return True

    def _on_training_end(self) -> None:
        self.bar.close()


def _callbacks_in(callback) -> Iterator[BaseCallback]:
    """``callback`` and, depth first, the callbacks that a ``CallbackList`` of it holds."""
    if callback is not None:
        yield callback
        for child in getattr(callback, "callbacks", ()):
            yield from _callbacks_in(child)


class TrainingSummary(BaseCallback):
    """The terminal's lines of a run (``train -v 1``):

    * at the start, whether ``-n`` is rounded up to whole rollouts (:func:`rounding_note`);
    * after the first update past every ``every`` environment steps, and at the end: the mean return and success
      rate of the last 100 episodes (SB3's episode buffers: the Monitor's raw returns; "no episode finished yet"
      before the first) and the environment steps per second of wall time since the start, updates included (a
      line written before an update would show the rollout's rate alone);
    * after each evaluation of an ``EvalCallback`` of the same run (with a ``log_path``): its step, the mean return
      ± standard deviation over its episodes and, where the environment reports it, the success rate.

    :param every: environment steps between summary lines
    """

    def __init__(self, every: int):
        super().__init__()
        self.every = max(int(every), 1)

    def _on_training_start(self) -> None:
        self.start_steps, self.start_time = self.model.num_timesteps, time.perf_counter()
        self.next_line, self.written_at = self.start_steps + self.every, None
        note = rounding_note(self.model, self.locals["total_timesteps"])
        if note is not None:
            self._print(note)
        # SB3 hands its callbacks learn's locals: "callback" is the run's whole list, evaluations included.
        self.evaluations = [c for c in _callbacks_in(self.locals.get("callback")) if isinstance(c, EvalCallback)]
        self.reported = [len(c.evaluations_timesteps) for c in self.evaluations]

    def _on_step(self) -> bool:
        self._report_evaluations()
        return True

    def _on_rollout_end(self) -> None:
        self._report_evaluations()

    def _on_rollout_start(self) -> None:  # the previous rollout's update is done: the rate counts it
        if self.model.num_timesteps >= self.next_line:
            self._write()
            while self.next_line <= self.model.num_timesteps:
                self.next_line += self.every

    def _on_training_end(self) -> None:
        self._report_evaluations()
        if self.written_at != self.model.num_timesteps:
            self._write()

    def summary(self) -> str:
        steps = self.model.num_timesteps
        parts = [f"{steps:>11,} steps"]
        if self.model.ep_info_buffer:
            parts.append(f"return {np.mean([info['r'] for info in self.model.ep_info_buffer]):.4g}")
        else:
            parts.append("no episode finished yet")
        if self.model.ep_success_buffer:
            parts.append(f"success {np.mean(self.model.ep_success_buffer):.2f}")
        rate = (steps - self.start_steps) / max(time.perf_counter() - self.start_time, 1e-9)
        parts.append(f"{rate:,.0f} steps/s")
        return " | ".join(parts)

    @staticmethod
    def evaluation_line(evaluation: EvalCallback) -> str:
        """The line of ``evaluation``'s latest result, e.g. ``  4,096 steps | evaluation: return 0.62 ± 0.31 over 20
        episodes | success 0.81``."""
        returns = np.asarray(evaluation.evaluations_results[-1], dtype=float)
        parts = [
            f"{evaluation.evaluations_timesteps[-1]:>11,} steps",
            f"evaluation: return {returns.mean():.4g} ± {returns.std():.4g} over {returns.size} "
            f"episode{'s' if returns.size != 1 else ''}",
        ]
        successes = evaluation.evaluations_successes
        if len(successes) == len(evaluation.evaluations_timesteps) and len(successes[-1]):
            parts.append(f"success {np.mean(successes[-1]):.2f}")
        return " | ".join(parts)

    def _report_evaluations(self) -> None:
        for index, evaluation in enumerate(self.evaluations):
            if len(evaluation.evaluations_timesteps) > self.reported[index]:
                self.reported[index] = len(evaluation.evaluations_timesteps)
                self._print(self.evaluation_line(evaluation))

    @staticmethod
    def _print(line: str) -> None:
        from tqdm.auto import tqdm

        tqdm.write(line)  # above a progress bar, if one is shown

    def _write(self) -> None:
        self._print(self.summary())
        self.written_at = self.model.num_timesteps


class ActivityFigureCallback(BaseCallback):
    """Every ``every`` rollouts, log a figure of one episode's network activity to TensorBoard (``snn/activity``):
    input / hidden / output spike rasters, output membrane potentials, the traces of a few synapses and the
    modulatory signals (:func:`sb3_spikeplastic.zoo.figures.activity_figure`).

    The episode runs on a separate single environment made by ``env`` (never a training environment), always reset
    with the same ``seed``, so successive figures show the same episode (e.g. the same T-maze cues) as training
    goes on. With ``VecNormalize`` the training statistics normalise its observations (without updating them).

    :param env: an environment id, or a function returning a fresh environment.
    :param every: rollouts between figures (>= 1).
    :param env_kwargs: ``gymnasium.make`` arguments when ``env`` is an id.
    :param seed: reset seed of the episode.
    :param max_steps: environment steps recorded (see :func:`record_episode`).
    :param deterministic: mean / arg-max actions.
    :param tag: the logger key.
    """

    def __init__(
        self,
        env: Union[str, Callable[[], gymnasium.Env]],
        every: int = 10,
        env_kwargs: Optional[Mapping[str, Any]] = None,
        seed: int = 0,
        max_steps: Optional[int] = None,
        deterministic: bool = True,
        tag: str = "snn/activity",
        verbose: int = 0,
    ):
        super().__init__(verbose)
        if int(every) < 1:
            raise ValueError(f"every={every!r} must be >= 1 rollout")
        if isinstance(env, str):
            env_id, kwargs = env, dict(env_kwargs or {})
            self._make_env: Callable[[], gymnasium.Env] = lambda: gymnasium.make(env_id, **kwargs)
            self._title = env_id
        else:
            self._make_env = env
            self._title = ""
        self.every, self.seed, self.max_steps = int(every), seed, max_steps
        self.deterministic, self.tag = deterministic, tag
        self.n_rollouts = 0
        self._env: Optional[gymnasium.Env] = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.n_rollouts += 1
        if self.n_rollouts % self.every:
            return
        self.logger.record(self.tag, Figure(self.make_figure(), close=True), exclude=("stdout", "log", "json", "csv"))

    def make_figure(self):
        """Record the episode and draw its figure (a ``matplotlib.figure.Figure``)."""
        from .figures import activity_figure

        if self._env is None:
            self._env = self._make_env()
            if not self._title and self._env.spec is not None:
                self._title = self._env.spec.id
        vec_normalize = self.model.get_vec_normalize_env()
        obs_transform = vec_normalize.normalize_obs if vec_normalize is not None and vec_normalize.norm_obs else None
        policy = self.model.policy
        was_training = policy.training
        policy.set_training_mode(False)
        try:
            activity = record_episode(
                policy,
                self._env,
                seed=self.seed,
                deterministic=self.deterministic,
                max_steps=self.max_steps,
                obs_transform=obs_transform,
            )
        finally:
            policy.set_training_mode(was_training)
        return activity_figure(activity, title=f"{self._title}  step {self.num_timesteps:,}")

    def _on_training_end(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None
