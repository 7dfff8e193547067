"""``sb3-spikeplastic study FILE``: workers that share one Optuna study train and evaluate every cell of a study
file once (the work of a cell: :mod:`sb3_spikeplastic.study.cell`).

The queue. Each cell is a ``WAITING`` Optuna trial carrying the cell and the work it was queued for (user
attributes ``cell``, ``work``); a worker takes one with ``study.optimize`` (a heartbeat while it runs). Running
``study`` queues every cell with no trial waiting or running and no finished trial that did that work (so raising a
budget, adding seeds, variants or evaluations queues exactly what is new). Two workers that queue the same cell at
once leave two trials; a worker runs its trial only if no earlier trial of the cell is waiting or running and no
finished one did its work, else it marks it pruned (``duplicate_of``). A worker runs only the cells of its own
invocation's ``--variants`` and ``--seeds``: another invocation's cell that it takes goes back to the end of the
queue for a worker that runs it (``requeued``). A killed worker stops sending heartbeats:
its trial is failed after the grace period and queued again (:mod:`sb3_spikeplastic.study.storage`), and the cell
resumes from what it had written. The study records its declaration (every variant's resolved entry, every
evaluation's protocol); a file that declares an existing variant or evaluation otherwise is refused, so results
of two declarations never mix.
"""

from __future__ import annotations

import multiprocessing
import sys
import time
from dataclasses import dataclass
from functools import reduce
from pathlib import Path
from typing import Callable, Optional

from ..envs import route_mujoco_warnings
from .cell import run_cell
from .declaration import Study
from .layout import StudyFolder
from .storage import (
    HEARTBEAT_INTERVAL,
    _plain,
    check_model,
    describe_storage,
    one_line,
    open_storage,
    quiet_optuna,
    retry_callback,
    storage_exists,
    worker_name,
)

#: The user attribute of an Optuna study that holds its declaration.
DECLARATION_KEY = "study"
#: Seconds a worker with no cell to take waits before it looks at the study again.
POLL_INTERVAL = 5


def cell_key(env: str, variant: str, seed: int) -> str:
    return f"{env} {variant} {seed}"


@dataclass
class StudyJob:
    """A checked study and where it runs (:func:`prepare`).

    :param study: the study file's declaration
    :param folder: the study's folder (default storage, ``runs/``, ``training/``, ``episodes/``, the report)
    :param name: the Optuna study's name
    :param storage: ``--storage`` (``None``: SQLite in ``folder``)
    :param configs: the resolved entry of each ``(env, variant)``
    :param heartbeat_interval: seconds between heartbeats of a running cell
    :param grace_period: seconds without a heartbeat after which a running cell is failed and queued again
    :param device: torch device of the models
    :param torch_threads: ``torch.set_num_threads`` of each worker
    :param save_freq: environment steps between a training's periodic checkpoints, of which the latest two stay (0:
        only the budgets' models): a cell cut short continues from the latest
    :param declared: the whole study file when ``study`` is a part of it (``--variants``, ``--seeds``): the report
        covers the whole study
    """

    study: Study
    folder: Path
    name: str
    storage: Optional[str]
    configs: dict[tuple[str, str], dict]
    heartbeat_interval: int = HEARTBEAT_INTERVAL
    grace_period: Optional[int] = None
    device: str = "cpu"
    torch_threads: int = 1
    save_freq: int = 0
    declared: Optional[Study] = None

    @property
    def layout(self) -> StudyFolder:
        return StudyFolder(self.folder)

    @property
    def declaration(self) -> dict:
        """What results depend on: each ``(env, variant)``'s entry (its length aside: budgets may grow), the
        evaluations during training, and each evaluation's protocol."""
        s = self.study
        return _plain(
            {
                "training": {"eval_freq": s.eval_freq, "eval_episodes": s.eval_episodes},
                "variants": {
                    f"{env} {variant}": {
                        "train_env": s.train_env(env, variant),
                        **{k: v for k, v in config.items() if k != "n_timesteps"},
                    }
                    for (env, variant), config in self.configs.items()
                },
                "evaluations": {
                    name: {
                        "kind": e.kind,
                        "model": e.model,
                        "clip_obs": e.clip_obs,
                        "shift": e.shift,
                        "ablation": e.ablation,
                        **e.protocol.as_dict(),
                        # Only where declared: a study recorded before these keys existed is declared alike.
                        **({"info_keys": list(e.info_keys)} if e.info_keys else {}),
                        **({"align": e.align} if e.align is not None else {}),
                    }
                    for name, e in s.evaluations.items()
                },
            }
        )

    def work(self, variant: str) -> dict:
        """What a cell of ``variant`` is queued to do: train to its largest budget, run these evaluations."""
        return {"budget": max(self.study.budgets_of(variant)), "evaluations": sorted(self.study.evaluations)}

    def open(self):
        """The Optuna study (created if new), its declaration merged with this one's."""
        import optuna

        storage = open_storage(self.storage, self.folder, self.heartbeat_interval, self.grace_period, retry=True)
        study = optuna.create_study(
            storage=storage,
            study_name=self.name,
            direction="maximize",
            sampler=optuna.samplers.RandomSampler(seed=0),
            load_if_exists=True,
        )
        merged = merge_declarations(
            study.user_attrs.get(DECLARATION_KEY),
            self.declaration,
            self.name,
            describe_storage(self.storage, self.folder),
        )
        if merged != study.user_attrs.get(DECLARATION_KEY):
            study.set_user_attr(DECLARATION_KEY, merged)
        return study


