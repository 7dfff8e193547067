"""The observation-group control of the HalfCheetah protocol: its table sets each group of elements' return ratio
beside the all-element one, from the per-episode files."""

import argparse

import pytest
from helpers import load_experiment

from sb3_spikeplastic.robustness import RobustnessRow, write_episodes_csv


@pytest.fixture(scope="module")
def control():
    return load_experiment("obs_group_control")


def write(folder, name, sigmas, returns):
    rows = [RobustnessRow(name, "obs", s, r, 0.0, 4, 0.0, (r,) * 4) for s, r in zip(sigmas, returns)]
    write_episodes_csv(rows, folder / "robustness" / name / "robustness_HalfCheetah-v5_obs_episodes.csv")


def test_elements_split_the_observation(control):
    assert sorted(i for elements in control.ELEMENTS.values() for i in elements) == list(range(17))


def test_table_reads_every_group_of_elements_at_the_largest_sigma(tmp_path, control):
    for seed, r0 in enumerate((4000.0, 2000.0)):
        name = f"mlp@300k_s{seed}"
        write(tmp_path, name, (0.0, 0.1, 0.2), (r0, 0.1 * r0, 0.0))  # the protocol: every element
        write(tmp_path / "obs_groups" / "height", name, (0.0, 0.1), (r0, 0.2 * r0))
        write(tmp_path / "obs_groups" / "angles", name, (0.0, 0.1), (r0, 0.5 * r0))
        write(tmp_path / "obs_groups" / "velocities", name, (0.0, 0.1), (r0, 0.9 * r0))
    write(tmp_path / "obs_groups" / "height", "static@300k_s0", (0.0, 0.1), (3000.0, 2900.0))  # one group only
    args = argparse.Namespace(out=tmp_path, episodes=4, sigmas=[0.0, 0.1])
    lines = control.table(args).splitlines()
    assert not any(row.startswith("| static@300k |") for row in lines)
    (line,) = [row for row in lines if row.startswith("| mlp@300k |")]
    cells = [cell.strip() for cell in line.split("|")[1:-1]]
    assert cells == ["mlp@300k", "2", "3000", "0.10 [0.10, 0.10]", "0.20 [0.20, 0.20]", "0.50 [0.50, 0.50]",
                     "0.90 [0.90, 0.90]"]
    assert "| group | seeds | R0 | every element | height only | angles only | velocities only |" in lines
