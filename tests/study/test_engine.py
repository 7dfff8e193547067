"""``sb3-spikeplastic study``: workers sharing one Optuna study run every cell once, running it again does nothing,
a raised budget continues the runs, a dead worker's cell is run again, a cell queued twice runs once, and a study
declared otherwise under the same name is refused."""

import collections
import contextlib
import csv
import os
import shutil
import signal
import socket
import time
from pathlib import Path

import optuna
import pytest
import yaml

from sb3_spikeplastic import cli
from sb3_spikeplastic.study import engine, study_from_dict
from sb3_spikeplastic.study.layout import StudyFolder, read_final, read_robustness, read_training

ENV = "CartPole-v1"
CELLS = [(v, s) for v in ("small", "large") for s in (0, 1)]
#: A study of one short run per cell and one evaluation: what the queue tests need, in a second or two per cell.
MINI = {
    "conf": "cartpole.yml",
    "envs": [ENV],
    "seeds": [0],
    "budgets": [64],
    "variants": {
        "small": {"hyperparams": ["policy_kwargs.net_arch=[8]"]},
        "large": {"hyperparams": ["policy_kwargs.net_arch=[16]"]},
    },
    "evaluations": {"final": {"episodes": 2, "seed": 100}},
}


def load(folder, name="tiny", storage=None):
    return optuna.load_study(study_name=name, storage=storage or f"sqlite:///{folder.resolve()}/study.db")


def completed(study):
    """How often each cell completed."""
    return collections.Counter(t.user_attrs["cell"] for t in study.trials if t.state.name == "COMPLETE")


def files_of(folder):
    """Every file under ``folder`` with its modification time."""
    return {p.relative_to(folder): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, tiny_cartpole, tiny_study):
    """The tiny study run by two workers, once for the module; paths relative to the returned root (the run
    folders record them: a copy of the root is a study of its own)."""
    root = tmp_path_factory.mktemp("tiny")
    (root / "cartpole.yml").write_text(tiny_cartpole)
    (root / "tiny.yml").write_text(yaml.safe_dump(tiny_study, sort_keys=False))
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        assert cli.main(["study", "tiny.yml", "--workers", "2", "-f", "logs"]) == 0
    return root


@pytest.fixture
def copy_of(tiny, tmp_path, monkeypatch):
    """A copy of the tiny study's root, the working directory."""
    root = tmp_path / "root"
    shutil.copytree(tiny, root)
    monkeypatch.chdir(root)
    return root


def test_two_workers_run_every_cell_once(tiny):
    folder = tiny / "logs" / "study" / "tiny"
    study = load(folder)
    assert completed(study) == {engine.cell_key(ENV, v, s): 1 for v, s in CELLS}
    for trial in study.trials:
        if trial.state.name == "COMPLETE":
            assert trial.user_attrs["work"] == {"budget": 256, "evaluations": ["final", "robustness"]}
        elif "cell" in trial.user_attrs:  # two workers taking the same cell at once: the later steps aside
            assert trial.state.name == "PRUNED" and "duplicate_of" in trial.user_attrs, trial
        else:  # a worker that saw a cell waiting which the other took first: its trial has no cell to run
            assert trial.state.name == "PRUNED", trial
    # the cells ran in worker processes of this machine, not in this one
    workers = {tuple(t.user_attrs["worker"].rsplit(":", 1)) for t in study.trials if "cell" in t.user_attrs}
    assert 1 <= len(workers) <= 2 and {host for host, _ in workers} == {socket.gethostname()}
    assert str(os.getpid()) not in {pid for _, pid in workers}

    layout = StudyFolder(folder)
    for variant, seed in CELLS:
        (run,) = layout.run_folders(ENV, variant, seed)  # trained once, to the largest budget
        assert (run / f"{ENV}.zip").is_file()
        assert sorted(layout.checkpoints(ENV, variant, seed)) == [128, 256]
        steps, _ = read_training(layout.training_file(ENV, variant, seed))
        assert steps.tolist() == [64, 128, 192, 256]
        for budget in (128, 256):
            episodes = layout.episodes_dir(ENV, variant, budget, seed)
            assert sorted(p.name for p in episodes.iterdir()) == ["final.csv", "robustness_obs.csv"]
            assert read_final(episodes / "final.csv")["return"].shape == (4,)
            sigmas, returns = read_robustness(episodes / "robustness_obs.csv")
            assert sigmas.tolist() == [0.0, 0.5] and returns.shape == (2, 3)
            with open(episodes / "robustness_obs.csv") as f:
                rows = list(csv.DictReader(f))
            assert len(rows) == 6 and {r["model"] for r in rows} == {f"{variant}@{budget}_s{seed}"}
    for name in ("table.md", "verdicts.md", "verdicts.csv", "points.csv", "robustness.png", "training_curves.png"):
        assert (folder / name).is_file(), name
    assert "| large@256 | small@256 | 2 vs 2 |" in (folder / "verdicts.md").read_text()


