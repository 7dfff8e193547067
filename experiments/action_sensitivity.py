"""Why the baselines' return hangs on the root's height: how far one observation element moves each policy's action.

The observation-group control (``obs_group_control.py``) finds that noise on the root's height alone costs the
baselines what noise on all 17 elements does, and the spiking networks almost nothing. This script measures the
policies themselves: on each model's own noise-free episode (deterministic actions, the protocol's first episode
seed), every step's action is computed again with one raw observation element shifted by ``--shift`` (0.1, the
control's sigma) from the same recurrent state, through the run's frozen ``VecNormalize`` statistics. The
sensitivity of an element is the absolute change of the clipped action, averaged over the action's dimensions and
the episode's steps; a policy that ignores the element scores 0.

Writes ``<out>/sensitivity/sensitivity.csv`` (model, element, sensitivity; the height's standard deviation in the
model's observation statistics, which sets how large the shift is in the units the policy reads) and
``<out>/sensitivity/table.md`` (per group of models: the mean over seeds and its range).

Usage: ``python experiments/action_sensitivity.py`` (after the grid's training; ~3 core-minutes).
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np
import torch
from fig4_table import group_of
from halfcheetah_grid import ENV, HELDOUT_SEED, VARIANTS, add_control_arguments, control_models, write_control_table
from obs_group_control import ELEMENTS

from sb3_spikeplastic.envs import route_mujoco_warnings
from sb3_spikeplastic.robustness import parse_models
from sb3_spikeplastic.run_folder import load_model, make_eval_env

FIELDS = ("model", "element", "sensitivity", "height_sd")


def action_sensitivity(model, env, shift: float) -> np.ndarray:
    """Mean absolute change of the clipped action when each raw observation element alone is shifted by ``shift``,
    over one episode of ``env`` (a 1-environment ``VecNormalize`` with frozen statistics, or a plain ``VecEnv``)."""
    obs = env.reset()
    normalize = getattr(env, "normalize_obs", lambda o: o)
    low, high = env.action_space.low, env.action_space.high
    state, start, done = None, np.ones(1, dtype=bool), False
    total, steps = np.zeros(env.observation_space.shape[0]), 0
    while not done:
        raw = env.get_original_obs() if hasattr(env, "get_original_obs") else obs
        action, new_state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        action = np.clip(action, low, high)
        for i in range(total.size):
            shifted = raw.copy()
            shifted[:, i] += shift
            moved, _ = model.predict(normalize(shifted), state=state, episode_start=start, deterministic=True)
            total[i] += np.abs(np.clip(moved, low, high) - action).mean()
        obs, _, dones, _ = env.step(action)
        state, start, done, steps = new_state, np.zeros(1, dtype=bool), bool(dones[0]), steps + 1
    return total / steps


def measure(name: str, model_path, shift: float) -> list[dict]:
    info = parse_models([f"{name}={model_path}"])[name]
    env = make_eval_env(ENV, 1, HELDOUT_SEED, vecnormalize=info.vecnormalize)
    sensitivity = action_sensitivity(load_model(info), env, shift)
    height_sd = float(np.sqrt(env.obs_rms.var[0])) if hasattr(env, "obs_rms") else float("nan")
    env.close()
    return [dict(model=name, element=i, sensitivity=f"{s:.6g}", height_sd=f"{height_sd:.6g}")
            for i, s in enumerate(sensitivity)]


def read(path) -> dict[str, tuple[np.ndarray, float]]:
    """model -> (sensitivity per element, the height's standard deviation)."""
    rows = defaultdict(list)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rows[row["model"]].append(row)
    return {m: (np.array([float(r["sensitivity"]) for r in sorted(rs, key=lambda r: int(r["element"]))]),
                float(rs[0]["height_sd"])) for m, rs in rows.items()}


def table(data: dict[str, tuple[np.ndarray, float]], shift: float) -> str:
    def cell(values, digits: int = 3) -> str:
        return f"{np.mean(values):.{digits}f} ({np.min(values):.{digits}f}-{np.max(values):.{digits}f})"

    lines = [f"# Action change per step for a {shift:g} shift of one observation element", "",
             "Mean absolute change of the clipped action (averaged over its dimensions and one noise-free episode, "
             "the protocol's first episode seed); mean over seeds (range). The angles' and velocities' columns "
             "average their elements; the last column is the height's standard deviation in the model's "
             "observation statistics.", "",
             "| group | seeds | " + " | ".join(ELEMENTS) + " | height / angles | s.d. of height |",
             "|---|---|" + "---|" * (len(ELEMENTS) + 2)]
    for group in dict.fromkeys(group_of(m) for m in data):
        names = [m for m in data if group_of(m) == group]
        per_group = {e: [data[m][0][list(idx)].mean() for m in names] for e, idx in ELEMENTS.items()}
        ratios = [a / b for a, b in zip(per_group["height"], per_group["angles"])]
        lines.append(f"| {group} | {len(names)} | " + " | ".join(cell(v) for v in per_group.values())
                     + f" | {cell(ratios, 1)} | {cell([data[m][1] for m in names])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS,
                        default=["static", "dp-oja", "mlp", "mlp_zoo", "ppo_lstm", "ppo_lstm_zoo"])
    parser.add_argument("--shift", type=float, default=0.1, help="the shift of one raw observation element")
    add_control_arguments(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    route_mujoco_warnings()
    rows = []
    for name, model in control_models(args):
        print(f"{name}: {model}", flush=True)
        rows += measure(name, model, args.shift)
    folder = args.out / "sensitivity"
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "sensitivity.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    write_control_table(folder, table(read(folder / "sensitivity.csv"), args.shift))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
