"""The video of ``sb3-spikeplastic enjoy --video``: an environment that renders its frames, the frames as they go
into the video, and the file.

* Frames are the environment's ``render()`` with ``render_mode="rgb_array"`` (:func:`make_env`); a MuJoCo model's
  ``track`` camera films it.
* MuJoCo environments render offscreen through OpenGL; :func:`select_mujoco_gl` picks a backend that works on this
  machine (a headless one needs EGL or OSMesa).
* Frames are scaled by :func:`resize_nearest`, get a strip naming the environment's columns above them
  (:func:`caption_strip`: the T-maze's populations) and, with ``--raster`` (:class:`SpikeRaster`), a spiking
  policy's hidden-layer spikes of the last 200 ms beside them.
* :class:`VideoFile` writes through imageio (``pip install "sb3-spikeplastic[video]"``) to a temporary file
  beside the target and renames it into place at the end, so a crash or Ctrl-C leaves no half-written video.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

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


def check_video_options(
    video: Optional[os.PathLike],
    fps: Optional[float] = None,
    size: Optional[Sequence[int]] = None,
    raster: bool = False,
) -> None:
    """``ValueError`` unless the video options can be honoured: a known extension, imageio (and imageio-ffmpeg for
    ``.mp4``) installed, a positive finite ``fps`` and a ``size`` of two integers >= 16; ``fps``, ``size`` and
    ``raster`` only with a video. Checked before any work, so that a long run never fails at its end.

    :param video: the video file, or ``None`` (no video).
    :param fps: frames per second, or ``None`` (the environment's).
    :param size: ``(width, height)`` of the frames, or ``None`` (the environment's).
    :param raster: whether the frames get a spike raster (:class:`SpikeRaster`).
    """
    if video is None:
        given = [
            flag
            for flag, value in (("--fps", fps), ("--size", size), ("--raster", raster or None))
            if value is not None
        ]
        if given:
            raise ValueError(f"{', '.join(given)}: only with a video; give --video FILE too")
        return
    suffix = Path(video).suffix.lower()
    if suffix not in VIDEO_FORMATS:
        raise ValueError(
            f"--video {str(video)!r}: unknown video format {suffix or '(no extension)'!r}; accepted: "
            f"{', '.join(VIDEO_FORMATS)}"
        )
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
    return any(
        c.__name__ == "MujocoEnv" and c.__module__.startswith("gymnasium.envs.mujoco")
        for c in type(env.unwrapped).__mro__
    )


def _gl_works(backend: str) -> bool:
    """Whether MuJoCo can create a rendering context with ``backend``, tried in a child process: a process that
    loaded one OpenGL platform cannot switch to another."""
    env = {**os.environ, "MUJOCO_GL": backend}
    try:
        # (in the temporary folder: a MuJoCo that fails may leave MUJOCO_LOG.TXT in its working folder)
        result = subprocess.run(
            [sys.executable, "-c", _GL_PROBE], env=env, capture_output=True, timeout=120, cwd=tempfile.gettempdir()
        )
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
    raise RuntimeError(
        f"MuJoCo cannot render offscreen here (tried MUJOCO_GL={', '.join(candidates)}): install "
        "EGL (Debian/Ubuntu: apt install libegl1) or OSMesa (apt install libosmesa6), or set "
        "MUJOCO_GL to a backend that works"
    )


def make_env(
    env_id: str, env_kwargs: Optional[dict] = None, render: bool = False, size: Optional[Sequence[int]] = None
) -> gymnasium.Env:
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
        raise ValueError(
            f"{env_id} cannot render video frames (its render modes: "
            f"{', '.join(env.metadata.get('render_modes', ())) or 'none'}; rgb_array is needed)"
        )
    return env


def _mujoco_camera(env: gymnasium.Env, kwargs: dict, size: Optional[Sequence[int]]) -> dict:
    """The ``gymnasium.make`` arguments that set a MuJoCo environment's frame size and tracking camera."""
    import mujoco

    extra: dict[str, Any] = {}
    if size is not None:
        extra.update(width=int(size[0]), height=int(size[1]))
    if (
        "camera_name" not in kwargs
        and "camera_id" not in kwargs
        and mujoco.mj_name2id(env.unwrapped.model, mujoco.mjtObj.mjOBJ_CAMERA, "track") != -1
    ):
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
        self._hooks = [
            snn.register_forward_pre_hook(self._record, with_kwargs=True),
            snn.register_forward_hook(self._keep),
        ]

    @staticmethod
    def _record(module, args, kwargs):
        return args, {**kwargs, "record": True}

    def _keep(self, module, args, output) -> None:
        spikes = np.concatenate([s[0].cpu().numpy() > 0 for s in output[0].record.spikes[:-1]], axis=1)  # (T, n)
        self.window = np.roll(self.window, -len(spikes), axis=1)
        self.window[:, -len(spikes) :] = spikes.T

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
        ticks = image[:, :: self.steps_per_env_step]
        ticks[~self.window[:, :: self.steps_per_env_step]] = 48  # the first millisecond of each step
        image[:, :: self.steps_per_env_step] = ticks
        image = np.insert(image, np.cumsum(self.sizes)[:-1], 96, axis=0)  # a line between layers
        image = resize_nearest(image, self.window.shape[1] * scale, height)
        gap = np.full((height, 4, 3), 128, dtype=np.uint8)
        return np.concatenate([frame.astype(np.uint8), gap, image], axis=1)