def merge_declarations(stored: Optional[dict], new: dict, name: str, where: str) -> dict:
    """The union of a study's recorded declaration and a new one; ``ValueError`` when they declare the same
    variant (on the same environment), evaluation or training evaluations differently."""
    if stored is None:
        return new
    if stored["training"] != new["training"]:
        raise ValueError(
            f"study {name!r} in {where} was declared with other evaluations during training "
            f"({stored['training']}); results of two declarations never mix: give the study another "
            "name (--name) or storage"
        )
    for section, what in (("variants", "variant"), ("evaluations", "evaluation")):
        for key in stored[section].keys() & new[section].keys():
            old, now = stored[section][key], new[section][key]
            if old != now:
                differ = sorted(k for k in old.keys() | now.keys() if old.get(k) != now.get(k))
                raise ValueError(
                    f"study {name!r} in {where} declares {what} {key!r} otherwise (it differs in "
                    f"{', '.join(differ)}); results of two declarations never mix: give the study "
                    "another name (--name) or storage, or the variant another name"
                )
    return {
        "training": new["training"],
        **{section: {**stored[section], **new[section]} for section in ("variants", "evaluations")},
    }


def prepare(
    study: Study, folder: Path, name: str, storage: Optional[str] = None, build_models: bool = True, **options
) -> StudyJob:
    """Check a study before anything is written: every ``(env, variant)`` entry resolves, every budget can be
    checkpointed, each model is built once (``build_models``), and an existing study of that name was declared
    alike.

    :raises ValueError: one line
    """
    quiet_optuna()
    configs = {(env, variant): study.config(env, variant) for env in study.envs for variant in study.variants}
    for (env, variant), config in configs.items():
        bad = [b for b in study.budgets_of(variant) if b % config["n_envs"]]
        if bad:
            raise ValueError(
                f"budget {bad[0]} of variant {variant!r} on {env} is not a multiple of its n_envs="
                f"{config['n_envs']}: no model would be saved exactly there"
            )
    check_noises(study)
    job = StudyJob(study, Path(folder), name, storage, configs, **options)
    if build_models:
        for (env, variant), config in configs.items():
            try:
                check_model(env, config, job.device)
            except ValueError as exc:
                raise ValueError(f"variant {variant!r} on {env}: {exc}") from None
    if storage_exists(storage, job.folder):
        import optuna

        try:
            stored = optuna.load_study(study_name=name, storage=open_storage(storage, job.folder)).user_attrs
        except KeyError:
            stored = {}
        merge_declarations(stored.get(DECLARATION_KEY), job.declaration, name, describe_storage(storage, job.folder))
    return job


