"""A T-maze whose rewarded arm must be learned within the episode, and reverses once (after Backpropamine's
tasks, Miconi et al., 2019, and the two-armed reversal bandits of meta-RL, Wang et al., 2018).

Nothing in an episode's input says which arm pays: the agent learns it from the outcomes of its own choices,
which it must remember (its previous choice is not shown), and learns it again after the reversal.
:func:`reference_rates` gives the good-arm rates that bound what a policy can reach.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from sb3_spikeplastic.envs.tmaze import (
    LEFT,
    RIGHT,
    _check_int,
    _check_probability,
    check_rendering,
    raster_image,
    spike_probabilities,
)

# Index of each population in the input vector; each occupies ``neurons_per_population`` consecutive neurons.
_DECISION_POP, _REWARD_POP, _NO_REWARD_POP, _NOISE_POP = 0, 1, 2, 3
_N_POPULATIONS = 4

#: Video colours of the populations' spikes (decision cue, reward, no reward, noise) and of their columns' bands.
_POPULATION_COLOURS = np.array([(255, 255, 255), (0, 200, 0), (230, 0, 0), (150, 150, 150)])
_POPULATION_BANDS = np.array([(30, 30, 30), (10, 35, 10), (40, 10, 10), (15, 15, 15)])


class TMazeReversalEnv(gymnasium.Env):
    """Two-armed spiking T-maze of ``n_trials`` decisions whose paying arm is hidden and reverses once.

    At ``reset`` one arm is drawn (uniformly) to be the good one: it pays with probability ``p_reward`` (0.9),
    the other with ``1 - p_reward``. With ``reversal`` (the default) the good arm swaps once, from a trial drawn
    uniformly in ``reversal_trials`` (0-based, inclusive; default 4-6 of 10) on. No input says which arm pays.

    Each environment step is one trial of ``outcome_ms + decision_ms`` ms (10 + 15 = 25 by default)::

        | outcome of the previous trial (10 ms) | decision cue (15 ms) |  -> action: the arm (0 left, 1 right)

    * The **outcome** part shows the previous trial's outcome: the reward population fires at ``p_cue_event`` if
      that choice paid, the no-reward population if it did not (both rest at ``p_cue_rest`` in the first trial).
      The previous *choice* is not shown: interpreting an outcome needs the memory of one's own choice.
    * The **decision** part: the decision population fires at ``p_cue_event``.
    * Populations not active fire at ``p_cue_rest``, the noise population at ``p_noise`` throughout (the
      ``TMazeCue-v0`` levels, ``noise="low"`` or ``"high"``).

    Observation: the trial's 0/1 spike raster, shape ``(outcome_ms + decision_ms, 4 * neurons_per_population)``
    (populations in the order decision, reward, no reward, noise), float32. Action: ``Discrete(2)``. Reward: 1 if
    the chosen arm paid, else 0. The episode ends after the ``n_trials``-th choice (``terminated``). Every step's
    ``info`` holds ``"trial"``, ``"good_arm"``, ``"choice"``, ``"good_choice"`` and ``"paid"``; the final one also
    ``"good_choice_rate"`` (the episode's fraction of good-arm choices) and ``"reversal_trial"`` (``None``
    without reversal). The whole episode (good arm, reversal, every outcome draw and spike) follows from
    ``reset(seed=...)``: outcomes are drawn per trial and arm at reset, so one seed gives the same outcome to the
    same choice.

    Reference good-arm rates for the defaults (:func:`reference_rates`): random choice 0.5, an oracle that knows
    the arm 1.0, the best policy without memory (its choice depends on the current trial's input only) 0.594, an
    ideal Bayesian learner 0.855 (without reversal: 0.628 and 0.922).

    :param noise: ``"low"`` or ``"high"``: the spike probabilities left as ``None`` (as in ``TMazeCue-v0``).
    :param n_trials: decisions per episode.
    :param p_reward: probability that the good arm pays (the other arm pays with ``1 - p_reward``).
    :param reversal: whether the good arm swaps once during the episode.
    :param reversal_trials: ``(first, last)``: the first trial of the swapped arm is drawn uniformly in this range.
    :param outcome_ms: ms of a trial that show the previous outcome.
    :param decision_ms: ms of a trial that show the decision cue.
    :param neurons_per_population: neurons in each of the four populations.
    :param p_cue_event: spike probability per ms of an active population; ``None``: from ``noise``.
    :param p_cue_rest: spike probability per ms of an inactive population; ``None``: from ``noise``.
    :param p_noise: spike probability per ms of the noise population; ``None``: from ``noise``.
    :param render_mode: ``None`` or ``"rgb_array"`` (the trial's raster, 8x8 pixels per neuron-millisecond).
    :param render_fps: ``metadata["render_fps"]`` of a video.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        noise: str = "low",
        n_trials: int = 10,
        p_reward: float = 0.9,
        reversal: bool = True,
        reversal_trials: Sequence[int] = (4, 6),
        outcome_ms: int = 10,
        decision_ms: int = 15,
        neurons_per_population: int = 10,
        p_cue_event: float | None = None,
        p_cue_rest: float | None = None,
        p_noise: float | None = None,
        render_mode: str | None = None,
        render_fps: float = 4.0,
    ) -> None:
        self.p_cue_event, self.p_cue_rest, self.p_noise = spike_probabilities(noise, p_cue_event, p_cue_rest, p_noise)
        self.noise = noise
        fps = check_rendering(render_mode, render_fps)
        self.n_trials = _check_int("n_trials", n_trials, 1)
        self.p_reward = _check_probability("p_reward", p_reward)
        if not isinstance(reversal, (bool, np.bool_)):
            raise ValueError(f"reversal={reversal!r} must be True or False")
        self.reversal = bool(reversal)
        window = list(reversal_trials) if np.iterable(reversal_trials) else []
        if len(window) != 2:
            raise ValueError(f"reversal_trials={reversal_trials!r} must be (first, last) trial indices")
        first, last = (_check_int("reversal_trials", t, 1) for t in window)
        if self.reversal and not first <= last < self.n_trials:
            raise ValueError(
                f"reversal_trials={reversal_trials!r} must satisfy 1 <= first <= last < n_trials={self.n_trials}"
            )
        self.reversal_trials = (first, last)
        self.outcome_ms = _check_int("outcome_ms", outcome_ms, 1)
        self.decision_ms = _check_int("decision_ms", decision_ms, 1)
        self.neurons_per_population = _check_int("neurons_per_population", neurons_per_population, 1)

        self.frame_ms = self.outcome_ms + self.decision_ms
        self.n_inputs = _N_POPULATIONS * self.neurons_per_population
        self.observation_space = spaces.Box(0.0, 1.0, shape=(self.frame_ms, self.n_inputs), dtype=np.float32)
        self.action_space = spaces.Discrete(2)
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": fps}

        #: The good arm of the first trial (0 = left, 1 = right).
        self.first_good_arm: int | None = None
        #: The first trial of the swapped arm, or ``None`` without reversal.
        self.reversal_trial: int | None = None
        self._pays = np.zeros((0, 2), dtype=bool)  # (trial, arm): whether that arm pays in that trial
        self._uniform = np.zeros((0, self.frame_ms, self.n_inputs))  # the spike draws of every trial
        self._trial = 0
        self._frame = np.zeros(self.observation_space.shape, dtype=np.float32)
        self._good_choices = 0

    @property
    def reward_input(self) -> dict[str, Any] | None:
        """Where a trial's raster shows the reward the previous trial paid, for the policies that read it
        (:class:`sb3_spikeplastic.sb3.modulation.RewardInput`): the reward population's mean spike rate minus the
        no-reward population's, scaled so that its expected value is the reward (1 or 0), and 0.5 in the first
        trial (no outcome shown). ``None`` where the two populations fire alike (no outcome in the input)."""
        contrast = (self.p_cue_event - self.p_cue_rest) * self.outcome_ms / self.frame_ms
        if contrast == 0:
            return None
        n = self.neurons_per_population
        return {
            "positive": list(range(_REWARD_POP * n, (_REWARD_POP + 1) * n)),
            "negative": list(range(_NO_REWARD_POP * n, (_NO_REWARD_POP + 1) * n)),
            "scale": 1.0 / (2.0 * contrast),
            "offset": 0.5,
        }

    def good_arm(self, trial: int) -> int:
        """The arm that pays with ``p_reward`` in ``trial`` (0-based) of the current episode."""
        swapped = self.reversal_trial is not None and trial >= self.reversal_trial
        return int(self.first_good_arm) ^ int(swapped)

    def _raster(self, trial: int, paid: bool | None) -> np.ndarray:
        """The spikes of ``trial`` given the previous trial's outcome (``None``: the first trial)."""
        p = np.full((self.frame_ms, _N_POPULATIONS), self.p_cue_rest)
        p[:, _NOISE_POP] = self.p_noise
        if paid is not None:
            p[: self.outcome_ms, _REWARD_POP if paid else _NO_REWARD_POP] = self.p_cue_event
        p[self.outcome_ms :, _DECISION_POP] = self.p_cue_event
        p = np.repeat(p, self.neurons_per_population, axis=1)
        return (self._uniform[trial] < p).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Draw a new episode (good arm, reversal trial, outcomes, spikes) and return the first trial's raster."""
        super().reset(seed=seed)
        rng = self.np_random
        self.first_good_arm = int(rng.integers(LEFT, RIGHT + 1))
        first, last = self.reversal_trials
        self.reversal_trial = int(rng.integers(first, last + 1)) if self.reversal else None
        good = np.array([self.good_arm(t) for t in range(self.n_trials)])
        pay_probability = np.where(np.arange(2)[None, :] == good[:, None], self.p_reward, 1.0 - self.p_reward)
        self._pays = rng.random((self.n_trials, 2)) < pay_probability
        self._uniform = rng.random((self.n_trials, self.frame_ms, self.n_inputs))
        self._trial, self._good_choices = 0, 0
        self._frame = self._raster(0, None)
        return self._frame.copy(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Choose an arm in the current trial: reward 1 if it paid; the next raster shows the outcome."""
        if not self.action_space.contains(action):
            raise ValueError(f"action={action!r} is not in {self.action_space}")
        if self._trial >= self.n_trials or self.first_good_arm is None:
            raise RuntimeError("the episode has ended (or never started): call reset() before step()")
        trial, choice = self._trial, int(action)
        good = self.good_arm(trial)
        paid = bool(self._pays[trial, choice])
        self._good_choices += choice == good
        info = {"trial": trial, "good_arm": good, "choice": choice, "good_choice": choice == good, "paid": paid}
        self._trial += 1
        terminated = self._trial == self.n_trials
        if terminated:
            info.update(good_choice_rate=self._good_choices / self.n_trials, reversal_trial=self.reversal_trial)
            self._frame = np.zeros(self.observation_space.shape, dtype=np.float32)
        else:
            self._frame = self._raster(self._trial, paid)
        return self._frame.copy(), float(paid), terminated, False, info

    def render(self) -> np.ndarray | None:
        """The current trial's raster as an RGB image (``render_mode="rgb_array"``), else ``None``."""
        if self.render_mode != "rgb_array":
            return None
        return raster_image(self._frame, _POPULATION_COLOURS, _POPULATION_BANDS, self.neurons_per_population)

    @property
    def video_labels(self) -> list[tuple[float, str]]:
        """Captions of a video frame's columns, ``(centre as a fraction of the width, text)``: the populations."""
        names = ("decision", "reward", "no reward", "noise")
        return [((i + 0.5) / _N_POPULATIONS, name) for i, name in enumerate(names)]


# ----------------------------------------------------------------------------------------------------------------
# Reference good-arm rates


def _hypotheses(n_trials: int, reversal: bool, reversal_trials: Sequence[int]) -> list[tuple[int, int | None]]:
    """Every equally likely ``(first good arm, reversal trial)`` of an episode."""
    trials = range(reversal_trials[0], reversal_trials[1] + 1) if reversal else [None]
    return [(arm, r) for arm in (LEFT, RIGHT) for r in trials]


def _good(arm: int, r: int | None, trial: int) -> int:
    return arm ^ int(r is not None and trial >= r)


def memoryless_rate(
    choose_left: Sequence[float],
    n_trials: int = 10,
    p_reward: float = 0.9,
    reversal: bool = True,
    reversal_trials: Sequence[int] = (4, 6),
) -> float:
    """Expected good-arm rate of a policy whose choice depends on the current trial's input only: it chooses left
    with probability ``choose_left[o]`` where ``o`` is the outcome shown (0: none, the first trial; 1: paid; 2: not
    paid). Exact: the distribution of the shown outcome is carried forward trial by trial."""
    total = 0.0
    hypotheses = _hypotheses(n_trials, reversal, reversal_trials)
    for arm, r in hypotheses:
        shown = np.array([1.0, 0.0, 0.0])  # P(outcome shown) in the current trial
        for trial in range(n_trials):
            good = _good(arm, r, trial)
            left = np.asarray(choose_left, dtype=float)
            p_good = left if good == LEFT else 1.0 - left
            total += float(shown @ p_good)
            paid = float(shown @ (p_good * p_reward + (1.0 - p_good) * (1.0 - p_reward)))
            shown = np.array([0.0, paid, 1.0 - paid])
    return total / (len(hypotheses) * n_trials)


def best_memoryless_policy(
    n_trials: int = 10, p_reward: float = 0.9, reversal: bool = True, reversal_trials: Sequence[int] = (4, 6)
) -> tuple[tuple[float, ...], float]:
    """The memoryless policy with the highest :func:`memoryless_rate`: ``(choose_left per shown outcome, rate)``.
    A grid of steps of 0.1, then a search along each coordinate with steps halving down to 1e-4."""

    def rate(policy) -> float:
        return memoryless_rate(policy, n_trials, p_reward, reversal, reversal_trials)

    best = list(max(itertools.product(np.linspace(0.0, 1.0, 11), repeat=3), key=rate))
    step = 0.05
    while step >= 1e-4:
        improved = False
        for i, sign in itertools.product(range(3), (-1.0, 1.0)):
            candidate = list(best)
            candidate[i] = float(np.clip(candidate[i] + sign * step, 0.0, 1.0))
            if rate(candidate) > rate(best) + 1e-12:
                best, improved = candidate, True
        if not improved:
            step /= 2
    return tuple(float(v) for v in best), rate(best)


def bayes_choice(
    choices: Sequence[int],
    outcomes: Sequence[bool],
    p_reward: float = 0.9,
    reversal: bool = True,
    reversal_trials: Sequence[int] = (4, 6),
    n_trials: int = 10,
) -> int:
    """The ideal Bayesian learner's next choice: the arm most probably good in the next trial given its earlier
    choices and their outcomes (ties: left). Greedy is optimal here: either arm's outcome tells as much about which
    arm is good, so no choice is worth making for its information."""
    trial = len(choices)
    posterior = {LEFT: 0.0, RIGHT: 0.0}
    for arm, r in _hypotheses(n_trials, reversal, reversal_trials):
        likelihood = 1.0
        for t, (choice, paid) in enumerate(zip(choices, outcomes)):
            p = p_reward if choice == _good(arm, r, t) else 1.0 - p_reward
            likelihood *= p if paid else 1.0 - p
        posterior[_good(arm, r, trial)] += likelihood
    return LEFT if posterior[LEFT] >= posterior[RIGHT] else RIGHT


def bayes_rate(
    n_trials: int = 10, p_reward: float = 0.9, reversal: bool = True, reversal_trials: Sequence[int] = (4, 6)
) -> float:
    """Expected good-arm rate of the ideal Bayesian learner (:func:`bayes_choice`), exact: every outcome sequence
    of every hypothesis, weighted by its probability."""
    hypotheses = _hypotheses(n_trials, reversal, reversal_trials)
    total = 0.0
    for arm, r in hypotheses:

        def walk(choices: list[int], outcomes: list[bool], weight: float) -> float:
            trial = len(choices)
            if trial == n_trials:
                return 0.0
            choice = bayes_choice(choices, outcomes, p_reward, reversal, reversal_trials, n_trials)
            good = choice == _good(arm, r, trial)
            p = p_reward if good else 1.0 - p_reward
            return (
                weight * good
                + walk([*choices, choice], [*outcomes, True], weight * p)
                + walk([*choices, choice], [*outcomes, False], weight * (1.0 - p))
            )

        total += walk([], [], 1.0)
    return total / (len(hypotheses) * n_trials)


def reference_rates(
    n_trials: int = 10, p_reward: float = 0.9, reversal: bool = True, reversal_trials: Sequence[int] = (4, 6)
) -> dict[str, float]:
    """Good-arm rates (the fraction of trials whose choice is the paying arm) that bound a policy on
    :class:`TMazeReversalEnv`: random choice, an oracle that knows the arm, the best memoryless policy and the
    ideal Bayesian learner. A good-arm rate ``g`` is a reward rate of ``g p + (1 - g)(1 - p)``."""
    _, memoryless = best_memoryless_policy(n_trials, p_reward, reversal, reversal_trials)
    return {
        "random": 0.5,
        "oracle": 1.0,
        "memoryless": memoryless,
        "bayes": bayes_rate(n_trials, p_reward, reversal, reversal_trials),
    }
