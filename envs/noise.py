"""Observation, action and joint-friction noise for MuJoCo locomotion (paper §3.2, Fig. 4 F-H).

Three composable wrappers, each drawing from its own random generator (reseeded by ``reset(seed=...)``, so a
seeded run is reproducible and the wrapped environment's own random stream is untouched), and each an exact
no-op at ``sigma = 0``: no noise is drawn and nothing is changed, so trajectories are bit-identical to the bare
environment's. :func:`make_noisy_env` stacks them; :func:`noise_kwargs` maps a noise type and a ``sigma`` to its
arguments, which is how the robustness protocol sweeps one noise type at a time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium.envs.registration import load_env_creator
from gymnasium.utils import RecordConstructorArgs

#: Noise types accepted by :func:`noise_kwargs` (and the robustness protocol).
NOISE_TYPES = ("obs", "action", "friction")
#: Model parameters :class:`FrictionNoise` can perturb.
FRICTION_TARGETS = ("damping", "geom_friction")


def _check_sigma(name: str, sigma: Any) -> float:
    """Return ``sigma`` as a float, or raise a one-line ``ValueError`` unless it is finite and >= 0."""
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}={sigma!r} must be a finite number >= 0")
    if not math.isfinite(sigma) or sigma < 0:
        raise ValueError(f"{name}={sigma!r} must be a finite number >= 0")
    return float(sigma)


def _check_target(target: Any) -> str:
    """Return ``target``, or raise a one-line ``ValueError`` unless it is one of :data:`FRICTION_TARGETS`."""
    if target not in FRICTION_TARGETS:
        raise ValueError(f"friction target={target!r} is not one of {FRICTION_TARGETS}")
    return target


def _check_indices(indices: Any, shape: tuple[int, ...]) -> tuple[int, ...]:
    """Return ``indices`` as a sorted tuple, or raise a one-line ``ValueError`` unless they are distinct integers
    indexing a 1-D observation of ``shape``."""
    if len(shape) != 1:
        raise ValueError(f"obs indices={indices!r} need a 1-D observation, got shape {shape}")
    accepted = f"distinct integers in [0, {shape[0] - 1}]"
    if isinstance(indices, (str, bytes)) or not isinstance(indices, Sequence) or not indices:
        raise ValueError(f"obs indices={indices!r} must be a non-empty list of {accepted}")
    for i in indices:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < shape[0]:
            raise ValueError(f"obs index {i!r} in {list(indices)!r} is not one of {accepted}")
    if len(set(indices)) != len(indices):
        raise ValueError(f"obs indices={list(indices)!r} repeat an index; accepted: {accepted}")
    return tuple(sorted(int(i) for i in indices))


class _NoiseWrapper(gymnasium.Wrapper):
    """Base of the noise wrappers: ``sigma`` and a private generator reseeded by ``reset(seed=...)``."""

    #: Distinguishes the wrappers' generators, so that stacked wrappers seeded alike draw independent noise.
    _stream: int

    def __init__(self, env: gymnasium.Env, sigma: float) -> None:
        super().__init__(env)
        self.sigma = _check_sigma("sigma", sigma)
        self.noise_rng = self._generator(None)

    def _generator(self, seed: int | None) -> np.random.Generator:
        # A child of the seed rather than the seed itself: the wrapped environment seeds its own generator with
        # the same integer, and the noise must not replay the environment's random numbers.
        return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(self._stream,)))

    def _reseed(self, seed: int | None) -> None:
        # Unseeded resets continue the current stream, as the environment's own generator does.
        if seed is not None:
            self.noise_rng = self._generator(seed)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        self._reseed(seed)
        return self.env.reset(seed=seed, options=options)


class ObservationNoise(_NoiseWrapper, RecordConstructorArgs):
    """Additive Gaussian observation noise ``x + z``, ``z ~ N(0, sigma^2)`` per element, at reset and every step.

    The noise is added to the raw observation, before any normalisation or spike encoding by the policy, and the
    observation's float dtype is kept. The result may leave a bounded observation space (HalfCheetah's is
    unbounded).

    :param env: environment with a floating-point ``Box`` observation space.
    :param sigma: standard deviation of ``z``; 0 is an exact no-op.
    :param indices: perturb only these elements of a 1-D observation (e.g. the 12 the paper's HalfCheetah network
        encodes); None perturbs every element. ``z`` is drawn for every element and zeroed elsewhere, so the
        perturbed elements get the same draws as with ``indices=None``: evaluations of disjoint groups are paired
        with the all-element one.
    """

    _stream = 1

    def __init__(self, env: gymnasium.Env, sigma: float, indices: Sequence[int] | None = None) -> None:
        RecordConstructorArgs.__init__(self, sigma=sigma, indices=indices)
        super().__init__(env, sigma)
        space = env.observation_space
        if not (isinstance(space, gymnasium.spaces.Box) and np.issubdtype(space.dtype, np.floating)):
            raise ValueError(f"ObservationNoise needs a floating-point Box observation space, got {space}")
        self.indices = None if indices is None else _check_indices(indices, space.shape)
        self._mask = None
        if self.indices is not None:
            self._mask = np.zeros(space.shape)
            self._mask[list(self.indices)] = 1.0

    def _perturb(self, obs: np.ndarray) -> np.ndarray:
        if self.sigma == 0.0:
            return obs
        z = self.noise_rng.normal(0.0, self.sigma, size=np.shape(obs))
        if self._mask is not None:
            z = z * self._mask
        return (obs + z).astype(np.asarray(obs).dtype, copy=False)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        obs, info = super().reset(seed=seed, options=options)
        return self._perturb(obs), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._perturb(obs), reward, terminated, truncated, info


class ActionNoise(_NoiseWrapper, RecordConstructorArgs):
    """Multiplicative Gaussian action noise ``a * (1 + z)``, ``z ~ N(0, sigma^2)`` per action dimension and step.

    The perturbed action is not clipped (the paper does not clip): MuJoCo clamps the control to the actuators'
    ``ctrlrange``, while HalfCheetah's control cost is computed from the perturbed action. Its dtype is kept.

    :param env: environment with a ``Box`` action space.
    :param sigma: standard deviation of ``z``; 0 is an exact no-op.
    """

    _stream = 2

    def __init__(self, env: gymnasium.Env, sigma: float) -> None:
        RecordConstructorArgs.__init__(self, sigma=sigma)
        super().__init__(env, sigma)
        if not isinstance(env.action_space, gymnasium.spaces.Box):
            raise ValueError(f"ActionNoise needs a Box action space, got {env.action_space}")

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        if self.sigma != 0.0:
            action = np.asarray(action)
            z = self.noise_rng.normal(0.0, self.sigma, size=action.shape)
            action = (action * (1.0 + z)).astype(action.dtype, copy=False)
        return self.env.step(action)


class FrictionNoise(_NoiseWrapper, RecordConstructorArgs):
    """Joint-friction noise: per episode, the model's friction parameters ``f`` become ``f_nominal * (1 + z)``.

    ``z ~ N(0, sigma^2)`` is drawn once at every ``reset`` and held for the episode. The nominal values are copied
    once, at construction, and every episode scales them afresh, so perturbations never compound across episodes;
    ``close()`` restores them. The applied factors ``max(1 + z, 0)`` are in ``info["friction_factors"]`` at reset
    and at every step: they are clipped at 0 because a negative damping or friction coefficient is unphysical and
    makes the simulation diverge.

    Targets:

    * ``"damping"`` (default): ``dof_damping`` of the degrees of freedom of the joints that actuators drive, one
      factor per degree of freedom (6 for HalfCheetah). This is the viscous joint friction. MuJoCo's dry joint
      friction, ``dof_frictionloss``, is 0 in HalfCheetah, so scaling it would change nothing.
    * ``"geom_friction"``: the contact friction ``geom_friction`` of every geom, one factor per geom applied to
      its sliding, torsional and rolling coefficients alike.

    :param env: a MuJoCo environment (``env.unwrapped.model`` is its ``mujoco.MjModel``).
    :param sigma: standard deviation of ``z``; 0 is an exact no-op (the model is never written).
    :param target: ``"damping"`` or ``"geom_friction"``.
    """

    _stream = 3

    def __init__(self, env: gymnasium.Env, sigma: float, target: str = "damping") -> None:
        RecordConstructorArgs.__init__(self, sigma=sigma, target=target)
        super().__init__(env, sigma)
        self.target = _check_target(target)
        model = getattr(env.unwrapped, "model", None)
        if model is None or not hasattr(model, "dof_damping"):
            raise ValueError(
                f"FrictionNoise needs a MuJoCo environment (env.unwrapped.model), got {type(env.unwrapped).__name__}"
            )
        self._model = model
        if self.target == "damping":
            self._dofs = self._actuated_dofs(model)
            self._nominal = model.dof_damping[self._dofs].copy()
        else:
            self._nominal = model.geom_friction.copy()
        self.factors = np.ones(len(self._nominal))

    @staticmethod
    def _actuated_dofs(model: Any) -> np.ndarray:
        """Degrees of freedom of the joints driven by joint-transmission actuators, in actuator order."""
        import mujoco  # only this wrapper needs MuJoCo itself

        # Compared as ints: MuJoCo's pybind enums do not compare equal to numpy integers from the model's arrays.
        joint_transmissions = {int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)}
        joints = [
            int(j) for t, j in zip(model.actuator_trntype, model.actuator_trnid[:, 0]) if int(t) in joint_transmissions
        ]
        if not joints:
            raise ValueError("FrictionNoise target='damping' needs actuators that drive joints; the model has none")
        return np.concatenate([np.flatnonzero(model.dof_jntid == j) for j in dict.fromkeys(joints)])

    def _apply(self, factors: np.ndarray) -> None:
        if self.target == "damping":
            self._model.dof_damping[self._dofs] = self._nominal * factors
        else:
            self._model.geom_friction[:] = self._nominal * factors[:, None]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        self._reseed(seed)
        if self.sigma != 0.0:
            z = self.noise_rng.normal(0.0, self.sigma, size=len(self._nominal))
            self.factors = np.maximum(1.0 + z, 0.0)
            self._apply(self.factors)
        obs, info = self.env.reset(seed=seed, options=options)
        info["friction_factors"] = self.factors.copy()
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["friction_factors"] = self.factors.copy()
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        if self.sigma != 0.0:
            self._apply(np.ones(len(self._nominal)))
        super().close()


def noise_kwargs(
    noise_type: str, sigma: float, friction_target: str = "damping", obs_indices: Sequence[int] | None = None
) -> dict[str, Any]:
    """Arguments of :func:`make_noisy_env` that apply one noise type with standard deviation ``sigma``.

    :param noise_type: one of :data:`NOISE_TYPES`.
    :param sigma: standard deviation of the noise.
    :param friction_target: the friction parameters perturbed by ``"friction"`` noise.
    :param obs_indices: the observation elements perturbed by ``"obs"`` noise (None: all).
    :return: e.g. ``{"action_noise": 0.1}``.
    """
    if noise_type not in NOISE_TYPES:
        raise ValueError(f"noise type {noise_type!r} is not one of {NOISE_TYPES}")
    kwargs: dict[str, Any] = {f"{noise_type}_noise": _check_sigma(f"{noise_type}_noise", sigma)}
    if noise_type == "friction":
        kwargs["friction_target"] = _check_target(friction_target)
    if obs_indices is not None:
        if noise_type != "obs":
            raise ValueError(f"obs_indices={obs_indices!r} apply to noise type 'obs' only, not {noise_type!r}")
        kwargs["obs_indices"] = obs_indices
    return kwargs


def env_from(env_id_or_env, make_kwargs: dict) -> gymnasium.Env:
    """``gymnasium.make(id, **make_kwargs)`` for an id, the environment itself for an instance (which takes no
    ``make_kwargs``): what the ``make_*_env`` helpers wrap."""
    if isinstance(env_id_or_env, str):
        return gymnasium.make(env_id_or_env, **make_kwargs)
    if make_kwargs:
        raise ValueError(f"make_kwargs {sorted(make_kwargs)} need an environment id, not an environment instance")
    return env_id_or_env


def make_noisy_env(
    env_id_or_env: str | gymnasium.Env,
    obs_noise: float = 0.0,
    action_noise: float = 0.0,
    friction_noise: float = 0.0,
    friction_target: str = "damping",
    obs_indices: Sequence[int] | None = None,
    **make_kwargs: Any,
) -> gymnasium.Env:
    """Make (or take) an environment and wrap it with the noises whose ``sigma`` is non-zero.

    Friction noise is innermost, then action noise, then observation noise.

    :param env_id_or_env: a registered id, made with ``gymnasium.make(id, **make_kwargs)``, or an environment.
    :param obs_noise: ``sigma`` of :class:`ObservationNoise`.
    :param action_noise: ``sigma`` of :class:`ActionNoise`.
    :param friction_noise: ``sigma`` of :class:`FrictionNoise`.
    :param friction_target: ``target`` of :class:`FrictionNoise`.
    :param obs_indices: ``indices`` of :class:`ObservationNoise` (None: every element).
    :param make_kwargs: arguments of ``gymnasium.make`` (e.g. ``max_episode_steps``); only with an id.
    :return: the wrapped environment.
    """
    obs_noise = _check_sigma("obs_noise", obs_noise)
    action_noise = _check_sigma("action_noise", action_noise)
    friction_noise = _check_sigma("friction_noise", friction_noise)
    _check_target(friction_target)
    env = env_from(env_id_or_env, make_kwargs)
    if friction_noise:
        env = FrictionNoise(env, friction_noise, target=friction_target)
    if action_noise:
        env = ActionNoise(env, action_noise)
    if obs_noise:
        env = ObservationNoise(env, obs_noise, indices=obs_indices)
    return env


def make_noisy_base_env(
    base_id: str,
    obs_noise: float = 0.0,
    action_noise: float = 0.0,
    friction_noise: float = 0.0,
    friction_target: str = "damping",
    obs_indices: Sequence[int] | None = None,
    **env_kwargs: Any,
) -> gymnasium.Env:
    """Registration entry point of the noisy ids: ``base_id``'s bare environment class, wrapped with noise.

    The bare class is built from ``base_id``'s registered entry point, without ``gymnasium.make``'s wrappers, so
    that ``gymnasium.make`` of the noisy id adds one env checker, order enforcer and time limit around the whole
    stack, and ``env.spec`` can recreate it.

    :param base_id: the registered id of the environment to perturb, e.g. ``"HalfCheetah-v5"``.
    :param obs_noise: ``sigma`` of :class:`ObservationNoise`.
    :param action_noise: ``sigma`` of :class:`ActionNoise`.
    :param friction_noise: ``sigma`` of :class:`FrictionNoise`.
    :param friction_target: ``target`` of :class:`FrictionNoise`.
    :param obs_indices: ``indices`` of :class:`ObservationNoise` (None: every element).
    :param env_kwargs: constructor arguments of the base environment (they override its registered kwargs).
    :return: the wrapped environment.
    """
    spec = gymnasium.spec(base_id)
    env = load_env_creator(spec.entry_point)(**{**spec.kwargs, **env_kwargs})
    return make_noisy_env(env, obs_noise, action_noise, friction_noise, friction_target, obs_indices)
