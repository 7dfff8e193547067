"""The robustness protocol of the paper's Fig. 4 F-H (Schmidgall et al. 2021, §3.2) as one definition: the noise
types, the sigma grid, the episodes per point, the held-out seed, the threshold below which a model did not learn,
and the area under the ratio curve.

Every model is evaluated on ``episodes`` deterministic episodes per (noise, sigma), all environments seeded from
``seed``, so every model and every sigma sees the same episode seeds and the comparison is paired; sigma = 0 is the
model's noise-free return R0. The ratio to R0 is :func:`sb3_spikeplastic.study.robustness.return_ratio`; the AUC is the
trapezoid area under the ratio curve divided by the sigma range (1: no loss at any sigma).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: The noise types of the Fig. 4 study: joint friction (viscous damping), action and observation.
NOISES = ("friction", "action", "obs")


@dataclass(frozen=True)
class Protocol:
    """How a trained model is evaluated under noise.

    :param noises: noise types (``friction``, ``action``, ``obs``)
    :param sigmas: noise standard deviations, starting with 0 (R0)
    :param episodes: deterministic episodes per (noise, sigma)
    :param seed: first environment seed: far from every training and training-evaluation seed (held out)
    :param n_envs: environments stepped side by side (one batched forward pass)
    :param learned_threshold: a model whose R0 is below this did not learn the task: listed apart, left out of
        every ratio and comparison (a ratio near 1 of a model that never moved says nothing about robustness)
    :param friction_target: ``damping`` (the joints' viscous damping) or ``geom_friction``
    :param obs_indices: observation noise on these elements only (``None``: all)
    """

    noises: tuple[str, ...] = NOISES
    sigmas: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4)
    episodes: int = 100
    seed: int = 1_000_000
    n_envs: int = 100
    learned_threshold: float = 1000.0
    friction_target: str = "damping"
    obs_indices: tuple[int, ...] | None = None

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


#: The protocol of every HalfCheetah result in ``docs/halfcheetah.md``.
FIG4 = Protocol()


def ratio_to_r0(means: np.ndarray) -> np.ndarray:
    r"""The return ratio of each sigma's mean return to the first's (R0), on the last axis:
    :math:`1 + (R_\sigma - R_0) / |R_0|` (see :func:`sb3_spikeplastic.study.robustness.return_ratio`)."""
    r0 = means[..., :1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r0 == 0, np.nan, 1.0 + (means - r0) / np.abs(r0))


def auc(ratios: np.ndarray, sigmas) -> np.ndarray:
    """Area under the ratio curve (last axis: sigma) divided by the sigma range: 1 = no loss at any sigma."""
    sigmas = np.asarray(sigmas, dtype=float)
    return np.trapezoid(ratios, sigmas, axis=-1) / (sigmas[-1] - sigmas[0])