def check_noises(study: Study) -> None:
    """``ValueError`` unless every robustness evaluation's noise applies to every environment of the study."""
    from ..envs.noise import make_noisy_env, noise_kwargs

    for name, evaluation in study.evaluations.items():
        p = evaluation.protocol
        for env in study.envs:
            for noise in p.noises:
                try:
                    make_noisy_env(env, **noise_kwargs(noise, 0.1, p.friction_target, p.obs_indices)).close()
                except (ValueError, TypeError) as exc:
                    raise ValueError(f"evaluation {name!r}: {noise} noise cannot be applied to {env}: {exc}") from None


# ----------------------------------------------------------------------------------------------------------------
# The queue


def _by_cell(study) -> dict[str, list]:
    cells: dict[str, list] = {}
    for trial in study.get_trials(deepcopy=False):
        if "cell" in trial.user_attrs and "duplicate_of" not in trial.user_attrs:
            cells.setdefault(trial.user_attrs["cell"], []).append(trial)
    return cells


def covers(done: dict, work: dict) -> bool:
    """Whether a finished trial's work includes ``work``."""
    return done["budget"] >= work["budget"] and set(work["evaluations"]) <= set(done["evaluations"])


def queue_cells(job: StudyJob, study) -> int:
    """Queue every cell of the study that is neither waiting, running nor done; returns how many."""
    trials = _by_cell(study)
    queued = 0
    for env, variant, seed in job.study.cells():
        key, work = cell_key(env, variant, seed), job.work(variant)
        mine = trials.get(key, [])
        if any(t.state.name in ("WAITING", "RUNNING") for t in mine) or any(
            t.state.name == "COMPLETE" and covers(t.user_attrs["work"], work) for t in mine
        ):
            continue
        study.enqueue_trial({}, user_attrs={"cell": key, "work": work})
        queued += 1
    return queued


def own_cells(job: StudyJob) -> set[str]:
    """The keys of the cells that ``job`` runs (its ``--variants`` and ``--seeds``)."""
    return {cell_key(env, variant, seed) for env, variant, seed in job.study.cells()}


def owner_of(study, trial) -> Optional[int]:
    """The trial that owns ``trial``'s cell, if another one does: an earlier trial waiting or running, or a
    finished one that did this trial's work."""
    key, work = trial.user_attrs["cell"], trial.user_attrs["work"]
    for other in study.get_trials(deepcopy=False):
        if other.number == trial.number or other.user_attrs.get("cell") != key or "duplicate_of" in other.user_attrs:
            continue
        state = other.state.name
        if (state in ("WAITING", "RUNNING") and other.number < trial.number) or (
            state == "COMPLETE" and covers(other.user_attrs["work"], work)
        ):
            return other.number
    return None


class CellRunner:
    """The objective of a study worker: one cell per trial.

    :param job: the study and where it runs
    :param log: where the progress lines go
    """

    def __init__(self, job: StudyJob, log: Callable[[str], None] = print):
        self.job, self.log = job, log
        self.current: Optional[int] = None
        self.cells = own_cells(job)

    def __call__(self, trial) -> float:
        import optuna

        self.current = trial.number
        if "cell" not in trial.user_attrs:  # made by ask() when another worker took the last waiting cell
            raise optuna.TrialPruned("no cell")
        if trial.user_attrs["cell"] not in self.cells:
            # Queued by an invocation with other --variants or --seeds, whose study this worker's lacks: back to the
            # end of the queue, for a worker that runs it.
            trial.study.enqueue_trial(
                {}, user_attrs={"cell": trial.user_attrs["cell"], "work": trial.user_attrs["work"]}
            )
            trial.set_user_attr("requeued", True)
            trial.set_user_attr("duplicate_of", "queue")
            raise optuna.TrialPruned("another selection's cell")
        trial.set_user_attr("worker", worker_name())
        owner = owner_of(trial.study, trial)
        if owner is not None:
            trial.set_user_attr("duplicate_of", owner)
            raise optuna.TrialPruned(f"cell taken by trial {owner}")
        env, variant, seed = trial.user_attrs["cell"].rsplit(" ", 2)
        self.log(f"{env} {variant} seed {seed}: started (trial {trial.number})")
        try:
            written = run_cell(self.job, env, variant, int(seed), trial)
        except (optuna.TrialPruned, KeyboardInterrupt):
            raise
        except Exception as exc:
            trial.set_user_attr("error", one_line(exc))
            raise
        return float(written)


