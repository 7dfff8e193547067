"""The noisy spiking cue-association T-maze (paper §3.1 and appendix 5.4)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

#: Spike probabilities per ms ``(cue event, cue rest, noise population)`` of the paper's two noise levels
#: (appendix 5.4, "Cue-Association Training Details").
NOISE_LEVELS: dict[str, tuple[float, float, float]] = {
    "low": (0.75, 0.05, 0.2),
    "high": (0.65, 0.25, 0.4),
}

LEFT, RIGHT = 0, 1
# Index of each population in the input vector; each occupies ``neurons_per_population`` consecutive neurons.
_LEFT_POP, _RIGHT_POP, _DECISION_POP, _NOISE_POP = 0, 1, 2, 3
_N_POPULATIONS = 4


def _check_int(name: str, value: Any, minimum: int) -> int:
    """Return ``value`` as an int, or raise a one-line ``ValueError`` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}={value!r} must be an integer >= {minimum}")
    return int(value)


def _check_probability(name: str, value: Any) -> float:
    """Return ``value`` as a float in [0, 1], or raise a one-line ``ValueError`` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}={value!r} must be a probability in [0, 1]")
    if not 0.0 <= float(value) <= 1.0:  # also rejects NaN
        raise ValueError(f"{name}={value!r} must be a probability in [0, 1]")
    return float(value)


#: Video colours of the populations' spikes (left cue, right cue, decision cue, noise) and of their columns' bands.
_POPULATION_COLOURS = np.array([(60, 140, 255), (255, 150, 40), (255, 255, 255), (150, 150, 150)])
_POPULATION_BANDS = np.array([(10, 20, 40), (40, 25, 10), (30, 30, 30), (15, 15, 15)])
#: Pixels per neuron-millisecond in a video frame.
_BLOCK = 8


def spike_probabilities(noise: str, p_cue_event: Any, p_cue_rest: Any, p_noise: Any) -> tuple[float, float, float]:
    """``(p_cue_event, p_cue_rest, p_noise)``: each given one checked, each ``None`` from the ``noise`` level."""
    if noise not in NOISE_LEVELS:
        raise ValueError(f"noise={noise!r} is not one of {tuple(NOISE_LEVELS)}")
    given = {"p_cue_event": p_cue_event, "p_cue_rest": p_cue_rest, "p_noise": p_noise}
    return tuple(
        _check_probability(name, level if value is None else value)
        for (name, value), level in zip(given.items(), NOISE_LEVELS[noise])
    )


def check_rendering(render_mode: Any, render_fps: Any) -> float:
    """``render_fps`` as a float, once ``render_mode`` and it are checked (one-line errors naming them)."""
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode={render_mode!r} is not supported; accepted: None, 'rgb_array'")
    if isinstance(render_fps, bool) or not isinstance(render_fps, (int, float)) or not 0 < render_fps < float("inf"):
        raise ValueError(f"render_fps={render_fps!r} must be a finite number > 0")
    return float(render_fps)


def raster_image(frame: np.ndarray, colours: np.ndarray, bands: np.ndarray, neurons_per_population: int) -> np.ndarray:
    """A ``(ms, neurons)`` spike raster as an RGB image: each population's spikes in its colour (``colours``: one
    per population, or one per neuron) on its band, one 8x8 pixel block per neuron-millisecond."""
    if len(colours) != frame.shape[1]:
        colours = np.repeat(colours, neurons_per_population, axis=0)
    background = np.repeat(bands, neurons_per_population, axis=0)
    image = np.where(frame[..., None] > 0, colours[None], background[None]).astype(np.uint8)
    return np.kron(image, np.ones((_BLOCK, _BLOCK, 1), dtype=np.uint8))


class TMazeCueEnv(gymnasium.Env):
    """Cue-association T-maze with spiking input: choose the side that showed more cues.

    Four populations of ``neurons_per_population`` input neurons (default 10 each, 40 inputs in the order left cue,
    right cue, decision cue, noise) emit independent Bernoulli spikes every millisecond. ``n_cues`` cues, each
    randomly left or right, are shown one after another; after a rest delay ``r`` drawn from ``rest_choices_ms``
    the decision population announces the T-junction and the agent must name the side with more cues.

    Timeline of one episode (defaults; ``L``/``R`` = one cue slot of ``cue_ms``, ``.`` = gap of ``gap_ms``)::

        | lead-in |  L  .  R  .  R  .  L  .  R  .  L  .  L  |   rest r    | decision |
        | 5/0/20  | 7 cues x 25 ms, 6 gaps x 25 ms = 325 ms |  45/75/105  |  25 ms   |
        ^ reset returns the first frame          the action on the last frame is the decision ^

    * The cue phase lasts ``n_cues * cue_ms + (n_cues - 1) * gap_ms`` ms. The gaps keep consecutive cues apart, as
      the pauses between cues in the paper's input raster (Fig. 1B) do; a gap of one cue length is a 50 % duty
      cycle, and the longest episode (475 ms) stays within the 500 ms horizon of appendix 5.4 (gaps up to 32 ms
      would fit).
    * The rest delay is exactly ``r`` ms and the decision period closes the episode. So that the episode is a whole
      number of frames and the decision period is the end of the last frame, a *lead-in* of
      ``(-(cue phase + r + decision_ms)) mod frame_ms`` ms of cue-rest activity precedes the first cue.
      Defaults: ``r`` = 45, 75, 105 ms gives lead-ins of 5, 0, 20 ms and episodes of 400, 425, 475 ms = 16, 17,
      19 frames of 25 ms.
    * Spike probabilities per ms: the population of the presented side fires at ``p_cue_event`` during its cue slot,
      and the decision population during the decision period; every cue population (left, right, decision) fires
      at ``p_cue_rest`` whenever it is not active; the noise population fires at ``p_noise`` throughout.

    Observation: the 0/1 spike raster of one frame, shape ``(frame_ms, 4 * neurons_per_population)``, float32
    (``frame_ms`` = 25 by default: the policy sees every millisecond). ``reset`` returns the first frame and each
    ``step`` the next; the observation returned by the final step is all zeros. Action: ``Discrete(2)``,
    0 = left, 1 = right. Only the action taken on the last frame counts: it earns +1 if it names the side with
    more cues and -1 otherwise, and ends the episode (``terminated``); every other step earns 0. The final step's
    ``info`` holds ``"is_success"`` (read by Stable-Baselines3 for ``rollout/success_rate``) and
    ``"correct_action"``. After ``reset`` the episode's cue sides are in :attr:`cues` and its rest delay in
    :attr:`rest_ms`.

    The whole episode raster is drawn, vectorised, at ``reset`` from the environment's ``np_random``, so
    ``reset(seed=s)`` fixes the cues, the rest delay and every spike.

    :param noise: noise level, ``"low"`` or ``"high"``; it sets the spike probabilities left as ``None``.
    :param n_cues: number of cues; odd, so that one side always has more.
    :param cue_ms: duration of one cue in ms.
    :param gap_ms: pause (cue-rest activity) between consecutive cues in ms.
    :param rest_choices_ms: rest delays between the last cue and the decision period, drawn uniformly per episode.
    :param decision_ms: duration of the decision period in ms.
    :param frame_ms: milliseconds per observation (one environment step).
    :param neurons_per_population: neurons in each of the four populations.
    :param p_cue_event: spike probability per ms of an active cue population; ``None``: from ``noise``.
    :param p_cue_rest: spike probability per ms of an inactive cue population; ``None``: from ``noise``.
    :param p_noise: spike probability per ms of the noise population; ``None``: from ``noise``.
    :param horizon_ms: upper bound on the episode length in ms; the longest possible episode must fit.
    :param cues: a fixed cue sequence (``n_cues`` values, 0 = left, 1 = right) shown in every episode instead of
        random cues, e.g. all-left for figures. The random stream is consumed as with random cues, so for one seed
        the rest delay and the noise population's spikes do not depend on the cues.
    :param render_mode: ``None`` or ``"rgb_array"`` (the current frame's raster, one 8x8 pixel block per
        neuron-millisecond, time running down; each population's spikes in its colour, left cue blue, right cue
        orange, decision cue white, noise grey, with a dark band marking each population's columns; once the
        decision is made, the decision frame's spikes turn green if it was right and red if wrong). SB3 creates
        environments from an id with ``"rgb_array"``.
    :param render_fps: ``metadata["render_fps"]``, the frames per second of a video: 4 shows a 25 ms frame for
        250 ms (ten times slower than real time, ``1000 / frame_ms``), so that a person can follow the cues.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        noise: str = "low",
        n_cues: int = 7,
        cue_ms: int = 25,
        gap_ms: int = 25,
        rest_choices_ms: Sequence[int] = (45, 75, 105),
        decision_ms: int = 25,
        frame_ms: int = 25,
        neurons_per_population: int = 10,
        p_cue_event: float | None = None,
        p_cue_rest: float | None = None,
        p_noise: float | None = None,
        horizon_ms: int = 500,
        cues: Sequence[int] | None = None,
        render_mode: str | None = None,
        render_fps: float = 4.0,
    ) -> None:
        self.p_cue_event, self.p_cue_rest, self.p_noise = spike_probabilities(noise, p_cue_event, p_cue_rest, p_noise)
        self.noise = noise
        fps = check_rendering(render_mode, render_fps)
        self.n_cues = _check_int("n_cues", n_cues, 1)
        if self.n_cues % 2 == 0:
            raise ValueError(f"n_cues={n_cues!r} must be odd so that one side always shows more cues")
        self.cue_ms = _check_int("cue_ms", cue_ms, 1)
        self.gap_ms = _check_int("gap_ms", gap_ms, 0)
        self.decision_ms = _check_int("decision_ms", decision_ms, 1)
        self.frame_ms = _check_int("frame_ms", frame_ms, 1)
        self.neurons_per_population = _check_int("neurons_per_population", neurons_per_population, 1)
        self.horizon_ms = _check_int("horizon_ms", horizon_ms, 1)
        is_sequence = np.iterable(rest_choices_ms) and not isinstance(rest_choices_ms, (str, bytes))
        if not is_sequence or len(rest_choices_ms) == 0:
            raise ValueError(f"rest_choices_ms={rest_choices_ms!r} must be a non-empty sequence of integers >= 0")
        self.rest_choices_ms = tuple(_check_int("rest_choices_ms", r, 0) for r in rest_choices_ms)

        self._fixed_cues: list[int] | None = None
        if cues is not None:
            fixed = list(cues) if np.iterable(cues) else []
            if len(fixed) != self.n_cues or any(c not in (LEFT, RIGHT) for c in fixed):
                raise ValueError(f"cues={cues!r} must be {self.n_cues} values, each 0 (left) or 1 (right)")
            self._fixed_cues = [int(c) for c in fixed]

        self.cue_phase_ms = self.n_cues * self.cue_ms + (self.n_cues - 1) * self.gap_ms
        longest = max(self.episode_length_ms(r) for r in self.rest_choices_ms)
        if longest > self.horizon_ms:
            raise ValueError(
                f"horizon_ms={horizon_ms!r} is shorter than the longest episode ({longest} ms with lead-in); "
                "shorten the cues, gaps, rest or decision period, or raise horizon_ms"
            )

        self.n_inputs = _N_POPULATIONS * self.neurons_per_population
        self.observation_space = spaces.Box(0.0, 1.0, shape=(self.frame_ms, self.n_inputs), dtype=np.float32)
        self.action_space = spaces.Discrete(2)
        self.render_mode = render_mode
        # Real time: one frame of frame_ms per frame shown.
        self.metadata = {**type(self).metadata, "render_fps": fps}

        #: Sides of the current episode's cues (0 = left, 1 = right), in order of presentation.
        self.cues: list[int] = []
        #: Rest delay of the current episode in ms.
        self.rest_ms: int | None = None
        self._frames = np.zeros((0, self.frame_ms, self.n_inputs), dtype=np.float32)
        self._frame = 0
        self._success: bool | None = None  # the decision of the current episode, once made

    def lead_in_ms(self, rest_ms: int) -> int:
        """Cue-rest lead-in before the first cue that makes an episode with rest delay ``rest_ms`` whole frames.

        :param rest_ms: the episode's rest delay in ms.
        :return: lead-in in ms, in ``[0, frame_ms)``.
        """
        return -(self.cue_phase_ms + rest_ms + self.decision_ms) % self.frame_ms

    def episode_length_ms(self, rest_ms: int) -> int:
        """Length of an episode with rest delay ``rest_ms``, lead-in included: a multiple of ``frame_ms``.

        :param rest_ms: the episode's rest delay in ms.
        :return: episode length in ms.
        """
        return self.lead_in_ms(rest_ms) + self.cue_phase_ms + rest_ms + self.decision_ms

    @property
    def correct_action(self) -> int:
        """The side with more cues in the current episode (0 = left, 1 = right)."""
        return int(2 * sum(self.cues) > self.n_cues)

    @property
    def n_frames(self) -> int:
        """Number of frames (environment steps) of the current episode."""
        return len(self._frames)

    def _spike_probabilities(self) -> np.ndarray:
        """Per-ms, per-population spike probabilities of the current episode, shape ``(episode_ms, 4)``."""
        total = self.episode_length_ms(self.rest_ms)
        p = np.full((total, _N_POPULATIONS), self.p_cue_rest)
        p[:, _NOISE_POP] = self.p_noise
        first = self.lead_in_ms(self.rest_ms)
        for i, side in enumerate(self.cues):
            start = first + i * (self.cue_ms + self.gap_ms)
            p[start : start + self.cue_ms, _LEFT_POP if side == LEFT else _RIGHT_POP] = self.p_cue_event
        p[total - self.decision_ms :, _DECISION_POP] = self.p_cue_event
        return p

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Draw a new episode (cues, rest delay, all spikes) and return its first frame.

        :param seed: seed of the environment's random generator.
        :param options: unused.
        :return: the first frame and an empty info dict.
        """
        super().reset(seed=seed)
        cues = self.np_random.integers(LEFT, RIGHT + 1, size=self.n_cues).tolist()
        self.cues = list(self._fixed_cues) if self._fixed_cues is not None else cues
        self.rest_ms = int(self.np_random.choice(self.rest_choices_ms))
        p = np.repeat(self._spike_probabilities(), self.neurons_per_population, axis=1)
        raster = self.np_random.random(p.shape) < p
        self._frames = raster.astype(np.float32).reshape(-1, self.frame_ms, self.n_inputs)
        self._frame = 0
        self._success = None
        return self._frames[0].copy(), {}

    def render(self) -> np.ndarray | None:
        """The current frame's spike raster as an RGB image (``render_mode="rgb_array"``), else ``None``.

        After the decision the decision frame is shown again, its spikes green (right) or red (wrong), so that a
        video of the episode ends on its outcome.
        """
        if self.render_mode != "rgb_array":
            return None
        frame = (
            self._frames[min(self._frame, len(self._frames) - 1)]
            if len(self._frames)
            else np.zeros((self.frame_ms, self.n_inputs), dtype=np.float32)
        )
        if self._success is None:
            colours = _POPULATION_COLOURS
        else:
            colours = np.tile((0, 200, 0) if self._success else (230, 0, 0), (self.n_inputs, 1))
        return raster_image(frame, colours, _POPULATION_BANDS, self.neurons_per_population)

    @property
    def video_labels(self) -> list[tuple[float, str]]:
        """Captions of a video frame's columns, ``(centre as a fraction of the width, text)``: the populations."""
        return [
            ((i + 0.5) / _N_POPULATIONS, name) for i, name in enumerate(("left cue", "right cue", "decision", "noise"))
        ]

    def action_masks(self) -> np.ndarray:
        """Which actions are open on the current frame, in sb3-contrib's ``MaskablePPO`` convention.

        Only the last frame's action is a decision (paper §3.1: the agent acts once, at the end of the decision
        period); every other frame's action is ignored by :meth:`step`, so there only action 0 is open. A learner
        that honours the mask (``sb3_spikeplastic.PPO(use_action_masks=True)``) then draws no policy gradient
        from the ignored actions, whose advantages are pure noise for the policy; the task is unchanged.

        :return: boolean array of shape ``(2,)``: ``[True, True]`` on the decision frame, else ``[True, False]``.
        """
        decision = len(self._frames) > 0 and self._frame == len(self._frames) - 1
        return np.array([True, decision])

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Advance one frame; on the last frame the action is the decision and ends the episode.

        :param action: 0 (left) or 1 (right).
        :return: next frame, reward, terminated, truncated (always False), info.
        """
        if not self.action_space.contains(action):
            raise ValueError(f"action={action!r} is not in {self.action_space}")
        if self._frame >= len(self._frames):
            raise RuntimeError("the episode has ended (or never started): call reset() before step()")
        self._frame += 1
        if self._frame < len(self._frames):
            return self._frames[self._frame].copy(), 0.0, False, False, {}
        success = int(action) == self.correct_action
        self._success = success
        info = {"is_success": success, "correct_action": self.correct_action}
        terminal = np.zeros(self.observation_space.shape, dtype=np.float32)
        return terminal, 1.0 if success else -1.0, True, False, info
