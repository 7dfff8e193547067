"""``sb3-spikeplastic grid``: workers sharing one study run every cell once, a dead worker's cell is run again,
the summary, the T-maze grid file, and bad input."""

import csv
import os
import socket
import sys
import threading
import time
from pathlib import Path

import optuna
import pytest
from helpers import TINY_CARTPOLE, run_cli

from sb3_spikeplastic import grid as grid_mod
from sb3_spikeplastic.studies import default_storage_url

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"
GRID = """conf: cartpole.yml
envs: [CartPole-v1]
seeds: [0, 1]
n_timesteps: 128
final_eval: {episodes: 2, seed: 100}
variants:
  small: ["policy_kwargs.net_arch=[8]"]
  large: {hyperparams: ["policy_kwargs.net_arch=[16]"]}
"""
CELLS = {("small", 0), ("small", 1), ("large", 0), ("large", 1)}


@pytest.fixture
def files(tmp_path):
    (tmp_path / "cartpole.yml").write_text(TINY_CARTPOLE)
    (tmp_path / "tiny.yml").write_text(GRID)
    return tmp_path


def cells_of(study, state="COMPLETE"):
    return [(t.params["variant"], t.params["seed"]) for t in study.trials if t.state.name == state]


def test_two_workers_run_every_cell_once(files, capsys):
    code, out, err = run_cli(capsys, "grid", files / "tiny.yml", "--workers", "2", "-f", files / "logs")
    assert code == 0, err
    folder = files / "logs" / "grid" / "tiny"
    study = optuna.load_study(study_name="tiny", storage=default_storage_url(folder))
    assert sorted(cells_of(study)) == sorted(CELLS)  # each cell completed once
    # Two workers asking at the same moment may both get the last cell: the later trial sees the earlier one
    # and steps aside without training.
    assert all(t.state.name == "PRUNED" and "duplicate_of" in t.user_attrs for t in study.trials
               if t.state.name != "COMPLETE")
    # the cells ran in worker processes of this machine, not in this one: at most two of them
    workers = {tuple(t.user_attrs["worker"].rsplit(":", 1)) for t in study.trials}
    assert 1 <= len(workers) <= 2 and {host for host, _ in workers} == {socket.gethostname()}
    assert str(os.getpid()) not in {pid for _, pid in workers}
    for variant, seed in CELLS:
        (run,) = (folder / "runs" / f"CartPole-v1_{variant}_{seed}" / "ppo").iterdir()  # trained once
        assert (run / "CartPole-v1.zip").is_file() and (run / "final_eval.json").is_file()
    with open(folder / "grid.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["variant"], r["seed"], r["state"]) for r in rows] == [
        ("small", "0", "done"), ("large", "0", "done"), ("small", "1", "done"), ("large", "1", "done")]
    trial = {(t.params["variant"], t.params["seed"]): t for t in study.trials if t.state.name == "COMPLETE"}
    assert float(rows[0]["final_return"]) == trial[("small", 0)].value
    table = (folder / "grid.md").read_text()
    assert "| small | CartPole-v1 | 2/2 |" in table and "±" in table and table in out

    # Running it again finds nothing to do; the summary alone can be written at any time.
    n_trials = len(study.trials)
    assert run_cli(capsys, "grid", files / "tiny.yml", "-f", files / "logs")[0] == 0
    assert len(optuna.load_study(study_name="tiny", storage=default_storage_url(folder)).trials) == n_trials
    assert run_cli(capsys, "grid", files / "tiny.yml", "-f", files / "logs", "--summary-only")[0] == 0


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")  # the dead worker's trial is made by hand
@pytest.mark.parametrize("storage", [None, "journal.log"])
def test_a_dead_workers_cell_is_run_again(files, storage):
    """A cell left RUNNING by a worker that stopped sending heartbeats (killed) is failed after the grace period
    and queued again with the same parameters; the next worker runs it."""
    storage = None if storage is None else str(files / storage)
    grid = grid_mod.load_grid(files / "tiny.yml").select(seeds=[0])
    job = grid_mod.prepare(grid, files / "g", "tiny", storage, heartbeat_interval=1, grace_period=2)
    study = job.open_study()
    dead = study.ask()  # what a worker does before it dies: take a cell, start it, send a heartbeat
    cell = {k: dead.suggest_categorical(k, v) for k, v in grid.search_space().items()}
    study._storage.record_heartbeat(dead._trial_id)
    time.sleep(2.5)
    lines = []
    assert grid_mod.run_worker(job, lines.append) == 0
    study = job.load_study()
    assert [t.state.name for t in study.trials if t.number == dead.number] == ["FAIL"]
    (rerun,) = [t for t in study.trials if t.params == cell and t.state.name == "COMPLETE"]
    assert rerun.system_attrs["failed_trial"] == dead.number
    assert sorted(cells_of(study)) == [("large", 0), ("small", 0)]  # every cell once
    assert any(f"(trial {rerun.number}): done" in line for line in lines)


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")  # the trials are made by hand
def test_a_trial_waits_for_an_earlier_trial_to_choose_its_cell(files):
    """Two workers starting the same cell at once: the later trial checks while the earlier one has not chosen
    its cell yet. It waits for that choice and steps aside; the earlier trial does not wait for the later one."""
    grid = grid_mod.load_grid(files / "tiny.yml").select(seeds=[0])
    job = grid_mod.prepare(grid, files / "g", "tiny", heartbeat_interval=1, grace_period=60)
    study = job.open_study()
    space = grid.search_space()
    cell = {"env": "CartPole-v1", "variant": "small", "seed": 0}

    def choose(trial, delay=0.0):  # what CellRunner's suggest_categorical calls store
        time.sleep(delay)
        for name, value in cell.items():
            study._storage.set_trial_param(trial._trial_id, name, space[name].index(value),
                                           optuna.distributions.CategoricalDistribution(space[name]))

    earlier, later = study.ask(), study.ask()
    choose(later)
    chooser = threading.Thread(target=choose, args=(earlier, 0.5))
    chooser.start()
    runner = grid_mod.CellRunner(job)
    start = time.monotonic()
    assert runner.duplicate_of(study, study.trials[later.number]) == earlier.number
    assert time.monotonic() - start >= 0.5
    chooser.join()
    assert runner.duplicate_of(study, study.trials[earlier.number]) is None


