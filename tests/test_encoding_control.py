"""The input controls of the HalfCheetah protocol: the MLP's inputs are exactly the spiking policy's encoder
probabilities, or spike counts drawn with them and replayed for the same observation, and a short run trains,
evaluates on the protocol's episode seeds and tabulates against the grid's models."""

import argparse

import gymnasium
import numpy as np
import pytest
import torch
from helpers import load_experiment

from sb3_spikeplastic import PPO
from sb3_spikeplastic.robustness import RobustnessRow, write_episodes_csv


@pytest.fixture(scope="module")
def control():
    return load_experiment("encoding_control")


@pytest.fixture(autouse=True)
def _mujoco_log_in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def test_features_are_the_spiking_policys_encoder_probabilities(control):
    env = gymnasium.make("HalfCheetah-v5")
    spiking = PPO("SpikePlasticPolicy", env, n_steps=64, batch_size=64, device="cpu").policy
    extractor, kwargs = control.features_extractor("rates")
    features = extractor(env.observation_space, **kwargs)
    obs = torch.tensor(np.random.default_rng(0).normal(0, 2.5, size=(8, 17)), dtype=torch.float32)
    obs[0, 0] = 7.0  # beyond the bound: clipped as the spiking encoder clips
    expected = spiking.snn.encoder.probabilities(obs)
    assert features.features_dim == expected.shape[1] == 17 * 10
    torch.testing.assert_close(features(obs), expected, rtol=0, atol=0)
    # by hand: cell k of dimension 1, centre -3 + 6 k / 9, beta 0.5
    k, x = 4, float(obs[1, 1])
    assert float(features(obs)[1, 10 + k]) == pytest.approx(max(np.exp(-0.5 * (-3 + 6 * k / 9 - x) ** 2), 0.05),
                                                            rel=1e-5)


def test_spike_counts_replay_for_the_same_observation_and_average_to_the_probabilities(control):
    env = gymnasium.make("HalfCheetah-v5")
    extractor, kwargs = control.features_extractor("spikes")
    features = extractor(env.observation_space, **kwargs)
    assert kwargs["steps"] == 10
    obs = torch.tensor(np.random.default_rng(1).normal(0, 1.0, size=(4, 17)), dtype=torch.float32)
    counts = features(obs)
    torch.testing.assert_close(features(obs.clone()), counts, rtol=0, atol=0)  # PPO's update sees the rollout's
    assert torch.equal(counts * 10, (counts * 10).round())  # spike counts over T = 10 steps
    assert not torch.equal(features(obs + 1e-3), counts)  # another observation, other spikes
    # over many distinct observations of the same cell probabilities the counts average to those probabilities
    many = obs[:1].repeat(4000, 1)
    many[:, 16] += torch.linspace(0, 1e-3, 4000)  # distinct bits, probabilities of the other dimensions unchanged
    mean = features(many)[:, :160].mean(0)
    torch.testing.assert_close(mean, features.encoder.probabilities(obs[:1])[0, :160], rtol=0, atol=0.02)


def write(folder, name, noise, r0, losses, sigmas=(0.0, 0.4)):
    rows = [RobustnessRow(name, noise, s, r0 * (1 - loss), 0.0, 2, 0.0, (r0 * (1 - loss),) * 2)
            for s, loss in zip(sigmas, losses)]
    write_episodes_csv(rows, folder / "robustness" / name / f"robustness_HalfCheetah-v5_{noise}_episodes.csv")


def test_a_short_run_trains_evaluates_and_compares(tmp_path, control, monkeypatch):
    monkeypatch.setattr(control.cfg, "resolve_hyperparams",
                        lambda *a, resolve=control.cfg.resolve_hyperparams, **k: {
                            **resolve(*a, **k), "n_envs": 2, "n_steps": 64, "batch_size": 64, "n_epochs": 1})
    for noise in ("friction", "action", "obs"):
        write(tmp_path, "mlp@2k_s0", noise, 4000.0, (0.0, 0.8))
        write(tmp_path, "static@2k_s0", noise, 3000.0, (0.0, 0.2))
    args = ["--input", "rates", "spikes", "--seeds", "0", "--budget", "2000", "--sigmas", "0", "0.4", "--episodes", "2", "--n-envs", "2",
            "--out", str(tmp_path)]
    assert control.main(args) == 0
    for name in ("mlp+encoder@2k_s0", "mlp+spikes@2k_s0"):
        folder = tmp_path / "encoding" / "runs" / name
        assert (folder / "model.zip").exists() and (folder / "vecnormalize.pkl").exists()
        for noise in ("friction", "action", "obs"):
            assert (tmp_path / "encoding" / "robustness" / name / f"robustness_HalfCheetah-v5_{noise}_episodes.csv").exists()
    table = (tmp_path / "encoding" / "table.md").read_text().splitlines()
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in table if line.startswith("| ")}
    assert {("obs", "mlp+encoder@2k"), ("obs", "mlp+spikes@2k"), ("obs", "mlp@2k"), ("obs", "static@2k")} <= set(rows)
    # the plain MLP keeps 0.2 of 4000 at sigma 0.4: AUC (1 + 0.2) / 2 = 0.60
    assert "| 0.60 [0.60, 0.60] |" in rows[("obs", "mlp@2k")]
