"""Control for the observation-noise result of the HalfCheetah protocol: which observation elements carry the loss?

Under observation noise on all 17 elements the baselines lose most of their return at sigma 0.1 where the spiking
networks lose little. The same sigma is a different perturbation for different elements: the 8 positions (root
height and angle, 6 joint angles) vary over a few tenths, the 9 velocities over units, so in standardised units the
noise is large on the positions (most of all on the root's height, s.d. ~0.14) and small on the velocities. This
script evaluates the grid's models again with the noise on one group of elements at a time
(``ObservationNoise(indices=...)``, which draws the same noise as the all-element evaluation for the elements it
perturbs), same episode seeds, no retraining.

Writes ``<out>/obs_groups/<elements>/robustness/<model>/`` (the per-episode returns) and
``<out>/obs_groups/table.md``: per group of models the ratio of the return at the largest sigma to R0 with the
noise on every element (from the grid) and on each group of elements, two-stage bootstrap intervals over seeds and
episodes (:mod:`sb3_spikeplastic.intervals`).

Usage: ``python experiments/obs_group_control.py`` (after the grid's robustness evaluations).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from fig4_table import fmt, group_of, r0, ratio_at, read_episodes
from halfcheetah_grid import ENV, HELDOUT_SEED, VARIANTS, add_control_arguments, control_models, write_control_table

from sb3_spikeplastic.envs import route_mujoco_warnings
from sb3_spikeplastic.intervals import bootstrap_interval
from sb3_spikeplastic.robustness import evaluate_robustness, parse_models, write_episodes_csv
from sb3_spikeplastic.run_folder import load_model

#: HalfCheetah-v5's observation: the root's height, its angle and the 6 joint angles, then the 9 velocities.
ELEMENTS = {"height": (0,), "angles": tuple(range(1, 8)), "velocities": tuple(range(8, 17))}
NOISE = "obs"


def episodes_path(args: argparse.Namespace, elements: str, name: str):
    return args.out / "obs_groups" / elements / "robustness" / name / f"robustness_{ENV}_{NOISE}_episodes.csv"


def evaluate(name: str, model_path, elements: str, args: argparse.Namespace) -> None:
    info = parse_models([f"{name}={model_path}"])[name]
    rows = evaluate_robustness({name: load_model(info)}, ENV, NOISE, args.sigmas, n_episodes=args.episodes,
                               seed=HELDOUT_SEED, vec_normalize_stats={name: info.vecnormalize}, progress_bar=False,
                               n_envs=args.n_envs, obs_indices=ELEMENTS[elements])
    write_episodes_csv(rows, episodes_path(args, elements, name))


def table(args: argparse.Namespace) -> str:
    every = read_episodes(args.out)
    groups = {elements: read_episodes(args.out / "obs_groups" / elements) for elements in ELEMENTS}
    sigma = max(args.sigmas)
    lines = [f"# Observation noise σ {sigma:g} on some elements: return relative to R0", "",
             f"{args.episodes} episodes per point, the protocol's episode seeds; 95 % two-stage bootstrap intervals "
             "over seeds and episodes. The noise on every element (the protocol's evaluation) or only on "
             + "; ".join(f"{elements} ({', '.join(map(str, ELEMENTS[elements]))})" for elements in ELEMENTS) + ".",
             "", "| group | seeds | R0 | every element | " + " | ".join(f"{e} only" for e in ELEMENTS) + " |",
             "|---|---|---|---|" + "---|" * len(ELEMENTS)]
    models = sorted(set.intersection(*(set(g) for g in groups.values())))
    for group in dict.fromkeys(group_of(m) for m in models):
        names = [m for m in models if group_of(m) == group and NOISE in every.get(m, {})]
        if not names:
            continue
        cells = []
        sigmas, _ = every[names[0]][NOISE]
        j = int(np.flatnonzero(np.isclose(sigmas, sigma))[0])
        cells.append(fmt(bootstrap_interval([every[m][NOISE][1] for m in names], ratio_at(j)), 2))
        for elements in ELEMENTS:
            data = [groups[elements][m][NOISE] for m in names]
            k = int(np.flatnonzero(np.isclose(data[0][0], sigma))[0])
            cells.append(fmt(bootstrap_interval([d[1] for d in data], ratio_at(k)), 2))
        start = np.mean([r0(every[m][NOISE][1]) for m in names])
        lines.append(f"| {group} | {len(names)} | {start:.0f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS,
                        default=["static", "dp-oja", "mlp", "mlp_zoo", "ppo_lstm", "ppo_lstm_zoo"])
    add_control_arguments(parser)
    parser.set_defaults(sigmas=[0.0, 0.1])  # where the baselines have already lost most of their return
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    route_mujoco_warnings()  # HalfCheetah's settotalmass deprecation, once per environment otherwise
    for name, model in control_models(args):
        for elements in ELEMENTS:
            if episodes_path(args, elements, name).exists():
                continue
            print(f"{name}, noise on the {elements}: {model}", flush=True)
            evaluate(name, model, elements, args)
    write_control_table(args.out / "obs_groups", table(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
