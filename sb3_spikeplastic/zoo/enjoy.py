"""Watch a trained agent (``sb3-spikeplastic enjoy``, after rl-baselines3-zoo's ``enjoy.py`` and
``record_video.py``): play episodes of a model on one environment, report each episode's return, length and
success, and record them as a video (:mod:`sb3_spikeplastic.zoo.video`).

* The model acts through ``model.predict(obs, state=..., episode_start=...)``, so a recurrent policy (the spiking
  network's state and traces, an LSTM) carries its state through each episode and starts afresh at the next; the
  run's ``VecNormalize`` statistics normalise the observations, frozen, as in training.
* A video gets one frame after each ``reset`` and one after each step, the last one included, so an episode of
  ``n`` steps gives ``n + 1`` frames and episodes of ``n_1 ... n_k`` steps give ``n_1 + ... + n_k + k`` (exactly
  so in an ``.mp4``; a ``.gif`` merges identical consecutive frames into one longer frame).

Errors of the caller's input are ``ValueError`` (the command line reports them in one line).
:func:`enjoy_command` is ``sb3-spikeplastic enjoy``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence

import gymnasium
import numpy as np

from .video import (
    CAPTION_MIN_WIDTH,
    SpikeRaster,
    VideoFile,
    caption_strip,
    check_video_options,
    is_mujoco_env,
    make_env,
    resize_nearest,
    select_mujoco_gl,
    video_fps,
)


@dataclasses.dataclass
class Episode:
    """One episode played.

    :param episode_return: sum of the environment's (raw, unnormalised) rewards.
    :param length: steps taken.
    :param success: ``info["is_success"]`` of its last step, ``None`` when the environment reports none.
    :param cut: stopped by ``max_steps`` (or ``total_steps``) before the environment ended it.
    """

    episode_return: float
    length: int
    success: Optional[bool]
    cut: bool


def play(
    model,
    env: gymnasium.Env,
    n_episodes: Optional[int] = 1,
    deterministic: bool = True,
    seed: Optional[int] = 0,
    max_steps: Optional[int] = None,
    obs_transform: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    on_frame: Optional[Callable[[np.ndarray], None]] = None,
    on_step: Optional[Callable[[], None]] = None,
    on_reset: Optional[Callable[[], None]] = None,
    total_steps: Optional[int] = None,
) -> Iterator[Episode]:
    """Play ``n_episodes`` episodes of ``model`` on ``env``, yielding each :class:`Episode` as it ends.

    The policy's recurrent state is carried through ``model.predict(obs, state=..., episode_start=...)`` and reset
    at each episode's first step; a model trained with action masks (the T-maze's) gets the environment's
    ``action_masks()``.

    :param model: an SB3 algorithm (``sb3_spikeplastic.PPO``, SB3's or sb3-contrib's).
    :param env: a single (not vectorised) environment with the model's spaces.
    :param n_episodes: episodes to play (``None``: as many as ``total_steps`` allows).
    :param deterministic: mean / arg-max actions, else sampled ones.
    :param seed: ``env.reset(seed=seed)`` before the first episode (the next ones continue its random stream).
    :param max_steps: stop an episode after this many steps (``None``: when the environment ends it).
    :param obs_transform: applied to each (batched) observation before the policy, e.g. the run's frozen
        ``VecNormalize.normalize_obs``.
    :param on_frame: called with ``env.render()`` after each reset and each step (see the module's frame rule).
    :param on_step: called after each step (e.g. a progress bar).
    :param on_reset: called after each reset, before its frame.
    :param total_steps: at most this many steps in all (rl-zoo's ``enjoy -n``): the episode it ends is cut.
    """
    masked = bool(getattr(model, "use_action_masks", False))
    state, played = None, 0
    if n_episodes is None and total_steps is None:
        raise ValueError("give n_episodes or total_steps")
    for index in itertools.count():
        if (n_episodes is not None and index >= n_episodes) or (total_steps is not None and played >= total_steps):
            return
        obs, info = env.reset(seed=seed if index == 0 else None)
        if on_reset is not None:
            on_reset()
        if on_frame is not None:
            on_frame(env.render())
        episode_start = np.ones((1,), dtype=bool)
        total, length, done = 0.0, 0, False
        while not done and (max_steps is None or length < max_steps) and (total_steps is None or played < total_steps):
            batch = np.asarray(obs)[None]
            if obs_transform is not None:
                batch = obs_transform(batch)
            extra: dict[str, Any] = {}
            if masked:
                extra["action_masks"] = np.asarray(env.get_wrapper_attr("action_masks")())[None]
            actions, state = model.predict(
                batch, state=state, episode_start=episode_start, deterministic=deterministic, **extra
            )
            episode_start = np.zeros((1,), dtype=bool)
            obs, reward, terminated, truncated, info = env.step(actions[0])
            total += float(reward)
            length += 1
            played += 1
            done = bool(terminated or truncated)
            if on_frame is not None:
                on_frame(env.render())
            if on_step is not None:
                on_step()
        success = info.get("is_success") if done else None
        yield Episode(total, length, None if success is None else bool(success), not done)


def describe(index: int, episode: Episode, cut_by: str = "--max-steps") -> str:
    """One line for an episode: its number, return, length, success, and whether ``max_steps`` (or what
    ``cut_by`` names) cut it."""
    line = f"episode {index}: return {episode.episode_return:.4g}, {episode.length} steps"
    if episode.success is not None:
        line += ", success" if episode.success else ", failure"
    if episode.cut:
        line += f" (cut by {cut_by})"
    return line


class Player:
    """A model, the environment it plays in (rendering frames when a video is asked for), the run's frozen
    ``VecNormalize`` statistics and the video's settings, all checked at construction; :meth:`run` plays.

    :param model: the loaded model.
    :param env_id: the environment to play in.
    :param env_kwargs: its ``gymnasium.make`` arguments.
    :param vecnormalize: the run's ``VecNormalize`` statistics file, or ``None``.
    :param model_path: the model's file, for messages.
    :param video: the video file (``.mp4`` or ``.gif``; checked with :func:`check_video_options`), or ``None``.
    :param fps: frames per second of the video (``None``: :func:`video_fps`).
    :param size: ``(width, height)`` of the video's frames (``None``: the environment's).
    :param raster: draw the hidden layers' spikes beside each frame (:class:`SpikeRaster`).
    :raises ValueError: the environment cannot be made or does not fit the model, the statistics do not fit it,
        MuJoCo cannot render here, or ``raster`` is asked of a policy without spiking hidden layers.
    """

    def __init__(
        self,
        model,
        env_id: str,
        env_kwargs: Optional[dict] = None,
        vecnormalize: Optional[Path] = None,
        model_path: Optional[os.PathLike] = None,
        video: Optional[os.PathLike] = None,
        fps: Optional[float] = None,
        size: Optional[Sequence[int]] = None,
        raster: bool = False,
    ):
        from .run_folder import check_spaces

        self.model, self.env_id, self.vecnormalize = model, env_id, vecnormalize
        self.video = Path(video) if video is not None else None
        self.size = tuple(size) if size is not None else None
        self.env = make_env(env_id, env_kwargs, render=self.video is not None, size=self.size)
        try:
            check_spaces(model, self.env, env_id, model_path or "(in memory)")
            self.obs_transform = self._normalizer()
            self.raster = SpikeRaster(model.policy) if raster else None
            self.gl = None
            if self.video is not None and is_mujoco_env(self.env):
                try:
                    self.gl = select_mujoco_gl()
                except RuntimeError as exc:
                    raise ValueError(str(exc)) from None
        except BaseException:
            self.env.close()
            raise
        self.fps = video_fps(self.env, fps)
        self._caption: Optional[np.ndarray] = None

    def _normalizer(self) -> Optional[Callable[[np.ndarray], np.ndarray]]:
        """``normalize_obs`` of the run's ``VecNormalize`` statistics (``None`` without them): it only reads the
        statistics, which therefore stay frozen."""
        if self.vecnormalize is None:
            return None
        from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

        try:  # loaded around this environment, which checks that the statistics fit its observations
            stats = VecNormalize.load(str(self.vecnormalize), DummyVecEnv([lambda: self.env]))
        except Exception as exc:  # statistics of other spaces, or not statistics at all
            raise ValueError(
                f"cannot use the VecNormalize statistics {str(self.vecnormalize)!r} with "
                f"{self.env_id}: {' '.join(str(exc).split())}"
            ) from None
        return stats.normalize_obs if stats.norm_obs else None

    def _frame(self, frame: np.ndarray) -> np.ndarray:
        """A rendered frame as it goes into the video: resized, captioned above where the environment names its
        columns (the T-maze's populations) and the frame is wide enough, the spike raster beside it."""
        if self.size is not None and frame.shape[1::-1] != self.size:
            frame = resize_nearest(frame, *self.size)
        labels = getattr(self.env.unwrapped, "video_labels", None)
        if labels and frame.shape[1] >= CAPTION_MIN_WIDTH:
            if self._caption is None or self._caption.shape[1] != frame.shape[1]:
                self._caption = caption_strip(frame.shape[1], labels)
            frame = np.concatenate([self._caption, frame.astype(np.uint8)], axis=0)
        return frame if self.raster is None else self.raster.draw(frame)

    def run(
        self,
        n_episodes: Optional[int] = 1,
        deterministic: bool = True,
        seed: Optional[int] = 0,
        max_steps: Optional[int] = None,
        progress: bool = True,
        total_steps: Optional[int] = None,
    ) -> list[Episode]:
        """Play and print each episode (and a summary); write the video if one was asked for.

        :param n_episodes: episodes to play (``None``: as many as ``total_steps`` allows).
        :param deterministic: mean / arg-max actions.
        :param seed: reset seed of the first episode.
        :param max_steps: at most this many steps per episode (``None``: as the environment ends it).
        :param progress: show a progress bar over environment steps.
        :param total_steps: at most this many steps in all (rl-zoo's ``enjoy -n``; the last episode is cut).
        :return: the episodes played.
        """
        from tqdm.auto import tqdm

        from .run_folder import cpu_settings_of

        limit = getattr(self.env.spec, "max_episode_steps", None)
        cap = min(c for c in (max_steps, limit) if c) if (max_steps or limit) else None
        episodes: list[Episode] = []
        with contextlib.ExitStack() as stack:
            stack.callback(self.env.close)
            stack.enter_context(cpu_settings_of(self.model))
            if self.raster is not None:
                stack.callback(self.raster.close)
            total = total_steps if total_steps is not None else cap and n_episodes * cap
            bar = stack.enter_context(
                tqdm(total=total, unit="step", disable=not progress, dynamic_ncols=True, leave=False)
            )
            video = stack.enter_context(VideoFile(self.video, self.fps)) if self.video is not None else None
            on_frame = (lambda frame: video.append(self._frame(frame))) if video is not None else None
            for episode in play(
                self.model,
                self.env,
                n_episodes,
                deterministic,
                seed,
                max_steps,
                self.obs_transform,
                on_frame,
                lambda: bar.update(1),
                self.raster.reset if self.raster is not None else None,
                total_steps,
            ):
                episodes.append(episode)
                budget_spent = total_steps is not None and sum(e.length for e in episodes) >= total_steps
                cut_by = "-n" if budget_spent and not (max_steps and episode.length >= max_steps) else "--max-steps"
                bar.write(describe(len(episodes), episode, cut_by))
                if cap is not None and total_steps is None:  # an early end: its remaining steps leave the total
                    bar.total -= cap - episode.length
                    bar.refresh()
            if video is not None:
                video.commit()
        returns = np.array([e.episode_return for e in episodes])
        mode = "deterministic" if deterministic else "stochastic"
        summary = f"mean return {returns.mean():.4g}"
        if len(returns) > 1:
            summary += f" ± {returns.std():.4g} over {len(returns)} episodes"
        print(f"{summary} ({mode}); {sum(e.length for e in episodes)} steps in all")
        successes = [e.success for e in episodes if e.success is not None]
        if successes:
            print(f"success rate {np.mean(successes):.3f} ({sum(successes)}/{len(successes)})")
        if video is not None:
            height, width = video.shape[:2]
            print(
                f"wrote {video.path}: {video.n_frames} frames ({sum(e.length for e in episodes)} steps + one "
                f"reset frame per episode), {width}x{height}, {self.fps:g} fps"
            )
        return episodes


def enjoy_command(
    run: Optional[str] = None,
    model: Optional[str] = None,
    env: Optional[str] = None,
    vecnormalize: Optional[str] = None,
    best: bool = False,
    env_kwargs: Optional[Sequence[str]] = None,
    n_episodes: Optional[int] = None,
    deterministic: bool = True,
    seed: Optional[int] = None,
    max_steps: Optional[int] = None,
    video: Optional[str] = None,
    fps: Optional[float] = None,
    size: Optional[Sequence[int]] = None,
    raster: bool = False,
    no_progress: bool = False,
    device: str = "cpu",
    torch_threads: int = 1,
    n_timesteps: Optional[int] = None,
    folder: Optional[str] = None,
    exp_id: int = 0,
    load_checkpoint: Optional[int] = None,
    load_last_checkpoint: bool = False,
) -> Callable[[], int]:
    """``sb3-spikeplastic enjoy`` with these options (its long names): the model is found and loaded and its
    :class:`Player` built (``ValueError``, nothing written); returns the play, which prints the model and each
    episode (:meth:`Player.run`) and returns 0. ``n_episodes`` defaults to 1, or with ``n_timesteps`` (rl-zoo's
    ``-n``: steps in all) to as many as fit."""
    import torch

    from .inputs import check_int, check_output_path, model_source
    from .run_folder import load_model

    check_int("--n-episodes", n_episodes, 1)
    check_int("--n-timesteps", n_timesteps, 1)
    check_int("--max-steps", max_steps, 1)
    if n_episodes is None and n_timesteps is None:
        n_episodes = 1
    if video:
        check_output_path(video, "--video", directory=False)
    check_video_options(video, fps, size, raster)
    info, env_id = model_source(
        run, model, env, vecnormalize, best, env_kwargs, folder, exp_id, load_checkpoint, load_last_checkpoint
    )
    torch.set_num_threads(torch_threads)
    player = Player(
        load_model(info, device),
        env_id,
        info.env_kwargs,
        info.vecnormalize,
        info.model_path,
        video=video,
        fps=fps,
        size=size,
        raster=raster,
    )

    def enjoy() -> int:
        print(f"{env_id}: {info.model_path}" + (f" (VecNormalize: {info.vecnormalize})" if info.vecnormalize else ""))
        first = seed
        if first is None:  # a first episode that ends as most do (a success-reporting task, a spiking policy)
            first, note = 0, None
            if hasattr(player.model.policy, "snn") and deterministic:
                from .recording import typical_seed

                first, note = typical_seed(
                    player.model.policy,
                    lambda: gymnasium.make(env_id, **info.env_kwargs),
                    0,
                    obs_transform=player.obs_transform,
                )
            if note:
                print(f"first episode: seed {first} ({note}; --seed picks another)")
        torch.manual_seed(first)
        player.run(n_episodes, deterministic, first, max_steps, progress=not no_progress, total_steps=n_timesteps)
        return 0

    return enjoy
