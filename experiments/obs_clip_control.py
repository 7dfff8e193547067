"""Control for the observation-noise result of the HalfCheetah protocol: is the spiking networks' edge their input
clipping?

The spiking entry standardises the observation (``VecNormalize``, clipped at 10) and its place-cell encoder then
clips every standardised value to ``obs_bounds`` = [-3, 3]; the MLP and RecurrentPPO baselines read the
standardised value up to the ``VecNormalize`` clip of 10. This script evaluates the baselines of
``experiments/halfcheetah_grid.py`` under observation noise again, on the same episode seeds, with their frozen
``VecNormalize`` statistics clipping at the encoder's bound instead: the same input clipping as the spiking
networks, nothing else changed (no retraining). If the clipped baselines keep their return under observation
noise, the spiking networks' robustness to it is the clipping, not the spikes.

Writes ``<out>/obs_clip/robustness/<model>/`` (the per-episode returns) and
``<out>/obs_clip/table.md``: per baseline group the area under the ratio curve and the return at the largest sigma,
with and without the clip, and the paired difference (clipped minus as trained), two-stage bootstrap intervals
over seeds and episodes (:mod:`sb3_spikeplastic.intervals`).

Usage: ``python experiments/obs_clip_control.py --budget 300000`` (after the grid's robustness evaluations).
"""

from __future__ import annotations

import argparse
import inspect
import tempfile
from pathlib import Path

import gymnasium
import numpy as np
import torch
from fig4_table import auc, fmt, group_of, read_episodes
from halfcheetah_grid import BASELINES, ENV, HELDOUT_SEED, add_control_arguments, control_models, write_control_table

from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_spikeplastic.envs import route_mujoco_warnings
from sb3_spikeplastic.intervals import bootstrap_interval
from sb3_spikeplastic.policy import SpikePlasticPolicy
from sb3_spikeplastic.robustness import evaluate_robustness, parse_models, write_episodes_csv
from sb3_spikeplastic.run_folder import load_model

#: The spiking encoder's upper bound for standardised observations (``SpikePlasticPolicy``'s default ``obs_bounds``,
#: which the HalfCheetah entry keeps).
ENCODER_BOUND = float(inspect.signature(SpikePlasticPolicy).parameters["obs_bounds"].default[1])
NOISE = "obs"


def clipped_statistics(source: Path, target: Path, clip: float) -> Path:
    """A copy of the ``VecNormalize`` pickle ``source`` whose observations are clipped at ``clip``."""
    stats = VecNormalize.load(str(source), DummyVecEnv([lambda: gymnasium.make(ENV)]))
    stats.clip_obs = clip
    target.parent.mkdir(parents=True, exist_ok=True)
    stats.save(str(target))
    stats.close()
    return target


def evaluate(name: str, model_path: Path, args: argparse.Namespace) -> None:
    info = parse_models([f"{name}={model_path}"])[name]
    if info.vecnormalize is None:
        raise ValueError(f"{name}: no VecNormalize statistics beside {model_path}; nothing to clip")
    with tempfile.TemporaryDirectory() as tmp:
        stats = clipped_statistics(Path(info.vecnormalize), Path(tmp) / "vecnormalize.pkl", args.clip)
        rows = evaluate_robustness({name: load_model(info)}, ENV, NOISE, args.sigmas, n_episodes=args.episodes,
                                   seed=HELDOUT_SEED, vec_normalize_stats={name: stats}, progress_bar=False,
                                   n_envs=args.n_envs)
    write_episodes_csv(rows, args.out / "obs_clip" / "robustness" / name / f"robustness_{ENV}_{NOISE}_episodes.csv")


def mean_return(seeds) -> float:
    return float(np.mean([episodes.mean() for episodes in seeds]))


def table(args: argparse.Namespace) -> str:
    clipped = read_episodes(args.out / "obs_clip")
    trained = read_episodes(args.out)
    lines = [f"# Observation noise, baselines with the encoder's input clip (|z| <= {args.clip:g}) and as trained",
             "", f"{args.episodes} episodes per point, the protocol's episode seeds; 95 % two-stage bootstrap "
             "intervals over seeds and episodes; the difference is paired (same model, same episodes).", "",
             "| group | seeds | R0 as trained | R0 clipped | AUC as trained | AUC clipped | clipped − as trained "
             "| return at σ max, as trained | clipped |", "|---|---|---|---|---|---|---|---|---|"]
    for group in dict.fromkeys(group_of(m) for m in sorted(clipped)):
        names = [m for m in sorted(clipped) if group_of(m) == group and NOISE in trained.get(m, {})]
        sigmas = clipped[names[0]][NOISE][0]
        pairs = [np.stack([trained[m][NOISE][1], clipped[m][NOISE][1]]) for m in names]
        measure = auc(sigmas)
        as_trained = bootstrap_interval([p[0] for p in pairs], measure)
        with_clip = bootstrap_interval([p[1] for p in pairs], measure)
        difference = bootstrap_interval(pairs, lambda s: measure([d[1] for d in s]) - measure([d[0] for d in s]))
        returns = [fmt(bootstrap_interval([p[k, j] for p in pairs], mean_return)) for j in (0, -1) for k in (0, 1)]
        lines.append(f"| {group} | {len(names)} | {returns[0]} | {returns[1]} | {fmt(as_trained, 2)} "
                     f"| {fmt(with_clip, 2)} | {fmt(difference, 2)} | {returns[2]} | {returns[3]} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=list(BASELINES), choices=BASELINES)
    parser.add_argument("--clip", type=float, default=ENCODER_BOUND, help="bound of the standardised observations")
    add_control_arguments(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    route_mujoco_warnings()  # HalfCheetah's settotalmass deprecation, once per environment otherwise
    for name, model in control_models(args):
        if (args.out / "obs_clip" / "robustness" / name / f"robustness_{ENV}_{NOISE}_episodes.csv").exists():
            continue
        print(f"{name}: {model}", flush=True)
        evaluate(name, model, args)
    write_control_table(args.out / "obs_clip", table(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
