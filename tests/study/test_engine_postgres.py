"""A study shared through a real PostgreSQL server by two worker processes, as on two machines: one worker is
killed (SIGKILL) in the middle of a cell; the other takes the cell over, every cell is done exactly once and no raw
file is lost. ``slow`` (~20 s: two ``sb3-spikeplastic study`` processes train every cell of a study end to end); the
default suite runs the study command on SQLite and a journal file (test_engine.py) and PostgreSQL's storage
(test_storage.py)."""

import csv
import os
import signal
import subprocess
import sys
import time

import pytest

optuna = pytest.importorskip("optuna")
pytest.importorskip("psycopg2")

STUDY = """conf: cartpole.yml
envs: [CartPole-v1]
seeds: [0, 1]
budgets: [1024]
variants:
  small: {hyperparams: ["policy_kwargs.net_arch=[8]"]}
  large: {hyperparams: ["policy_kwargs.net_arch=[16]"]}
evaluations:
  final: {episodes: 5, seed: 100}
  robustness: {noises: [obs], sigmas: [0, 0.2], episodes: 4, n_envs: 2}
"""
CELLS = {f"CartPole-v1 {v} {s}" for v in ("small", "large") for s in (0, 1)}


def worker(files, url):
    """One ``sb3-spikeplastic study`` process, as a user starts it on a machine of their own."""
    command = [
        sys.executable,
        "-m",
        "sb3_spikeplastic.cli",
        "study",
        str(files / "pg.yml"),
        "--storage",
        url,
        "--folder",
        str(files / "shared"),
        "--heartbeat-interval",
        "1",
        "--grace-period",
        "4",
    ]
    return subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )


@pytest.mark.slow
def test_a_killed_workers_cell_is_taken_over(tmp_path, postgres_url, tiny_cartpole):
    (tmp_path / "cartpole.yml").write_text(tiny_cartpole.replace("512", "1024"))
    (tmp_path / "pg.yml").write_text(STUDY)
    victim, survivor = worker(tmp_path, postgres_url), worker(tmp_path, postgres_url)
    try:
        # Wait until the victim is training a cell (its trial running, its run folder made), then kill it.
        storage = optuna.storages.RDBStorage(postgres_url)
        deadline, killed = time.monotonic() + 120, None
        while killed is None and time.monotonic() < deadline:
            try:
                trials = optuna.load_study(study_name="pg", storage=storage).get_trials(deepcopy=False)
            except KeyError:  # not created yet
                trials = []
            for t in trials:
                if (
                    t.state.name == "RUNNING"
                    and t.user_attrs.get("worker", "").endswith(f":{victim.pid}")
                    and "run_dir" in t.user_attrs
                ):
                    victim.send_signal(signal.SIGKILL)
                    killed = t
                    break
            time.sleep(0.05)
        assert killed is not None, "the victim never ran a cell"
        victim.wait(30)
        out, _ = survivor.communicate(timeout=240)
    finally:
        for process in (victim, survivor):
            if process.poll() is None:
                process.kill()
    assert survivor.returncode == 0, out

    trials = optuna.load_study(study_name="pg", storage=optuna.storages.RDBStorage(postgres_url)).trials
    done = [t for t in trials if t.state.name == "COMPLETE"]
    assert sorted(t.user_attrs["cell"] for t in done) == sorted(CELLS)  # every cell done exactly once
    (dead,) = [t for t in trials if t.number == killed.number]
    assert dead.state.name == "FAIL"  # failed after the grace period...
    (rerun,) = [t for t in done if t.system_attrs.get("failed_trial") == killed.number]  # ...and queued again
    assert rerun.user_attrs["cell"] == killed.user_attrs["cell"]
    assert rerun.user_attrs["worker"].endswith(f":{survivor.pid}")
    others = [t for t in trials if t.state.name not in ("COMPLETE", "FAIL")]
    assert all(t.state.name == "PRUNED" for t in others)  # duplicates stepped aside, nothing left running

    # No raw row lost: every model's files are whole.
    for cell in CELLS:
        _, variant, seed = cell.split()
        folder = tmp_path / "shared" / "episodes" / "CartPole-v1" / f"{variant}@1024_s{seed}"
        with open(folder / "final.csv") as f:
            assert len(list(csv.DictReader(f))) == 5
        with open(folder / "robustness_obs.csv") as f:
            assert len(list(csv.DictReader(f))) == 2 * 4
    assert not list((tmp_path / "shared").rglob(".*.tmp*"))  # no half-written file left by the kill
