"""The observation-clip control of the HalfCheetah protocol: the clipped statistics change only the clip, and its
table pairs each model's clipped and as-trained episodes."""

import argparse

import gymnasium
import numpy as np
import pytest
from helpers import load_experiment
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_spikeplastic.robustness import RobustnessRow, write_episodes_csv

SIGMAS = (0.0, 0.2, 0.4)


@pytest.fixture(scope="module")
def control():
    return load_experiment("obs_clip_control")


def test_clipped_statistics_keep_the_standardisation_and_clip_at_the_bound(tmp_path, control):
    venv = VecNormalize(DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5")]))
    venv.obs_rms.mean = np.linspace(-1.0, 1.0, 17)
    venv.obs_rms.var = np.full(17, 4.0)
    venv.save(str(tmp_path / "trained.pkl"))
    target = control.clipped_statistics(tmp_path / "trained.pkl", tmp_path / "clipped.pkl", 3.0)
    clipped = VecNormalize.load(str(target), DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5")]))
    assert clipped.clip_obs == 3.0
    np.testing.assert_allclose(clipped.obs_rms.mean, venv.obs_rms.mean)
    obs = np.zeros((1, 17))
    obs[0, 0], obs[0, 1] = 100.0, 1.0  # (100 + 1) / 2 clipped to 3; (1 + 0.875) / 2 kept
    normalized = clipped.normalize_obs(obs)
    assert normalized[0, 0] == pytest.approx(3.0)
    assert normalized[0, 1] == pytest.approx((1.0 - venv.obs_rms.mean[1]) / np.sqrt(4.0 + 1e-8), rel=1e-6)


def write(folder, name, r0, losses):
    rows = [RobustnessRow(name, "obs", s, r0 * (1 - loss), 0.0, 4, 0.0, (r0 * (1 - loss),) * 4)
            for s, loss in zip(SIGMAS, losses)]
    write_episodes_csv(rows, folder / "robustness" / name / "robustness_HalfCheetah-v5_obs_episodes.csv")


def test_table_pairs_clipped_and_trained_episodes(tmp_path, control):
    for seed in range(2):
        write(tmp_path, f"mlp@300k_s{seed}", 4000.0, (0.0, 0.8, 0.8))  # as trained
        write(tmp_path / "obs_clip", f"mlp@300k_s{seed}", 4000.0, (0.0, 0.4, 0.4))  # clipped
    args = argparse.Namespace(out=tmp_path, clip=3.0, episodes=4)
    (line,) = [row for row in control.table(args).splitlines() if row.startswith("| mlp@300k |")]
    # AUC = trapezoid of the ratios over sigma / 0.4: (1 + 2 * 0.2 + 0.2) / 4 = 0.4 and (1 + 2 * 0.6 + 0.6) / 4 = 0.7
    cells = [cell.strip() for cell in line.split("|")[1:-1]]
    assert cells[1] == "2" and cells[4] == "0.40 [0.40, 0.40]" and cells[5] == "0.70 [0.70, 0.70]"
    assert cells[6] == "0.30 [0.30, 0.30]" and cells[7].startswith("800 ") and cells[8].startswith("2400 ")
