"""A change of dynamics during an episode, for MuJoCo locomotion: does a plastic policy adapt within an episode?

:class:`DynamicsSwitch` changes one part of the model once per episode, at a step drawn at reset (a weaker
actuator, stiffer joints, a flipped action, a heavier body), in the spirit of the leg damage on which Najarro &
Risi (NeurIPS 2020) tested evolved Hebbian networks. :func:`make_switch_env` wraps a registered id or an
environment; ``HalfCheetahSwitch-v5`` is ``HalfCheetah-v5`` wrapped (registered in this package's ``__init__``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium.envs.registration import load_env_creator
from gymnasium.utils import RecordConstructorArgs

from sb3_spikeplastic.envs.noise import env_from

#: The changes :class:`DynamicsSwitch` can make.
SWITCH_KINDS = ("actuator_gain", "friction", "action_flip", "mass")


def _check_kind(kind: Any) -> str:
    """Return ``kind``, or raise a one-line ``ValueError`` unless it is one of :data:`SWITCH_KINDS`."""
    if not isinstance(kind, str) or kind not in SWITCH_KINDS:
        raise ValueError(f"switch kind={kind!r} is not one of {SWITCH_KINDS}")
    return kind


def _is_int(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, np.integer))


def _is_number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))


def _pair(value: Any) -> bool:
    """Whether ``value`` is a two-element list or tuple (YAML gives lists)."""
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes)) and len(value) == 2


def _check_window(window: Any, max_episode_steps: int | None) -> tuple[int, int]:
    """Return ``window`` as ``(lo, hi)``, or raise a one-line ``ValueError`` unless ``0 <= lo <= hi`` are integers
    and ``hi <= max_episode_steps`` (when the limit is known)."""
    top = "max_episode_steps" if max_episode_steps is None else f"max_episode_steps={max_episode_steps}"
    accepted = f"two integers [lo, hi] with 0 <= lo <= hi <= {top}"
    if not _pair(window) or not all(_is_int(w) for w in window):
        raise ValueError(f"switch window={window!r} is not {accepted}")
    lo, hi = int(window[0]), int(window[1])
    if lo < 0 or lo > hi or (max_episode_steps is not None and hi > max_episode_steps):
        raise ValueError(f"switch window={list(window)!r} is not {accepted}")
    return lo, hi


def _check_factor_range(factor_range: Any) -> tuple[float, float]:
    """Return ``factor_range`` as ``(lo, hi)``, or raise a one-line ``ValueError`` unless ``0 < lo <= hi`` are
    finite numbers."""
    accepted = "two finite numbers [lo, hi] with 0 < lo <= hi"
    if not _pair(factor_range) or not all(_is_number(f) and math.isfinite(f) for f in factor_range):
        raise ValueError(f"switch factor_range={factor_range!r} is not {accepted}")
    lo, hi = float(factor_range[0]), float(factor_range[1])
    if lo <= 0 or lo > hi:
        raise ValueError(f"switch factor_range={list(factor_range)!r} is not {accepted}")
    return lo, hi


class DynamicsSwitch(gymnasium.Wrapper, RecordConstructorArgs):
    """Changes the dynamics once per episode, at a step drawn at reset, and restores them at the next reset.

    At every ``reset`` three numbers are drawn: the switch step ``s``, uniform over the integers of ``window``
    (both ends included); the target, uniform over the valid indices unless ``target`` is given; the factor,
    uniform in ``factor_range``. The first ``s`` steps of the episode run under the nominal dynamics; the change is
    made inside step ``s + 1``, before its action is applied, so that step (``info["elapsed_steps"] == s + 1``)
    and every later one run under the changed dynamics. ``s = 0`` changes the whole episode; ``s`` at the time
    limit changes nothing (a control without a switch).

    The draws come from the wrapper's own generator, a child of the seed given to ``reset(seed=...)`` (as in the
    noise wrappers of :mod:`sb3_spikeplastic.envs.noise`): a seeded run is reproducible, and the wrapped
    environment's own random stream, hence its initial states, is that of the bare environment. The three draws
    are taken in every episode whatever ``kind`` and ``target``, so one seed gives the same switch steps for every
    kind, and the same factors for every target.

    Kinds (``target`` is an index of the element changed):

    * ``"actuator_gain"``: the ``actuator_gear`` row of one actuator is scaled by the factor. HalfCheetah's
      actuators are motors with ``gainprm[0] = 1`` and gears 120, 90, 60, 120, 60, 30: the gear is where the model
      sets each joint's strength, and the joint torque is ``gear * ctrl``, so scaling the gear scales it exactly
      (as scaling ``gainprm[0]`` would). Target: an actuator, ``0 .. nu - 1``.
    * ``"friction"``: every degree of freedom's viscous ``dof_damping`` is scaled. MuJoCo's dry joint friction,
      ``dof_frictionloss``, is 0 in HalfCheetah, so the damping is its joint friction (as in ``FrictionNoise``);
      the root's degrees of freedom have no damping and stay at 0. No target (``info["switch_target"]`` is -1).
    * ``"action_flip"``: the sign of one action dimension is flipped before the action reaches the wrapped
      environment; the factor is -1 whatever ``factor_range``. Target: an action dimension.
    * ``"mass"``: one body's ``body_mass`` is scaled; its inertia is left as it is (the change of a point mass at
      the body's centre of mass). Target: a body, ``1 .. nbody - 1`` (0 is the world body).

    The model values at the switch are scaled, so that a wrapper inside this one that draws the same parameter at
    reset (``FrictionNoise``) is scaled in turn. Every ``reset``, before the wrapped environment's, writes back
    the values saved when this wrapper was built, so changes never compound across episodes; ``close()`` does too.

    ``info``, at reset and every step: ``switch_step`` (``s``), ``switch_kind``, ``switch_target``,
    ``switch_factor``, ``switched`` (whether this step ran under the changed dynamics; False at reset) and
    ``elapsed_steps`` (steps since reset, this one included).

    :param env: a MuJoCo environment (``env.unwrapped.model`` is its ``mujoco.MjModel``; ``"action_flip"`` only
        needs a 1-D ``Box`` action space).
    :param kind: one of :data:`SWITCH_KINDS`.
    :param window: ``[lo, hi]``, the range of the switch step, with ``0 <= lo <= hi <= max_episode_steps``.
    :param factor_range: ``[lo, hi]``, the range of the factor, ``0 < lo <= hi``; ``[f, f]`` fixes it.
    :param target: the index changed in every episode; None draws it at each reset.
    :param max_episode_steps: the time limit ``window`` must lie in; None takes the wrapped environment's
        (``env.spec.max_episode_steps``), and none known checks only ``0 <= lo <= hi``.
    """

    #: Distinguishes this wrapper's generator from the noise wrappers' (streams 1-3), so that stacked wrappers
    #: seeded alike draw independent numbers.
    _stream = 4

    def __init__(
        self,
        env: gymnasium.Env,
        kind: str = "actuator_gain",
        window: Sequence[int] = (300, 700),
        factor_range: Sequence[float] = (0.2, 0.5),
        target: int | None = None,
        max_episode_steps: int | None = None,
    ) -> None:
        RecordConstructorArgs.__init__(
            self,
            kind=kind,
            window=window,
            factor_range=factor_range,
            target=target,
            max_episode_steps=max_episode_steps,
        )
        super().__init__(env)
        self.kind = _check_kind(kind)
        if max_episode_steps is None and env.spec is not None:
            max_episode_steps = env.spec.max_episode_steps
        if max_episode_steps is not None and (not _is_int(max_episode_steps) or max_episode_steps < 1):
            raise ValueError(f"max_episode_steps={max_episode_steps!r} is not an integer >= 1 or None")
        self.max_episode_steps = max_episode_steps
        self.window = _check_window(window, max_episode_steps)
        self.factor_range = _check_factor_range(factor_range)
        self._model = None
        if kind == "action_flip":
            space = env.action_space
            if not (isinstance(space, gymnasium.spaces.Box) and len(space.shape) == 1):
                raise ValueError(f"switch kind='action_flip' needs a 1-D Box action space, got {space}")
            self._targets = (0, space.shape[0] - 1)
        else:
            model = getattr(env.unwrapped, "model", None)
            if model is None or not hasattr(model, "dof_damping"):
                raise ValueError(
                    f"switch kind={kind!r} needs a MuJoCo environment (env.unwrapped.model), "
                    f"got {type(env.unwrapped).__name__}"
                )
            self._model = model
            self._targets = {"actuator_gain": (0, model.nu - 1), "friction": None, "mass": (1, model.nbody - 1)}[kind]
            self._nominal = self._values().copy()
        self.target = self._check_target(target)
        self.noise_rng = self._generator(None)
        self.switch_step = self.window[1]
        self.switch_target = -1
        self.switch_factor = 1.0
        self.switched = False
        self.elapsed_steps = 0

    def _check_target(self, target: Any) -> int | None:
        """Return ``target``, or raise a one-line ``ValueError`` naming the accepted indices of this kind."""
        if target is None:
            return None
        if self._targets is None:
            raise ValueError(
                f"switch target={target!r} does not apply to kind={self.kind!r}, which scales every "
                "joint's damping; accepted: None"
            )
        what = {
            "actuator_gain": "an actuator",
            "action_flip": "an action dimension",
            "mass": "a body (0 is the world body)",
        }[self.kind]
        lo, hi = self._targets
        if not _is_int(target) or not lo <= target <= hi:
            raise ValueError(
                f"switch target={target!r} is not {what} of kind={self.kind!r}; accepted: an integer "
                f"in [{lo}, {hi}] or None (drawn at each reset)"
            )
        return int(target)

    def _generator(self, seed: int | None) -> np.random.Generator:
        # A child of the seed rather than the seed itself: the wrapped environment seeds its own generator with
        # the same integer, and the switch must not replay the environment's random numbers.
        return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(self._stream,)))

    def _values(self) -> np.ndarray:
        """The model array this kind changes (a view: writing to it changes the model)."""
        return {
            "actuator_gain": self._model.actuator_gear,
            "friction": self._model.dof_damping,
            "mass": self._model.body_mass,
        }[self.kind]

    def _restore(self) -> None:
        if self._model is not None:
            self._values()[:] = self._nominal

    def _switch(self) -> None:
        if self.kind == "friction":
            self._values()[:] = self._values() * self.switch_factor
        elif self.kind != "action_flip":  # a flip changes the actions, not the model
            values = self._values()
            values[self.switch_target] = values[self.switch_target] * self.switch_factor
        self.switched = True

    def _info(self, info: dict) -> dict:
        info.update(
            switch_step=self.switch_step,
            switch_kind=self.kind,
            switch_target=self.switch_target,
            switch_factor=self.switch_factor,
            switched=self.switched,
            elapsed_steps=self.elapsed_steps,
        )
        return info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        if seed is not None:  # unseeded resets continue the current stream, as the environment's own does
            self.noise_rng = self._generator(seed)
        self._restore()
        u = self.noise_rng.random(3)
        lo, hi = self.window
        self.switch_step = lo + min(int(u[0] * (hi - lo + 1)), hi - lo)
        if self._targets is None:
            self.switch_target = -1
        elif self.target is not None:
            self.switch_target = self.target
        else:
            first, last = self._targets
            self.switch_target = first + min(int(u[1] * (last - first + 1)), last - first)
        f_lo, f_hi = self.factor_range
        self.switch_factor = -1.0 if self.kind == "action_flip" else float(f_lo + u[2] * (f_hi - f_lo))
        self.switched = False
        self.elapsed_steps = 0
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, self._info(info)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        if not self.switched and self.elapsed_steps >= self.switch_step:
            self._switch()
        self.elapsed_steps += 1
        if self.switched and self.kind == "action_flip":
            action = np.array(action)  # a copy: the caller's action is left as it is
            action[self.switch_target] = -action[self.switch_target]
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._info(info)

    def close(self) -> None:
        self._restore()
        super().close()


def make_switch_env(
    env_id_or_env: str | gymnasium.Env,
    kind: str = "actuator_gain",
    window: Sequence[int] = (300, 700),
    factor_range: Sequence[float] = (0.2, 0.5),
    target: int | None = None,
    **make_kwargs: Any,
) -> gymnasium.Env:
    """Make (or take) an environment and wrap it with :class:`DynamicsSwitch`.

    :param env_id_or_env: a registered id, made with ``gymnasium.make(id, **make_kwargs)``, or an environment.
    :param kind: ``kind`` of :class:`DynamicsSwitch`.
    :param window: ``window`` of :class:`DynamicsSwitch`, checked against the environment's time limit.
    :param factor_range: ``factor_range`` of :class:`DynamicsSwitch`.
    :param target: ``target`` of :class:`DynamicsSwitch` (None: drawn at each reset).
    :param make_kwargs: arguments of ``gymnasium.make`` (e.g. ``max_episode_steps``); only with an id.
    :return: the wrapped environment.
    """
    _check_kind(kind)
    _check_factor_range(factor_range)
    env = env_from(env_id_or_env, make_kwargs)
    return DynamicsSwitch(env, kind=kind, window=window, factor_range=factor_range, target=target)


def make_switch_base_env(
    base_id: str,
    kind: str = "actuator_gain",
    window: Sequence[int] = (300, 700),
    factor_range: Sequence[float] = (0.2, 0.5),
    target: int | None = None,
    **env_kwargs: Any,
) -> gymnasium.Env:
    """Registration entry point of the switch ids: ``base_id``'s bare environment class, wrapped.

    The bare class is built from ``base_id``'s registered entry point, without ``gymnasium.make``'s wrappers, so
    that ``gymnasium.make`` of the switch id adds one env checker, order enforcer and time limit around the whole
    stack, and ``env.spec`` can recreate it. ``window`` is checked against ``base_id``'s registered time limit: a
    ``max_episode_steps`` given to ``gymnasium.make`` is applied outside the wrapper, which cannot see it.

    :param base_id: the registered id of the environment to change, e.g. ``"HalfCheetah-v5"``.
    :param kind: ``kind`` of :class:`DynamicsSwitch`.
    :param window: ``window`` of :class:`DynamicsSwitch`.
    :param factor_range: ``factor_range`` of :class:`DynamicsSwitch`.
    :param target: ``target`` of :class:`DynamicsSwitch` (None: drawn at each reset).
    :param env_kwargs: constructor arguments of the base environment (they override its registered kwargs).
    :return: the wrapped environment.
    """
    spec = gymnasium.spec(base_id)
    env = load_env_creator(spec.entry_point)(**{**spec.kwargs, **env_kwargs})
    return DynamicsSwitch(
        env,
        kind=kind,
        window=window,
        factor_range=factor_range,
        target=target,
        max_episode_steps=spec.max_episode_steps,
    )
