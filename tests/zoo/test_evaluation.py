"""``evaluate``'s report of an evaluation, and its checks before any work."""

from pathlib import Path

import numpy as np
import pytest

from sb3_spikeplastic.zoo.evaluation import Evaluation, evaluate_command, report_lines
from sb3_spikeplastic.zoo.run_folder import RunInfo


def test_report_lines_say_return_success_and_energy():
    energy = {
        "spikes_per_step": [100.0, 50.5],
        "synops_per_step": [2000.0],
        "total_spikes_per_step": 50.5,
        "total_synops_per_step": 2000.0,
        "total_plasticity_macs_per_step": None,
        "energy_nj": None,
    }
    result = Evaluation(np.array([1.0, 0.0, 1.0, 1.0]), np.array([8.0, 8.0, 9.0, 9.0]), [1.0, 0.0, 1.0, 1.0], energy)
    info = RunInfo(Path("run/TMazeCue-v0.zip"), "TMazeCue-v0", Path("run/TMazeCue-v0/vecnormalize.pkl"))
    assert report_lines(result, "TMazeCue-v0", info, deterministic=False) == [
        "TMazeCue-v0: run/TMazeCue-v0.zip (VecNormalize: run/TMazeCue-v0/vecnormalize.pkl)",
        f"mean return 0.750 ± {np.std([1.0, 0.0, 1.0, 1.0]):.3f} over 4 episodes (stochastic); mean episode length 8.5",
        "success rate 0.750 (3/4)",
        "per environment step: 50.5 spikes in the hidden and output layers and 100.0 in the input population, "
        "2,000 SynOps (2,000 by layer)",
    ]
    plain = Evaluation(np.array([-3.0]), np.array([20.0]), [], None)
    assert report_lines(plain, "HalfCheetah-v5", RunInfo(Path("m.zip")), deterministic=True) == [
        "HalfCheetah-v5: m.zip",
        "mean return -3.000 ± 0.000 over 1 episodes (deterministic); mean episode length 20.0",
    ]


def test_evaluate_checks_its_options_before_writing(tmp_path):
    for options, message in [
        ({"episodes": 0}, "--episodes=0 must be >= 1"),
        ({"n_envs": 0}, "--n-envs=0"),
        ({}, "give either --run FOLDER or --model PATH"),
    ]:
        with pytest.raises(ValueError, match=message):
            evaluate_command(output=str(tmp_path / "eval.json"), **options)
    assert list(tmp_path.iterdir()) == []