def test_running_it_again_queues_and_trains_nothing(copy_of, run_cli):
    folder = copy_of / "logs" / "study" / "tiny"
    n_trials = len(load(folder).trials)
    before = {part: files_of(folder / part) for part in ("runs", "training", "episodes")}
    code, out, err = run_cli("study", "tiny.yml", "-f", "logs")
    assert code == 0, err
    assert "cells: 4 done" in out and "started" not in out
    assert len(load(folder).trials) == n_trials
    assert {part: files_of(folder / part) for part in ("runs", "training", "episodes")} == before


def test_a_folder_of_raw_files_alone_trains_nothing(copy_of, run_cli):
    """The raw files without the runs or the study's database, as ``results/`` keeps them: every cell completes
    without training or writing anything."""
    raw = copy_of / "raw"
    for part in ("episodes", "training"):
        shutil.copytree(copy_of / "logs" / "study" / "tiny" / part, raw / part)
    before = files_of(raw)
    code, out, err = run_cli("study", "tiny.yml", "-f", "logs", "--folder", "raw")
    assert code == 0, err
    assert "cells: 4 done" in out and out.count("done, 0 file(s) written") == 4
    assert not (raw / "runs").exists()
    assert {p: t for p, t in files_of(raw).items() if p.parts[0] in ("episodes", "training")} == before


def test_a_raised_budget_continues_each_run_and_writes_only_its_files(copy_of, run_cli, tiny_study):
    folder = copy_of / "logs" / "study" / "tiny"
    layout = StudyFolder(folder)
    old_episodes = files_of(folder / "episodes")
    old_runs = {(v, s): files_of(layout.run_folders(ENV, v, s)[0]) for v, s in CELLS}
    (copy_of / "tiny.yml").write_text(yaml.safe_dump({**tiny_study, "budgets": [128, 256, 384]}, sort_keys=False))
    code, out, err = run_cli("study", "tiny.yml", "-f", "logs")
    assert code == 0, err

    study = load(folder)
    assert completed(study) == {engine.cell_key(ENV, v, s): 2 for v, s in CELLS}  # one more trial per cell
    for variant, seed in CELLS:
        first, second = layout.run_folders(ENV, variant, seed)
        assert second.name == f"{ENV}_2"
        args = yaml.safe_load((second / ENV / "args.yml").read_text())
        assert (copy_of / args["trained_agent"]).resolve() == (first / f"{ENV}.zip").resolve()
        assert args["start_timesteps"] == 256
        # the first run's models are untouched (TensorBoard may append to its event files)
        assert {p: t for p, t in files_of(first).items() if "tfevents" not in p.name} == {
            p: t for p, t in old_runs[(variant, seed)].items() if "tfevents" not in p.name
        }
        assert layout.model_at(ENV, variant, seed, 384) == second / "rl_model_384_steps.zip"
        assert layout.model_at(ENV, variant, seed, 256) == first / "rl_model_256_steps.zip"
        steps, _ = read_training(layout.training_file(ENV, variant, seed))
        assert steps.tolist() == [64, 128, 192, 256, 320, 384]  # the step counter was kept
        new = layout.episodes_dir(ENV, variant, 384, seed)
        assert sorted(p.name for p in new.iterdir()) == ["final.csv", "robustness_obs.csv"]
    now = files_of(folder / "episodes")
    assert {p: t for p, t in now.items() if p in old_episodes} == old_episodes  # old files not written again
    assert len(now) == len(old_episodes) + 2 * len(CELLS)
    assert "small@384" in (folder / "table.md").read_text()