@pytest.mark.parametrize("text, message", [
    (GRID + "repeats: 3\n", "unknown grid key 'repeats'"),
    (GRID.replace("{hyperparams:", "{hyperparameters:"), "unknown key of variant 'large' 'hyperparameters'"),
    (GRID.replace("net_arch=[8]", "net_arc=[8]"), "variant 'small' on CartPole-v1: unknown policy_kwargs key"),
    (GRID.replace("seeds: [0, 1]", "seeds: [0, 0]"), "must be a non-empty list of distinct integers"),
    (GRID.replace("final_eval: {episodes: 2, seed: 100}", "final_eval: {episodes: 0}"), "gives the cells no value"),
    (GRID.replace("CartPole-v1]", "CartPol-v1]"), "unknown environment id 'CartPol-v1'"),
    ("- a list\n", "must be a mapping"),
])
def test_bad_grid_files_are_one_line_and_write_nothing(files, capsys, text, message):
    (files / "bad.yml").write_text(text)
    code, out, err = run_cli(capsys, "grid", files / "bad.yml", "-f", files / "logs")
    assert code == 2 and err.count("\n") == 1 and err.startswith("sb3-spikeplastic: error: ") and message in err
    assert not (files / "logs").exists()


def test_bad_options_are_one_line_and_write_nothing(files, capsys):
    (files / "file").write_text("x")
    for argv, message in ((["--workers", "0"], "--workers=0 must be >= 1"),
                          (["--heartbeat-interval", "10", "--grace-period", "5"], "--grace-period=5 must be >= 11"),
                          (["--summary-only"], "no study 'tiny'"),
                          (["--storage", files / "file" / "j.log"], "--storage")):
        code, out, err = run_cli(capsys, "grid", files / "tiny.yml", "-f", files / "logs", *argv)
        assert code == 2 and err.count("\n") == 1 and message in err, err
    code, out, err = run_cli(capsys, "grid", files / "tiny.yml", "-f", files / "file" / "logs")
    assert code == 2 and "lies under the file" in err
    assert not (files / "logs").exists()


def test_the_tmaze_grid_file_and_its_script(tmp_path):
    """The paper's T-maze grid: 8 variants x 2 mazes x 3 seeds, and tmaze_grid.py's selections of it."""
    grid = grid_mod.load_grid(EXPERIMENTS / "tmaze_grid.yml")
    assert len(grid.variants) == 8 and grid.envs == ["TMazeCue-v0", "TMazeCueNoisy-v0"] and grid.seeds == [0, 1, 2]
    tanh = grid.config("TMazeCueNoisy-v0", "ndp-oja+tanh")["policy_kwargs"]
    assert tanh["rule"] == "ndp-oja" and tanh["rule_kwargs"] == {"modulation": "tanh", "wm_init_gain": 5}
    assert grid.final_eval.episodes == 1000 and grid.final_eval.best_model
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        import tmaze_grid
    finally:
        sys.path.remove(str(EXPERIMENTS))
    args = tmaze_grid.parse_args(["--rules", "static", "dp-oja", "--envs", "TMazeCue-v0", "--seeds", "0", "-n",
                                  "50000", "--heldout-episodes", "0", "--hyperparams", "n_epochs=2"])
    selected = tmaze_grid.selected_grid(args)
    assert list(selected.variants) == ["static", "dp-oja"] and selected.envs == ["TMazeCue-v0"]
    assert selected.seeds == [0] and selected.n_timesteps == 50_000 and selected.final_eval.episodes == 0
    assert selected.config("TMazeCue-v0", "dp-oja")["n_epochs"] == 2
