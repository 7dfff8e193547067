"""``plot``'s parts: the Monitor files of run folders, their labels and the summary line of each run."""

import json

import numpy as np
import pytest

from sb3_spikeplastic.zoo.figures import curve_summaries, plot_command, read_runs


def monitor_file(path, episodes, t_start=1000.0):
    """An SB3 Monitor file of ``(return, length, seconds, is_success)`` episodes."""
    lines = ["#" + json.dumps({"t_start": t_start, "env_id": "X"}), "r,l,t,is_success"]
    lines += [f"{r},{l},{t},{s}" for r, l, t, s in episodes]
    path.write_text("\n".join(lines) + "\n")


def test_runs_are_read_labelled_and_summed_up(tmp_path):
    run = tmp_path / "TMazeCue-v0_1"
    (run / "TMazeCue-v0").mkdir(parents=True)
    (run / "TMazeCue-v0" / "config.yml").write_text("TMazeCue-v0:\n  policy: SpikePlasticPolicy\n"
                                                     "  policy_kwargs: {rule: dp-bcm}\n")
    monitor_file(run / "0.monitor.csv", [(1.0, 10, 1.0, "True"), (0.0, 10, 3.0, "False")])
    monitor_file(run / "1.monitor.csv", [(-1.0, 20, 2.0, "True")])
    other = tmp_path / "other" / "TMazeCue-v0_1"  # the same folder name: labelled by its path
    other.mkdir(parents=True)
    monitor_file(other / "0.monitor.csv", [(5.0, 4, 1.0, "")] * 3)
    runs = read_runs([run, other])
    assert list(runs) == ["TMazeCue-v0_1 (dp-bcm)", "TMazeCue-v0_1"]
    first = runs["TMazeCue-v0_1 (dp-bcm)"]
    assert first["r"].tolist() == [1.0, -1.0, 0.0] and first["l"].tolist() == [10, 20, 10]  # in order of time
    assert first["is_success"].tolist() == [1.0, 1.0, 0.0]
    assert curve_summaries(runs, last=2) == [
        "TMazeCue-v0_1 (dp-bcm): 3 episodes, 40 steps, mean return of the last 2: -0.500, "
        "success rate of the last 2: 0.500",
        "TMazeCue-v0_1: 3 episodes, 12 steps, mean return of the last 2: 5.000"]
    assert np.isnan(runs["TMazeCue-v0_1"]["is_success"]).all()


def test_plot_checks_its_runs_before_writing(tmp_path):
    (tmp_path / "empty").mkdir()
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    monitor_file(unfinished / "0.monitor.csv", [])
    cases = [([tmp_path / "nowhere"], {}, "no run folder"), ([tmp_path / "empty"], {}, "no Monitor files"),
             ([unfinished], {}, "no finished episodes"), ([unfinished], {"x": "hours"}, "unknown --x 'hours'"),
             ([unfinished], {"smooth": 0}, "--smooth=0 must be >= 1")]
    for runs, options, message in cases:
        with pytest.raises(ValueError, match=message):
            plot_command(runs, output=tmp_path / "out" / "curves.png", **options)
    assert not (tmp_path / "out").exists()