def test_periodic_checkpoints_keep_every_budgets_model_and_a_cut_run_continues_from_them(files):
    """``--save-freq``: a checkpoint every N steps, the latest two kept and every budget's model never removed; the
    raw files are those of a study without it; a run cut short continues from its latest periodic checkpoint."""
    study = mini(files, budgets=[128, 256]).select(["small"])
    plain = engine.prepare(study, files / "plain", "mini")
    periodic = engine.prepare(study, files / "periodic", "mini", save_freq=32)  # every 16 calls of 2 envs
    for job in (plain, periodic):
        assert engine.run_worker(job, lambda line: None) == 0
    layout = StudyFolder(files / "periodic")
    assert sorted(layout.checkpoints(ENV, "small", 0)) == [128, 192, 224, 256]
    assert sorted(StudyFolder(files / "plain").checkpoints(ENV, "small", 0)) == [128, 256]
    for budget in (128, 256):
        for folder in (plain, periodic):
            assert (folder.layout.episodes_dir(ENV, "small", budget, 0) / "final.csv").is_file()
        assert (plain.layout.episodes_dir(ENV, "small", budget, 0) / "final.csv").read_bytes() == (
            periodic.layout.episodes_dir(ENV, "small", budget, 0) / "final.csv"
        ).read_bytes()

    # Cut short after 192 steps: no final model, no later checkpoint, nothing evaluated at 256.
    (run,) = layout.run_folders(ENV, "small", 0)
    for path in [run / f"{ENV}.zip", *run.glob("rl_model*_224_steps.*"), *run.glob("rl_model*_256_steps.*")]:
        path.unlink()
    shutil.rmtree(layout.episodes_dir(ENV, "small", 256, 0))
    job = engine.prepare(study, files / "periodic", "mini-continued", save_freq=32)
    assert engine.run_worker(job, lambda line: None) == 0
    first, second = layout.run_folders(ENV, "small", 0)
    assert yaml.safe_load((second / ENV / "args.yml").read_text())["start_timesteps"] == 192
    assert layout.model_at(ENV, "small", 0, 256) == second / "rl_model_256_steps.zip"
    assert (layout.episodes_dir(ENV, "small", 256, 0) / "final.csv").is_file()


def mini(files, **changes):
    """The MINI study (``changes``: top-level keys replaced) read from ``files``."""
    return study_from_dict({**MINI, **changes}, "mini.yml", files)


@contextlib.contextmanager
def deadline(seconds):
    """``TimeoutError`` in the block after ``seconds``."""

    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")  # the dead worker's trial is taken by hand
@pytest.mark.parametrize("storage", [None, "journal.log"])
def test_a_dead_workers_cell_is_run_again(files, storage):
    """A cell left RUNNING by a worker that stopped sending heartbeats (killed) is failed after the grace period
    and queued again; the next worker runs it, and every cell once."""
    storage = None if storage is None else str(files / storage)
    job = engine.prepare(mini(files), files / "s", "mini", storage, heartbeat_interval=1, grace_period=2)
    study = job.open()
    assert engine.queue_cells(job, study) == 2
    dead = study.ask()  # what a worker does before it dies: take a cell, start it, send a heartbeat
    cell = dead.user_attrs["cell"]
    study._storage.record_heartbeat(dead._trial_id)
    time.sleep(2.5)
    lines = []
    with deadline(60):  # a worker that never fails the dead trial waits for it forever
        assert engine.run_worker(job, lines.append) == 0
    study = job.open()
    assert [t.state.name for t in study.trials if t.number == dead.number] == ["FAIL"]
    (rerun,) = [t for t in study.trials if t.user_attrs.get("cell") == cell and t.state.name == "COMPLETE"]
    assert rerun.system_attrs["failed_trial"] == dead.number and rerun.number > dead.number
    assert completed(study) == {engine.cell_key(ENV, v, 0): 1 for v in ("small", "large")}
    assert any(f"(trial {rerun.number}): done" in line for line in lines), lines
    assert (files / "s" / "study.db").exists() == (storage is None)


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")
def test_a_cell_queued_twice_runs_once(files):
    job = engine.prepare(mini(files).select(["small"]), files / "s", "mini")
    study = job.open()
    key, work = engine.cell_key(ENV, "small", 0), job.work("small")
    for _ in range(2):  # two workers queueing the same cell at once
        study.enqueue_trial({}, user_attrs={"cell": key, "work": work})
    earlier, later = study.trials
    assert engine.owner_of(study, later) == earlier.number and engine.owner_of(study, earlier) is None
    assert engine.queue_cells(job, study) == 0  # the cell is waiting already
    lines = []
    assert engine.run_worker(job, lines.append) == 0
    earlier, later = job.open().trials
    assert earlier.state.name == "COMPLETE" and "duplicate_of" not in earlier.user_attrs
    assert later.state.name == "PRUNED" and later.user_attrs["duplicate_of"] == earlier.number
    assert len(StudyFolder(files / "s").run_folders(ENV, "small", 0)) == 1  # trained once
    assert any(f"(trial {later.number}): skipped, taken by trial {earlier.number}" in line for line in lines), lines