def run_worker(job: StudyJob, log: Callable[[str], None] = print) -> int:
    """Take cells until none is waiting and none is running; returns 0, or 130 when interrupted (the interrupted
    cell is queued again)."""
    import optuna
    import torch

    from ..snn.cpu_settings import keep_freed_memory

    torch.set_num_threads(job.torch_threads)
    keep_freed_memory()  # as `train` does: the training steps' buffers stay mapped
    study = job.open()
    queue_cells(job, study)
    runner = CellRunner(job, log)
    while True:
        optuna.storages.fail_stale_trials(study)
        # Only this invocation's cells keep it working (other invocations' workers run theirs).
        states = [t.state.name for t in study.get_trials(deepcopy=False) if t.user_attrs.get("cell") in runner.cells]
        if "WAITING" in states:
            try:
                study.optimize(runner, n_trials=1, catch=(Exception,), callbacks=[lambda _, t: log(cell_line(t))])
            except KeyboardInterrupt:
                interrupted = [t for t in study.get_trials(deepcopy=False) if t.number == runner.current]
                if interrupted and interrupted[0].state.name == "FAIL":
                    retry_callback(max_retry=None)(study, interrupted[0])
                    log(f"interrupted: trial {runner.current} queued again")
                return 130
        elif "RUNNING" in states:  # other workers' cells: wait, to take one over if its worker dies
            time.sleep(min(job.heartbeat_interval, POLL_INTERVAL))
        else:
            return 0


def cell_line(trial) -> str:
    """One line about a finished trial."""
    head = f"{trial.user_attrs.get('cell', '(no cell)')} (trial {trial.number})"
    if trial.state.name == "COMPLETE":
        return f"{head}: done, {int(trial.value)} file(s) written"
    if trial.state.name == "PRUNED" and trial.user_attrs.get("requeued"):
        return f"{head}: queued again for a worker of its own selection"
    if trial.state.name == "PRUNED":
        owner = trial.user_attrs.get("duplicate_of")
        return f"{head}: skipped" + (f", taken by trial {owner}" if owner is not None else "")
    return f"{head}: failed: {trial.user_attrs.get('error', 'interrupted')}"


def _worker_process(job: StudyJob, index: int) -> None:
    route_mujoco_warnings()  # a spawned process starts without the command line's route
    prefix = f"[worker {index}] "
    sys.exit(run_worker(job, lambda line: print(prefix + line, flush=True)))


def run_workers(job: StudyJob, workers: int = 1, log: Callable[[str], None] = print) -> int:
    """Run ``workers`` workers on this machine (one in this process, or each in a process of its own) and wait
    for them; returns the largest exit status."""
    if workers == 1:
        return run_worker(job, log)
    queue_cells(job, job.open())  # once, before the workers start
    context = multiprocessing.get_context("spawn")
    processes = [context.Process(target=_worker_process, args=(job, i + 1)) for i in range(workers)]
    for process in processes:
        process.start()
    try:
        for process in processes:
            process.join()
    except KeyboardInterrupt:  # the workers got it too: they queue their cells again and stop
        for process in processes:
            process.join()
        return 130
    # A worker killed by signal N (exit code -N) counts as the shell's 128 + N.
    return max(code if code >= 0 else 128 - code for code in (p.exitcode or 0 for p in processes))


# ----------------------------------------------------------------------------------------------------------------
# Status


