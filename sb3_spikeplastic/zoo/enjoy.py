"""Watch a trained agent (``sb3-spikeplastic enjoy``, after rl-baselines3-zoo's ``enjoy.py`` and
``record_video.py``): play episodes of a model on one environment, report each episode's return, length and
success, and record them as a video.

* The model acts through ``model.predict(obs, state=..., episode_start=...)``, so a recurrent policy (the spiking
  network's state and traces, an LSTM) carries its state through each episode and starts afresh at the next; the
  run's ``VecNormalize`` statistics normalise the observations, frozen, as in training.
* Frames are the environment's ``render()`` with ``render_mode="rgb_array"``: one after each ``reset`` and one
  after each step, the last one included, so an episode of ``n`` steps gives ``n + 1`` frames and episodes of
  ``n_1 ... n_k`` steps give ``n_1 + ... + n_k + k`` (exactly so in an ``.mp4``; a ``.gif`` merges identical
  consecutive frames into one longer frame).
* MuJoCo environments render offscreen through OpenGL; :func:`select_mujoco_gl` picks a backend that works on this
  machine (a headless one needs EGL or OSMesa).
* ``--raster`` (:class:`SpikeRaster`) draws a spiking policy's hidden-layer spikes of the last 200 ms beside each
  frame.
* :class:`VideoFile` writes through imageio (``pip install "sb3-spikeplastic[video]"``) to a temporary file
  beside the target and renames it into place at the end, so a crash or Ctrl-C leaves no half-written video.

Errors of the caller's input are ``ValueError`` (the command line reports them in one line).
:func:`enjoy_command` is ``sb3-spikeplastic enjoy``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence

import gymnasium
import numpy as np

#: Video file extensions and the imageio format that writes them.
VIDEO_FORMATS = {".mp4": "FFMPEG", ".gif": "GIF"}
#: Frames per second of a video when the environment names none (``metadata["render_fps"]``).
DEFAULT_FPS = 30.0
#: OpenGL backends tried for MuJoCo after the user's ``MUJOCO_GL``: both render without a display.
HEADLESS_GL = ("egl", "osmesa")
INSTALL_VIDEO = 'pip install "sb3-spikeplastic[video]"'

# Creates a MuJoCo rendering context with the backend named by MUJOCO_GL, as gymnasium's offscreen viewer does.
_GL_PROBE = """
import importlib, os, mujoco
context = importlib.import_module("mujoco." + os.environ["MUJOCO_GL"]).GLContext(16, 16)
context.make_current()
mujoco.MjrContext(mujoco.MjModel.from_xml_string("<mujoco/>"), mujoco.mjtFontScale.mjFONTSCALE_150)
"""


def check_video_options(video: Optional[os.PathLike], fps: Optional[float] = None,
                        size: Optional[Sequence[int]] = None, raster: bool = False) -> None:
    """``ValueError`` unless the video options can be honoured: a known extension, imageio (and imageio-ffmpeg for
    ``.mp4``) installed, a positive finite ``fps`` and a ``size`` of two integers >= 16; ``fps``, ``size`` and
    ``raster`` only with a video. Checked before any work, so that a long run never fails at its end.

    :param video: the video file, or ``None`` (no video).
    :param fps: frames per second, or ``None`` (the environment's).
    :param size: ``(width, height)`` of the frames, or ``None`` (the environment's).
    :param raster: whether the frames get a spike raster (:class:`SpikeRaster`).
    """
    if video is None:
        given = [flag for flag, value in (("--fps", fps), ("--size", size), ("--raster", raster or None))
                 if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: only with a video; give --video FILE too")
        return
    suffix = Path(video).suffix.lower()
    if suffix not in VIDEO_FORMATS:
        raise ValueError(f"--video {str(video)!r}: unknown video format {suffix or '(no extension)'!r}; accepted: "
                         f"{', '.join(VIDEO_FORMATS)}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"--fps {fps!r} must be a finite number > 0")
    if size is not None and min(size) < 16:
        raise ValueError(f"--size {size[0]} {size[1]}: width and height must be >= 16 pixels")
    try:
        import imageio  # noqa: F401

        if suffix == ".mp4":
            import imageio_ffmpeg  # noqa: F401
    except ImportError as exc:
        raise ValueError(f"--video {suffix} needs {exc.name} (not installed): {INSTALL_VIDEO}") from None


def is_mujoco_env(env: gymnasium.Env) -> bool:
    """Whether ``env`` is a Gymnasium MuJoCo environment (it renders through OpenGL)."""
    return any(c.__name__ == "MujocoEnv" and c.__module__.startswith("gymnasium.envs.mujoco")
               for c in type(env.unwrapped).__mro__)


def _gl_works(backend: str) -> bool:
    """Whether MuJoCo can create a rendering context with ``backend``, tried in a child process: a process that
    loaded one OpenGL platform cannot switch to another."""
    env = {**os.environ, "MUJOCO_GL": backend}
    try:
        # (in the temporary folder: a MuJoCo that fails may leave MUJOCO_LOG.TXT in its working folder)
        result = subprocess.run([sys.executable, "-c", _GL_PROBE], env=env, capture_output=True, timeout=120,
                                cwd=tempfile.gettempdir())
    except (OSError, subprocess.TimeoutExpired):
        return False
    return result.returncode == 0


def select_mujoco_gl(works: Callable[[str], bool] = _gl_works) -> str:
    """Choose the OpenGL backend of MuJoCo's offscreen rendering and set it as ``MUJOCO_GL`` in this process.

    Tried in order: the user's ``MUJOCO_GL`` if set, then ``egl`` and ``osmesa`` (both headless). Must run before
    the first MuJoCo frame is rendered in this process.

    :param works: whether a backend can render here (default: a test rendering context in a child process).
    :return: the backend chosen.
    :raises RuntimeError: if none works; the message names what to install.
    """
    user = os.environ.get("MUJOCO_GL")
    candidates = list(dict.fromkeys([*([user] if user else []), *HEADLESS_GL]))
    for backend in candidates:
        if works(backend):
            os.environ["MUJOCO_GL"] = backend
            return backend
    raise RuntimeError(f"MuJoCo cannot render offscreen here (tried MUJOCO_GL={', '.join(candidates)}): install "
                       "EGL (Debian/Ubuntu: apt install libegl1) or OSMesa (apt install libosmesa6), or set "
                       "MUJOCO_GL to a backend that works")


def make_env(env_id: str, env_kwargs: Optional[dict] = None, render: bool = False,
             size: Optional[Sequence[int]] = None) -> gymnasium.Env:
    """``gymnasium.make(env_id, **env_kwargs)``, rendering ``rgb_array`` frames when ``render``.

    :param env_id: Gymnasium id.
    :param env_kwargs: ``gymnasium.make`` arguments (the run's).
    :param render: make it with ``render_mode="rgb_array"``; ``ValueError`` if it cannot render so.
    :param size: ``(width, height)`` of a MuJoCo environment's offscreen camera (other environments' frames are
        scaled by :func:`resize_nearest` instead).

    A MuJoCo model's camera named ``track`` (HalfCheetah's follows the body) films it unless ``env_kwargs`` name a
    camera: gymnasium's default free camera stays where the episode started while the agent runs out of view.
    """
    kwargs = dict(env_kwargs or {})
    if render:
        kwargs["render_mode"] = "rgb_array"
    try:
        env = gymnasium.make(env_id, **kwargs)
        if render and is_mujoco_env(env):
            extra = _mujoco_camera(env, kwargs, size)
            if extra:
                env.close()
                env = gymnasium.make(env_id, **kwargs, **extra)
    except Exception as exc:  # gymnasium's and the environments' own errors of bad arguments
        raise ValueError(f"cannot make {env_id} with env_kwargs={kwargs}: {' '.join(str(exc).split())}") from None
    if render and "rgb_array" not in env.metadata.get("render_modes", ()):
        env.close()
        raise ValueError(f"{env_id} cannot render video frames (its render modes: "
                         f"{', '.join(env.metadata.get('render_modes', ())) or 'none'}; rgb_array is needed)")
    return env


def _mujoco_camera(env: gymnasium.Env, kwargs: dict, size: Optional[Sequence[int]]) -> dict:
    """The ``gymnasium.make`` arguments that set a MuJoCo environment's frame size and tracking camera."""
    import mujoco

    extra: dict[str, Any] = {}
    if size is not None:
        extra.update(width=int(size[0]), height=int(size[1]))
    if ("camera_name" not in kwargs and "camera_id" not in kwargs
            and mujoco.mj_name2id(env.unwrapped.model, mujoco.mjtObj.mjOBJ_CAMERA, "track") != -1):
        extra["camera_name"] = "track"
    return extra


def video_fps(env: gymnasium.Env, fps: Optional[float] = None) -> float:
    """``fps`` if given, else the environment's ``metadata["render_fps"]``, else :data:`DEFAULT_FPS`."""
    return float(fps or env.metadata.get("render_fps") or DEFAULT_FPS)


def resize_nearest(frame: np.ndarray, width: int, height: int) -> np.ndarray:
    """``frame`` ``(h, w, channels)`` scaled to ``(height, width, channels)`` by repeating or dropping pixels (sharp
    edges, as a spike raster should keep)."""
    rows = np.arange(height) * frame.shape[0] // height
    cols = np.arange(width) * frame.shape[1] // width
    return frame[rows][:, cols]


#: Frames narrower than this get no caption strip (its words would not fit).
CAPTION_MIN_WIDTH = 240


def caption_strip(width: int, labels: Sequence[tuple[float, str]], height: int = 18) -> np.ndarray:
    """A black ``(height, width, 3)`` strip with each label written, in white, centred at its fraction of the width
    (matplotlib's Agg renderer, no GUI)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / 100, height / 100), dpi=100, facecolor="black")
    canvas = FigureCanvasAgg(fig)
    for x, text in labels:
        fig.text(x, 0.5, text, color="white", ha="center", va="center", fontsize=7)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:height, :width, :3].copy()


class VideoFile:
    """A video written frame by frame through imageio, atomically.

    Frames go to a hidden temporary file beside ``path`` (same extension, so that the same writer serves);
    :meth:`commit` closes it and renames it to ``path``. Leaving the ``with`` block without :meth:`commit` (an
    error, Ctrl-C) removes the temporary file, so ``path`` is either the whole video or untouched. For ``.mp4``
    (H.264, yuv420p) odd frame sizes are padded by one black row or column.

    :param path: the video file (``.mp4`` or ``.gif``).
    :param fps: frames per second.
    """

    def __init__(self, path: os.PathLike, fps: float):
        self.path = Path(path)
        self.fps = float(fps)
        self.tmp = self.path.with_name(f".{self.path.stem}.tmp{os.getpid()}{self.path.suffix}")
        self.n_frames = 0
        self.shape: Optional[tuple[int, ...]] = None
        self._writer = None

    def __enter__(self) -> "VideoFile":
        return self

    def __exit__(self, *exc_info) -> None:
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:  # already failing: the temporary file goes anyway
                pass
            self._writer = None
        if self.tmp.exists():
            self.tmp.unlink()

    def _open(self):
        import imageio

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fmt = VIDEO_FORMATS[self.path.suffix.lower()]
        if fmt == "GIF":
            return imageio.get_writer(self.tmp, format=fmt, mode="I", duration=1000.0 / self.fps, loop=0)
        return imageio.get_writer(self.tmp, format=fmt, mode="I", fps=self.fps, macro_block_size=1)

    def append(self, frame: np.ndarray) -> None:
        """Add one ``(height, width, 3)`` ``uint8`` frame; every frame must have the first one's size."""
        frame = np.asarray(frame)
        if self.path.suffix.lower() == ".mp4" and (frame.shape[0] % 2 or frame.shape[1] % 2):
            frame = np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)))
        if self.shape is None:
            self.shape = frame.shape
            self._writer = self._open()
        elif frame.shape != self.shape:
            raise ValueError(f"frame {self.n_frames} has shape {frame.shape}, the video {self.shape}")
        self._writer.append_data(frame)
        self.n_frames += 1

    def commit(self) -> Path:
        """Finish the video and move it to :attr:`path`."""
        if self._writer is None:
            raise ValueError(f"no frames were written to {str(self.path)!r}")
        self._writer.close()
        self._writer = None
        os.replace(self.tmp, self.path)
        return self.path


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


