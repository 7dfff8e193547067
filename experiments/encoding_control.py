"""Controls for the observation-noise result of the HalfCheetah protocol: is the spiking networks' edge their
place-cell input code, or the randomness of their input spikes?

Under observation noise every spiking network keeps far more of its return than the MlpPolicy, and clipping the
MLP's input to the encoder's range does not change that (``experiments/obs_clip_control.py``). What remains
between the two is the input code (17 standardised values against 17 x 10 broad place cells), the spikes and the
network. This script trains the MlpPolicy of the ``mlp`` baseline (the spiking entry's PPO settings, the same
``VecNormalize``) with one change, its input, and evaluates it under every noise type with the protocol of
``experiments/halfcheetah_grid.py`` (100 episodes per point, the same episode seeds):

* ``--input rates`` (``mlp+encoder``): the spiking encoder's place-cell firing probabilities
  (:meth:`sb3_spikeplastic.coding.PopulationEncoder.probabilities` with the policy's default ``encoder_pop_size``,
  ``encoder_beta``, ``encoder_p_min`` and ``obs_bounds``), no spikes: the code alone.
* ``--input spikes`` (``mlp+spikes``): the spike counts of those cells over the policy's default ``steps``
  (Bernoulli spikes, each cell's count over T steps divided by T), drawn from keys hashed from the observation
  so that PPO's update sees the spikes its rollout saw (the spiking policy replays them the same way, from keys
  it stores): the code and its sampling noise, which the MLP now trains with.

If an input keeps the MLP's return under observation noise as the spiking networks keep theirs, it explains
their edge; if the MLP loses as the plain one does, the spiking network itself does.

Writes ``<out>/encoding/robustness/<variant>@<budget>_s<seed>/`` (per-episode returns, the grid's format), the
models under ``<out>/encoding/runs/`` and ``<out>/encoding/table.md``: per noise type the R0, the AUC of the ratio
curve and the return at the largest sigma of each MLP input and of the static SNN of the same budget, and each
one's difference from the plain MLP (two-stage bootstrap intervals over seeds and episodes,
:mod:`sb3_spikeplastic.intervals`).

Usage: ``python experiments/encoding_control.py --input rates spikes`` (after the grid's robustness evaluations of
``mlp`` and ``static`` at 300k steps).
"""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

import gymnasium
import numpy as np
import torch
from fig4_table import group_of, read_episodes, summary_cells
from halfcheetah_grid import ENV, HELDOUT_SEED, NOISES, add_control_arguments, budget_label, write_control_table

from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecNormalize

from sb3_spikeplastic import config as cfg
from sb3_spikeplastic.coding import PopulationEncoder, hash32
from sb3_spikeplastic.envs import route_mujoco_warnings
from sb3_spikeplastic.experiment import make_train_env
from sb3_spikeplastic.policy import VECTOR_STEPS, SpikePlasticPolicy
from sb3_spikeplastic.robustness import evaluate_robustness, write_episodes_csv

#: The spiking policy's encoder defaults, which the HalfCheetah entry keeps.
ENCODER = {k: v.default for k, v in inspect.signature(SpikePlasticPolicy).parameters.items()
           if k in ("encoder_pop_size", "encoder_beta", "encoder_p_min", "obs_bounds")}
#: ``--input`` -> the variant's name.
VARIANTS = {"rates": "mlp+encoder", "spikes": "mlp+spikes"}


class PlaceCellFeatures(BaseFeaturesExtractor):
    """The spiking encoder's place-cell firing probabilities as an MLP's input: every observation dimension is
    clipped to ``obs_bounds`` and read by ``pop_size`` Gaussian cells, :math:`p = \\mathrm{clip}(e^{-\\beta(\\Omega -
    x)^2}, p_{min}, 1)` (SpikePropamine appendix 5.2), without sampling spikes."""

    def __init__(self, observation_space: gymnasium.spaces.Box, pop_size: int, beta: float, p_min: float,
                 obs_bounds: tuple):
        n = int(np.prod(observation_space.shape))
        super().__init__(observation_space, features_dim=n * pop_size)
        self.encoder = PopulationEncoder(np.full(n, obs_bounds[0]), np.full(n, obs_bounds[1]), pop_size, beta, p_min)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.encoder.probabilities(observations.flatten(1))


class SpikeCountFeatures(PlaceCellFeatures):
    """The place cells' spike counts over ``steps`` network steps, divided by ``steps``: Bernoulli spikes with the
    cells' probabilities, from the encoder's counter-based sampler keyed by a hash of the observation's bits (the
    same observation always draws the same spikes, so PPO's update re-evaluates the rollout's inputs)."""

    def __init__(self, observation_space: gymnasium.spaces.Box, pop_size: int, beta: float, p_min: float,
                 obs_bounds: tuple, steps: int):
        super().__init__(observation_space, pop_size, beta, p_min, obs_bounds)
        self.steps = int(steps)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        obs = observations.flatten(1).to(torch.float32).contiguous()
        keys = torch.zeros(obs.shape[0], dtype=torch.int32, device=obs.device)
        for bits in obs.view(torch.int32).unbind(1):
            keys = hash32(keys ^ bits)
        return self.encoder(obs, keys, self.steps).mean(1)