def test_a_worker_leaves_another_selections_cell_to_that_selection(files):
    """Two invocations with other --variants share one study: a worker that takes the other's waiting cell puts it
    back at the end of the queue (never fails it) and runs its own; the other's worker then runs it."""
    folder = files / "s"
    large = engine.prepare(mini(files).select(["large"]), folder, "mini")
    small = engine.prepare(mini(files).select(["small"]), folder, "mini")
    assert engine.queue_cells(large, large.open()) == 1  # first in the queue: the cell the small worker cannot run
    lines = []
    assert engine.run_worker(small, lines.append) == 0
    study = small.open()
    small_key, large_key = engine.cell_key(ENV, "small", 0), engine.cell_key(ENV, "large", 0)
    assert completed(study) == {small_key: 1}
    (passed,) = [t for t in study.trials if t.user_attrs.get("requeued")]
    assert passed.state.name == "PRUNED" and passed.user_attrs["cell"] == large_key
    assert [t.state.name for t in study.trials if t.user_attrs.get("cell") == large_key] == ["PRUNED", "WAITING"]
    assert not any(t.state.name == "FAIL" for t in study.trials)
    assert any("queued again for a worker of its own selection" in line for line in lines), lines
    assert engine.run_worker(large, lines.append) == 0
    assert completed(large.open()) == {small_key: 1, large_key: 1}


@pytest.mark.parametrize(
    "changes, what",
    [
        (
            {"variants": {**MINI["variants"], "small": {"hyperparams": ["policy_kwargs.net_arch=[12]"]}}},
            "variant 'CartPole-v1 small'",
        ),
        ({"evaluations": {"final": {"episodes": 3, "seed": 100}}}, "evaluation 'final'"),
        ({"eval_freq": 64}, "other evaluations during training"),
    ],
)
def test_a_study_declared_otherwise_is_refused(files, run_cli, changes, what):
    folder = files / "logs" / "study" / "mini"
    job = engine.prepare(mini(files), folder, "mini")
    engine.queue_cells(job, job.open())  # the study exists: its declaration recorded, its cells queued
    before, stored = files_of(folder), load(folder, "mini").user_attrs

    with pytest.raises(ValueError, match="^study 'mini' .*" + what.replace("(", r"\(")) as error:
        engine.prepare(mini(files, **changes), folder, "mini")
    assert "\n" not in str(error.value)
    (files / "mini.yml").write_text(yaml.safe_dump({**MINI, **changes}))
    code, out, err = run_cli("study", files / "mini.yml", "-f", files / "logs")
    assert code == 2 and err.count("\n") == 1 and what in err, err
    assert files_of(folder) == before and load(folder, "mini").user_attrs == stored  # nothing written


def test_new_variants_and_seeds_join_an_existing_study(files):
    folder = files / "s"
    job = engine.prepare(mini(files), folder, "mini")
    assert engine.queue_cells(job, job.open()) == 2
    medium = {"hyperparams": ["policy_kwargs.net_arch=[12]"]}
    grown = mini(files, seeds=[0, 1], variants={**MINI["variants"], "medium": medium})
    job = engine.prepare(grown, folder, "mini")
    study = job.open()
    assert engine.queue_cells(job, study) == 4  # the cells not queued before, and only those
    waiting = [t.user_attrs["cell"] for t in study.trials if t.state.name == "WAITING"]
    assert sorted(waiting) == sorted(engine.cell_key(ENV, v, s) for v in ("small", "large", "medium") for s in (0, 1))
    declared = load(folder, "mini").user_attrs[engine.DECLARATION_KEY]["variants"]
    assert sorted(declared) == [f"{ENV} large", f"{ENV} medium", f"{ENV} small"]


ABLATION_STUDY = """envs: [TMazeCue-v0]
seeds: [0]
budgets: [64]
hyperparams: [n_envs=2, n_steps=32, batch_size=32, bptt_steps=16, n_epochs=1, "policy_kwargs.hidden_sizes=[16]"]
variants:
  static: {rule: static}
  dp-oja: {rule: dp-oja}
evaluations:
  final: {episodes: 6, seed: 100, n_envs: 2}
  frozen: {kind: final, ablation: frozen, episodes: 6, seed: 100, n_envs: 2}
  reset: {kind: final, ablation: "reset-every:1", episodes: 6, seed: 100, n_envs: 2}
"""