def play(model, env: gymnasium.Env, n_episodes: Optional[int] = 1, deterministic: bool = True,
         seed: Optional[int] = 0, max_steps: Optional[int] = None,
         obs_transform: Optional[Callable[[np.ndarray], np.ndarray]] = None,
         on_frame: Optional[Callable[[np.ndarray], None]] = None, on_step: Optional[Callable[[], None]] = None,
         on_reset: Optional[Callable[[], None]] = None, total_steps: Optional[int] = None) -> Iterator[Episode]:
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
            actions, state = model.predict(batch, state=state, episode_start=episode_start,
                                           deterministic=deterministic, **extra)
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


class SpikeRaster:
    """The hidden layers' spikes over the last environment steps of a :class:`~sb3_spikeplastic.SpikePlasticPolicy`,
    drawn beside each video frame.

    While attached, the policy's network records its activity (``record=True``: the same spikes and actions, plus
    the per-millisecond record) and hooks keep the last ``duration_ms`` of hidden spikes. :meth:`draw` puts them to
    the right of a frame: one row per hidden neuron (layers top to bottom, separated by a grey line; evenly spaced
    neurons when there are more than the frame's rows), one column per millisecond, the newest step at the right,
    grey ticks between environment steps.

    :param policy: the model's policy; ``ValueError`` unless it is a spiking policy with a hidden layer.
    :param duration_ms: network time shown (rounded down to whole environment steps, at least one).
    """

    def __init__(self, policy, duration_ms: int = 200):
        snn = getattr(policy, "snn", None)
        if snn is None:
            raise ValueError(f"--raster needs a SpikePlasticPolicy model, not {type(policy).__name__}")
        self.sizes = [layer.n_out for layer in snn.layers[:-1]]
        if not self.sizes:
            raise ValueError("--raster: the policy's network has no hidden layer")
        self.steps_per_env_step = int(snn.steps)
        self.n_steps = max(1, duration_ms // self.steps_per_env_step)
        self.window = np.zeros((sum(self.sizes), self.n_steps * self.steps_per_env_step), dtype=bool)
        self._hooks = [snn.register_forward_pre_hook(self._record, with_kwargs=True),
                       snn.register_forward_hook(self._keep)]

    @staticmethod
    def _record(module, args, kwargs):
        return args, {**kwargs, "record": True}

    def _keep(self, module, args, output) -> None:
        spikes = np.concatenate([s[0].cpu().numpy() > 0 for s in output[0].record.spikes[:-1]], axis=1)  # (T, n)
        self.window = np.roll(self.window, -len(spikes), axis=1)
        self.window[:, -len(spikes):] = spikes.T

    def reset(self) -> None:
        """Clear the window (a new episode)."""
        self.window[:] = False

    def close(self) -> None:
        """Detach from the network (it no longer records)."""
        for hook in self._hooks:
            hook.remove()
        self._hooks = []

    def draw(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` with the raster to its right, as tall as the frame."""
        height = frame.shape[0]
        scale = max(1, height // self.window.shape[1])  # whole pixels per millisecond
        image = np.where(self.window[..., None], np.uint8(255), np.uint8(0)).repeat(3, axis=-1)
        ticks = image[:, ::self.steps_per_env_step]
        ticks[~self.window[:, ::self.steps_per_env_step]] = 48  # the first millisecond of each step
        image[:, ::self.steps_per_env_step] = ticks
        image = np.insert(image, np.cumsum(self.sizes)[:-1], 96, axis=0)  # a line between layers
        image = resize_nearest(image, self.window.shape[1] * scale, height)
        gap = np.full((height, 4, 3), 128, dtype=np.uint8)
        return np.concatenate([frame.astype(np.uint8), gap, image], axis=1)


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

    def __init__(self, model, env_id: str, env_kwargs: Optional[dict] = None, vecnormalize: Optional[Path] = None,
                 model_path: Optional[os.PathLike] = None, video: Optional[os.PathLike] = None,
                 fps: Optional[float] = None, size: Optional[Sequence[int]] = None, raster: bool = False):
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
            raise ValueError(f"cannot use the VecNormalize statistics {str(self.vecnormalize)!r} with "
                             f"{self.env_id}: {' '.join(str(exc).split())}") from None
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

    def run(self, n_episodes: Optional[int] = 1, deterministic: bool = True, seed: Optional[int] = 0,
            max_steps: Optional[int] = None, progress: bool = True,
            total_steps: Optional[int] = None) -> list[Episode]:
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
            bar = stack.enter_context(tqdm(total=total, unit="step", disable=not progress, dynamic_ncols=True,
                                           leave=False))
            video = stack.enter_context(VideoFile(self.video, self.fps)) if self.video is not None else None
            on_frame = (lambda frame: video.append(self._frame(frame))) if video is not None else None
            for episode in play(self.model, self.env, n_episodes, deterministic, seed, max_steps,
                                self.obs_transform, on_frame, lambda: bar.update(1),
                                self.raster.reset if self.raster is not None else None, total_steps):
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
            print(f"wrote {video.path}: {video.n_frames} frames ({sum(e.length for e in episodes)} steps + one "
                  f"reset frame per episode), {width}x{height}, {self.fps:g} fps")
        return episodes


def enjoy_command(run: Optional[str] = None, model: Optional[str] = None, env: Optional[str] = None,
                  vecnormalize: Optional[str] = None, best: bool = False, env_kwargs: Optional[Sequence[str]] = None,
                  n_episodes: Optional[int] = None, deterministic: bool = True, seed: Optional[int] = None,
                  max_steps: Optional[int] = None,
                  video: Optional[str] = None, fps: Optional[float] = None, size: Optional[Sequence[int]] = None,
                  raster: bool = False, no_progress: bool = False, device: str = "cpu",
                  torch_threads: int = 1, n_timesteps: Optional[int] = None, folder: Optional[str] = None,
                  exp_id: int = 0, load_checkpoint: Optional[int] = None,
                  load_last_checkpoint: bool = False) -> Callable[[], int]:
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
    info, env_id = model_source(run, model, env, vecnormalize, best, env_kwargs, folder, exp_id, load_checkpoint,
                                load_last_checkpoint)
    torch.set_num_threads(torch_threads)
    player = Player(load_model(info, device), env_id, info.env_kwargs, info.vecnormalize, info.model_path,
                    video=video, fps=fps, size=size, raster=raster)

    def enjoy() -> int:
        print(f"{env_id}: {info.model_path}" + (f" (VecNormalize: {info.vecnormalize})" if info.vecnormalize else ""))
        first = seed
        if first is None:  # a first episode that ends as most do (a success-reporting task, a spiking policy)
            first, note = 0, None
            if hasattr(player.model.policy, "snn") and deterministic:
                from .recording import typical_seed

                first, note = typical_seed(player.model.policy, lambda: gymnasium.make(env_id, **info.env_kwargs),
                                           0, obs_transform=player.obs_transform)
            if note:
                print(f"first episode: seed {first} ({note}; --seed picks another)")
        torch.manual_seed(first)
        player.run(n_episodes, deterministic, first, max_steps, progress=not no_progress, total_steps=n_timesteps)
        return 0

    return enjoy
