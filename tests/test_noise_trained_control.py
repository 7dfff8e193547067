"""The noise-trained control of the HalfCheetah protocol: its runs train with the observation noise on, are evaluated on
the noise-free environment with the protocol's episode seeds, and its table sets them beside the grid's models."""

import argparse

import pytest
from helpers import load_experiment

from sb3_spikeplastic.config import yaml_load
from sb3_spikeplastic.robustness import RobustnessRow, write_episodes_csv


@pytest.fixture(scope="module")
def control():
    return load_experiment("noise_trained_control")


def write(folder, name, returns):
    rows = [RobustnessRow(name, "obs", s, r, 0.0, 4, 0.0, (r,) * 4) for s, r in zip((0.0, 0.1, 0.2), returns)]
    write_episodes_csv(rows, folder / "robustness" / name / "robustness_HalfCheetah-v5_obs_episodes.csv")


def test_table_sets_noise_trained_models_beside_the_grids(tmp_path, control):
    for seed in (0, 1):
        write(tmp_path, f"static@300k_s{seed}", (3000.0, 2700.0, 2400.0))  # ratios 1, 0.9, 0.8: AUC 0.9
        write(tmp_path, f"mlp@300k_s{seed}", (4000.0, 400.0, 0.0))  # AUC (0.55 + 0.05) / 2 = 0.3
        write(tmp_path / "noise_trained", f"mlp+obs0.1@300k_s{seed}", (2000.0, 2000.0, 1000.0))  # AUC 0.875
    write(tmp_path / "noise_trained", "mlp+obs0.1@300k_s2", (500.0, 500.0, 500.0))  # did not learn
    args = argparse.Namespace(out=tmp_path, episodes=4, budget=300_000, variants=["mlp", "mlp_zoo"])
    lines = control.table(args).splitlines()
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in lines
            if line.startswith("| ") and "@" in line}
    assert set(rows) == {"static@300k", "mlp@300k", "mlp+obs0.1@300k"}  # mlp_zoo has no data: no row
    assert rows["static@300k"] == ["2", "3000 [3000, 3000]", "0.90 [0.90, 0.90]", "2400 [2400, 2400]", "", ""]
    assert rows["mlp@300k"][2:] == ["0.30 [0.30, 0.30]", "0 [0, 0]", "-0.60 [-0.60, -0.60]",
                                    "-2400 [-2400, -2400]"]
    assert rows["mlp+obs0.1@300k"][0] == "2"
    assert lines[-1] == "Did not learn (R0 < 1000): mlp+obs0.1@300k_s2 (500)."
    assert rows["mlp+obs0.1@300k"][2:] == ["0.88 [0.88, 0.88]", "1000 [1000, 1000]", "-0.03 [-0.03, -0.03]",
                                           "-1400 [-1400, -1400]"]


def test_a_short_run_trains_with_the_noise_and_is_evaluated_on_the_protocols_seeds(tmp_path, control):
    code = control.main(["--variants", "mlp", "--train-sigmas", "0.3", "--seeds", "0", "--budget", "2048",
                         "--sigmas", "0", "0.1", "--episodes", "2", "--robustness-envs", "2", "--jobs", "1",
                         "--out", str(tmp_path)])
    assert code == 0
    name = "mlp+obs0.3@2k_s0"
    config = yaml_load((control.run_dir(name, argparse.Namespace(out=tmp_path)) / "NoisyHalfCheetah-v5" /
                        "config.yml").read_text())
    assert config["NoisyHalfCheetah-v5"]["env_kwargs"]["obs_noise"] == 0.3
    episodes = tmp_path / "noise_trained" / "robustness" / name / "robustness_HalfCheetah-v5_obs_episodes.csv"
    assert len(episodes.read_text().strip().splitlines()) == 1 + 2 * 2  # header, 2 sigmas x 2 episodes
    # 2048 steps do not learn to run: the table lists the model apart
    assert f"Did not learn (R0 < 1000): {name} (" in (tmp_path / "noise_trained" / "table.md").read_text()