def test_evaluations_under_a_plasticity_ablation(tmp_path):
    """An evaluation may run the spiking models under an ablation: the static network's episodes are those of its
    plain evaluation, the plastic network's run on W alone; the ablation is part of the declaration."""
    data = yaml.safe_load(ABLATION_STUDY)
    study = study_from_dict(data)
    assert (study.evaluations["frozen"].ablation, study.evaluations["reset"].ablation) == ("frozen", "reset-every:1")
    job = engine.prepare(study, tmp_path / "s", "ablation")
    assert engine.run_worker(job, lambda line: None) == 0
    episodes = tmp_path / "s" / "episodes" / "TMazeCue-v0"
    static = {name: read_final(episodes / "static@64_s0" / f"{name}.csv") for name in ("final", "frozen", "reset")}
    assert (static["final"]["return"] == static["frozen"]["return"]).all()
    assert (static["final"]["length"] == static["reset"]["length"]).all()
    for name in ("final", "frozen", "reset"):
        assert len(read_final(episodes / "dp-oja@64_s0" / f"{name}.csv")["return"]) == 6
    # Declaring the same evaluation name with another ablation is another declaration: refused.
    data["evaluations"]["frozen"]["ablation"] = "shuffled"
    with pytest.raises(ValueError, match="evaluation 'frozen' otherwise"):
        engine.prepare(study_from_dict(data), tmp_path / "s", "ablation")
    data["evaluations"]["frozen"]["ablation"] = "melted"
    with pytest.raises(ValueError, match="ablation of evaluation 'frozen'.*melted"):
        study_from_dict(data)


def _take_waiting_trials(folder, out):
    """A worker's way of taking trials: ask for the next waiting one until none is left."""
    import optuna

    from sb3_spikeplastic.study.storage import open_storage

    study = optuna.load_study(study_name="race", storage=open_storage(None, Path(folder)))
    taken = []
    while any(t.state.name == "WAITING" for t in study.get_trials(deepcopy=False)):
        trial = study.ask()
        taken.append(trial.number)
        time.sleep(0.01)
        study.tell(trial, 1.0)
    out.put(taken)


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")
def test_four_processes_never_take_the_same_waiting_trial_from_sqlite(tmp_path):
    """SQLite ignores Optuna's SELECT ... FOR UPDATE; the default storage's immediate transactions make taking a
    waiting trial atomic, so that two workers never run one cell (each trial is taken exactly once)."""
    import multiprocessing
    import queue

    import optuna

    from sb3_spikeplastic.study.storage import open_storage

    study = optuna.create_study(study_name="race", storage=open_storage(None, tmp_path))
    for i in range(40):
        study.enqueue_trial({}, user_attrs={"i": i})
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    workers = [context.Process(target=_take_waiting_trials, args=(str(tmp_path), out)) for _ in range(4)]
    for worker in workers:
        worker.start()
    try:
        taken = [number for _ in workers for number in out.get(timeout=120)]
    except queue.Empty:  # a worker died: it told a trial that another worker had finished
        taken = None
    finally:
        for worker in workers:
            worker.join(10)
            if worker.is_alive():
                worker.kill()
    assert taken is not None and len(taken) == len(set(taken))
    assert (
        {
            t.number
            for t in optuna.load_study(study_name="race", storage=open_storage(None, tmp_path)).trials
            if t.state.name == "COMPLETE"
        }
        == set(taken)
        >= set(range(40))
    )


def test_a_worker_process_routes_mujoco_warnings(monkeypatch):
    """A spawned worker starts without the command line's route of MuJoCo's warnings: it installs its own, so that
    its HalfCheetah builds neither print MuJoCo's deprecation nor write ./MUJOCO_LOG.TXT."""
    import mujoco

    previous = mujoco.get_mju_user_warning()
    try:
        mujoco.set_mju_user_warning(None)
        monkeypatch.setattr(engine, "run_worker", lambda job, log: 0)
        with pytest.raises(SystemExit) as exit_info:
            engine._worker_process(None, 1)
        assert exit_info.value.code == 0
        assert mujoco.get_mju_user_warning() is not None
    finally:
        mujoco.set_mju_user_warning(previous)