def status_rows(job: StudyJob) -> list[dict]:
    """One row per cell: its state (``done``, ``running``, ``waiting``, ``failed``, ``not run``), worker, minutes
    and error."""
    study = job.open()
    trials = _by_cell(study)
    rows = []
    for env, variant, seed in job.study.cells():
        mine = trials.get(cell_key(env, variant, seed), [])
        work = job.work(variant)
        done = [t for t in mine if t.state.name == "COMPLETE" and covers(t.user_attrs["work"], work)]
        states = {t.state.name for t in mine}
        state = (
            "done"
            if done
            else "running"
            if "RUNNING" in states
            else "waiting"
            if "WAITING" in states
            else "failed"
            if "FAIL" in states
            else "not run"
        )
        trial = done[-1] if done else (mine[-1] if mine else None)
        minutes = (
            (trial.datetime_complete - trial.datetime_start).total_seconds() / 60
            if trial and trial.datetime_complete and trial.datetime_start
            else None
        )
        rows.append(
            dict(
                env=env,
                variant=variant,
                seed=seed,
                state=state,
                trial=trial.number if trial else None,
                minutes=None if minutes is None else round(minutes, 1),
                worker=trial.user_attrs.get("worker") if trial else None,
                error=trial.user_attrs.get("error") if trial and not done else None,
            )
        )
    return rows


def run(job: StudyJob, workers: int = 1, log: Callable[[str], None] = print) -> int:
    """``sb3-spikeplastic study``: the workers, then the cells' states and the report of what exists."""
    from .report import write_report

    cells = len(job.study.cells())
    log(
        f"Study {job.name!r} ({cells} cell{'s' if cells > 1 else ''}) in {describe_storage(job.storage, job.folder)}; "
        f"{workers} worker(s) here; raw data under {job.folder}"
    )
    status = run_workers(job, workers, log)
    rows = status_rows(job)
    counts = reduce(lambda acc, r: {**acc, r["state"]: acc.get(r["state"], 0) + 1}, rows, {})
    log("cells: " + ", ".join(f"{n} {state}" for state, n in counts.items()))
    for row in rows:
        if row["state"] == "failed":
            log(f"failed: {row['env']} {row['variant']} seed {row['seed']}: {row['error']}")
    paths = write_report(job.declared or job.study, job.folder, log=log)
    log(f"wrote {', '.join(str(p) for p in paths)}")
    return status


def study_command(
    study_file: list[str],
    workers: int = 1,
    heartbeat_interval: int = 60,
    grace_period: Optional[int] = None,
    storage: Optional[str] = None,
    study_name: Optional[str] = None,
    log_folder: str = "logs",
    folder: Optional[str] = None,
    variants=None,
    seeds=None,
    device: str = "cpu",
    torch_threads: int = 1,
    save_freq: int = 0,
) -> Callable[[], int]:
    """``sb3-spikeplastic study [report] FILE`` with these options (its long names): the study file and the study
    are checked by :func:`prepare` (``ValueError``, nothing written); returns the work (:func:`run`, or the report
    alone)."""
    from ..zoo.inputs import check_device, check_int, check_output_path
    from .declaration import load_study_file
    from .report import report_command
    from .storage import check_storage

    if len(study_file) == 2 and study_file[0] == "report":
        return report_command(study_file[1], folder, log_folder, study_name)
    if len(study_file) != 1:
        raise ValueError(f"expected `study FILE` or `study report FILE`, got {' '.join(study_file)!r}")
    for option, value, minimum in (
        ("--workers", workers, 1),
        ("--heartbeat-interval", heartbeat_interval, 1),
        ("--grace-period", grace_period, heartbeat_interval + 1),
        ("--torch-threads", torch_threads, 1),
        ("--save-freq", save_freq, 0),
    ):
        check_int(option, value, minimum)
    check_device(device)
    check_output_path(folder or log_folder, "--folder" if folder else "-f/--log-folder", directory=True)
    check_storage(storage)
    declared, path = load_study_file(study_file[0])
    study = declared.select(variants, seeds) if variants or seeds else declared
    name = study_name or path.stem
    job = prepare(
        study,
        Path(folder) if folder else Path(log_folder) / "study" / name,
        name,
        storage,
        heartbeat_interval=heartbeat_interval,
        grace_period=grace_period,
        device=device,
        torch_threads=torch_threads,
        save_freq=save_freq,
        declared=declared,
    )
    return lambda: run(job, workers)