def features_extractor(input_kind: str) -> tuple[type, dict]:
    """The features extractor of ``--input`` and its arguments, from the spiking policy's defaults."""
    kwargs = dict(pop_size=ENCODER["encoder_pop_size"], beta=ENCODER["encoder_beta"], p_min=ENCODER["encoder_p_min"],
                  obs_bounds=tuple(ENCODER["obs_bounds"]))
    if input_kind == "spikes":
        return SpikeCountFeatures, {**kwargs, "steps": VECTOR_STEPS}
    return PlaceCellFeatures, kwargs


def train(input_kind: str, seed: int, folder: Path, args: argparse.Namespace) -> tuple[Path, Path]:
    """The ``mlp`` entry's PPO with the input of ``input_kind``, trained for ``args.budget`` steps; its model and
    ``VecNormalize`` statistics (written last: a folder with both is complete)."""
    model_path, stats_path = folder / "model.zip", folder / "vecnormalize.pkl"
    if model_path.exists() and stats_path.exists():
        return model_path, stats_path
    config = cfg.resolve_hyperparams(ENV, "mlp", [], n_timesteps=args.budget)
    policy, ppo_kwargs, policy_kwargs = cfg.model_arguments(config)
    extractor, extractor_kwargs = features_extractor(input_kind)
    policy_kwargs = {**policy_kwargs, "features_extractor_class": extractor,
                     "features_extractor_kwargs": extractor_kwargs}
    venv = VecNormalize(make_train_env(ENV, config["n_envs"], {}), **cfg.normalize_arguments(config))
    algorithm = cfg.algorithm_class(config.get("algo", "ppo"))
    model = algorithm(policy, venv, **ppo_kwargs, policy_kwargs=policy_kwargs, seed=seed, verbose=0)
    model.learn(config["n_timesteps"])
    folder.mkdir(parents=True, exist_ok=True)
    model.save(str(model_path))
    venv.save(str(stats_path))
    venv.close()
    return model_path, stats_path


def evaluate(name: str, model_path: Path, stats_path: Path, args: argparse.Namespace) -> None:
    folder = args.out / "encoding" / "robustness" / name
    todo = [n for n in NOISES if not (folder / f"robustness_{ENV}_{n}_episodes.csv").exists()]
    model = cfg.algorithm_class("ppo").load(str(model_path), device="cpu") if todo else None
    for noise in todo:
        csv = folder / f"robustness_{ENV}_{noise}_episodes.csv"
        rows = evaluate_robustness({name: model}, ENV, noise, args.sigmas, n_episodes=args.episodes,
                                   seed=HELDOUT_SEED, vec_normalize_stats={name: stats_path}, progress_bar=False,
                                   n_envs=args.n_envs)
        write_episodes_csv(rows, csv)


def table(args: argparse.Namespace) -> str:
    budget = budget_label(args.budget)
    encoded = read_episodes(args.out / "encoding")
    grid = read_episodes(args.out)
    groups = {"mlp": grid, **{variant: encoded for variant in VARIANTS.values()}, "static": grid}

    def seeds(variant: str, noise: str) -> list[np.ndarray]:
        data = groups[variant]
        return [data[m][noise][1] for m in sorted(data) if group_of(m) == f"{variant}@{budget}" and noise in data[m]]

    lines = [f"# {ENV}: the MlpPolicy with the spiking encoder's input, beside the plain MlpPolicy and the static "
             f"SNN ({budget} steps)", "",
             "mlp+encoder: the place cells' firing probabilities; mlp+spikes: their spike counts over T steps. "
             f"{args.episodes} episodes per point, the protocol's episode seeds; 95 % two-stage bootstrap intervals "
             "over seeds and episodes. AUC: area under the ratio-to-R0 curve (1 = no loss).", "",
             "| noise | model | seeds | R0 | AUC | return at σ max | AUC − mlp | return at σ max − mlp |",
             "|---|---|---|---|---|---|---|---|"]
    for noise in NOISES:
        plain = seeds("mlp", noise)
        if not plain or not any(seeds(v, noise) for v in VARIANTS.values()):
            continue
        sigmas = next(grid[m][noise][0] for m in grid if noise in grid[m])
        for variant in groups:
            group = seeds(variant, noise)
            if not group:
                continue
            cells = summary_cells(group, sigmas, None if variant == "mlp" else plain)
            lines.append(f"| {noise} | {variant}@{budget} | {len(group)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--input", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                        help="the MLP's input: place-cell rates, spike counts or both")
    add_control_arguments(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    route_mujoco_warnings()
    for input_kind in args.input:
        for seed in args.seeds:
            name = f"{VARIANTS[input_kind]}@{budget_label(args.budget)}_s{seed}"
            print(name, flush=True)
            model_path, stats_path = train(input_kind, seed, args.out / "encoding" / "runs" / name, args)
            evaluate(name, model_path, stats_path, args)
    write_control_table(args.out / "encoding", table(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
