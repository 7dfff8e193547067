"""The Optuna studies behind ``sb3-spikeplastic optimize`` and ``study``: where they are stored, how a worker that
died is noticed, and the check that an existing study was made with the same settings.

Storage (``--storage``):

* unset — SQLite in the study's folder, ``sqlite:///<log folder>/<study>/study.db`` (embedded: no server; several
  processes of one machine share it);
* a URL with ``://`` — an Optuna RDB storage (``sqlite:///path.db``, ``postgresql://user:pw@host/db``,
  ``mysql+pymysql://...``): the way to share a study between machines through a database server;
* anything else — the path of an Optuna journal file (``JournalStorage`` with a ``JournalFileBackend``): shared
  between machines through a shared file system (NFS), with no server.

Dead workers. A process killed in the middle of a trial leaves it ``RUNNING`` forever. Every storage opened here
records heartbeats: Optuna's own for RDB storages (``heartbeat_interval``/``grace_period``) and, for journal
files, which Optuna gives no heartbeat, :class:`JournalHeartbeatStorage`, the same interface
(``optuna.storages._heartbeat.BaseHeartbeat``) kept as a trial system attribute. ``study.optimize`` then records a
heartbeat while a trial runs and, before each new trial, fails the trials whose heartbeat is older than the grace
period (``optuna.storages.fail_stale_trials``); with ``retry=True`` Optuna's
``RetryHeartbeatStaleTrialCallback`` queues each of them again as a ``WAITING`` trial with the same parameters
(and grid cell), which the next worker to ask runs.
"""

from __future__ import annotations

import json
import os
import shlex
import socket
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

#: File of the default storage inside a study's folder.
DEFAULT_STORAGE_FILE = "study.db"
#: Seconds between heartbeats of a running trial (Optuna's suggestion); ``grace_period`` defaults to twice it.
HEARTBEAT_INTERVAL = 60
#: A trial is retried at most this often after its worker died (a cell that kills its worker every time stops).
MAX_RETRY = 3
#: Seconds SQLite waits for another process's lock before failing (its default, 5, is short for busy workers).
SQLITE_TIMEOUT = 60


def quiet_optuna() -> None:
    """Optuna's per-trial log lines off (the commands print their own) and its experimental-feature warnings
    (heartbeats, retries) silenced; ``ValueError`` when Optuna is not installed."""
    try:
        import optuna
    except ImportError:
        raise ValueError('optimize and study need Optuna: pip install "sb3-spikeplastic[optimize]"') from None

    optuna.logging.set_verbosity(optuna.logging.ERROR)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)


def default_storage_url(folder: Path) -> str:
    """The embedded default storage of a study whose folder is ``folder``."""
    return f"sqlite:///{Path(folder).resolve() / DEFAULT_STORAGE_FILE}"


def is_url(storage: str) -> bool:
    """Whether ``--storage`` names an RDB URL (else: a journal file path)."""
    return "://" in storage


def check_storage(storage: Optional[str]) -> None:
    """``ValueError`` unless a ``--storage`` journal file (not a URL) could be written."""
    from ..zoo.inputs import check_output_path

    if storage is not None and not is_url(storage):
        check_output_path(storage, "--storage", directory=False)


def _journal_heartbeat_class():
    from optuna.storages import JournalStorage
    from optuna.storages._heartbeat import BaseHeartbeat
    from optuna.trial import TrialState

    class JournalHeartbeatStorage(JournalStorage, BaseHeartbeat):
        """A journal storage with heartbeats, which Optuna's ``JournalStorage`` lacks: a running trial's heartbeat
        is its system attribute ``heartbeat`` (seconds since the epoch of the worker's clock; the machines' clocks
        must agree to well within ``grace_period``), and a ``RUNNING`` trial whose latest heartbeat (or start) is
        older than ``grace_period`` seconds is stale.

        :param backend: the journal backend (a ``JournalFileBackend``)
        :param heartbeat_interval: seconds between heartbeats
        :param grace_period: seconds after which a silent running trial is stale
        :param stale_callback: called with ``(study, trial)`` for each trial failed as stale
        """

        def __init__(
            self, backend, heartbeat_interval: int, grace_period: int, stale_callback: Optional[Callable] = None
        ):
            super().__init__(backend)
            self.heartbeat_interval, self.grace_period = heartbeat_interval, grace_period
            self.stale_callback = stale_callback

        def record_heartbeat(self, trial_id: int) -> None:
            self.set_trial_system_attr(trial_id, "heartbeat", time.time())

        def _get_stale_trial_ids(self, study_id: int) -> list[int]:
            now = time.time()
            stale = []
            for trial in self.get_all_trials(study_id, deepcopy=False, states=(TrialState.RUNNING,)):
                # A retried trial inherits the stale trial's attributes: its own start counts too.
                started = trial.datetime_start.timestamp() if trial.datetime_start else 0.0
                if now - max(trial.system_attrs.get("heartbeat", 0.0), started) > self.grace_period:
                    stale.append(trial._trial_id)
            return stale

        def get_heartbeat_interval(self) -> int:
            return self.heartbeat_interval

        def get_heartbeat_stale_trial_callback(self) -> Optional[Callable]:
            return self.stale_callback

    return JournalHeartbeatStorage


def _serialise_sqlite(engine) -> None:
    """Every SQLite transaction of ``engine`` starts with ``BEGIN IMMEDIATE`` (SQLAlchemy's recipe for pysqlite).

    Optuna takes a waiting trial by reading that it waits and marking it running in one transaction, atomic on a
    server through ``SELECT ... FOR UPDATE``; SQLite ignores that, and its default deferred transactions let two
    processes both read "waiting" before either writes, so that both run the same cell. An immediate transaction
    holds the write lock from its first statement: the second process reads "running" and takes another trial.
    """
    from sqlalchemy import event

    @event.listens_for(engine, "begin")
    def _begin(connection):
        connection.exec_driver_sql("BEGIN IMMEDIATE")


def retry_callback(max_retry: Optional[int] = MAX_RETRY) -> Callable:
    """Optuna's callback that queues a trial again as a ``WAITING`` copy (its parameters, grid cell and
    attributes), at most ``max_retry`` times per original trial (``None``: always)."""
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    return RetryHeartbeatStaleTrialCallback(max_retry=max_retry)


def open_storage(
    storage: Optional[str],
    folder: Path,
    heartbeat_interval: int = HEARTBEAT_INTERVAL,
    grace_period: Optional[int] = None,
    retry: bool = False,
):
    """The Optuna storage that ``--storage`` names, with heartbeats (see the module docstring).

    :param storage: ``None`` (SQLite in ``folder``), an RDB URL or a journal file path
    :param folder: the study's folder (created for the default storage)
    :param heartbeat_interval: seconds between heartbeats of a running trial
    :param grace_period: seconds without a heartbeat after which a running trial is failed (default: twice the
        interval)
    :param retry: queue each trial failed that way again (grid cells), instead of leaving it failed
    :raises ValueError: one line when the storage cannot be opened
    """
    import optuna

    quiet_optuna()
    grace_period = grace_period or 2 * heartbeat_interval
    callback = retry_callback() if retry else None
    if storage is None:
        Path(folder).mkdir(parents=True, exist_ok=True)
        storage = default_storage_url(folder)
    try:
        if is_url(storage):
            sqlite = storage.startswith("sqlite")
            # The driver's own transaction handling off (isolation_level None): see _serialise_sqlite.
            engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT, "isolation_level": None}} if sqlite else {}
            rdb = optuna.storages.RDBStorage(
                storage,
                engine_kwargs=engine_kwargs,
                heartbeat_interval=heartbeat_interval,
                grace_period=grace_period,
                heartbeat_stale_trial_callback=callback,
            )
            if sqlite:
                _serialise_sqlite(rdb.engine)
            return rdb
        from optuna.storages.journal import JournalFileBackend

        Path(storage).parent.mkdir(parents=True, exist_ok=True)
        return _journal_heartbeat_class()(JournalFileBackend(str(storage)), heartbeat_interval, grace_period, callback)
    except Exception as exc:  # SQLAlchemy's errors for a bad URL, a missing driver, a refused connection...
        message = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(
            f"cannot open the storage {masked(storage)!r}: {message.replace(storage, masked(storage))}"
        ) from None


def masked(storage: str) -> str:
    """A storage URL with its password replaced by ``***`` (messages and logs never show it)."""
    if not is_url(storage):
        return storage
    try:
        from sqlalchemy.engine import make_url

        return make_url(storage).render_as_string(hide_password=True)
    except Exception:  # not a URL SQLAlchemy reads: hide whatever stands between ':' and '@'
        import re

        return re.sub(r"(://[^:/@]*:)[^@]*@", r"\1***@", storage)


def describe_storage(storage: Optional[str], folder: Path) -> str:
    """What ``--storage`` stands for, for messages (a URL without its password)."""
    if storage is None:
        return default_storage_url(folder)
    return masked(storage) if is_url(storage) else f"journal file {storage}"


def storage_exists(storage: Optional[str], folder: Path) -> bool:
    """Whether the storage may already hold studies (a file storage that is not there holds none)."""
    if storage is None:
        return (Path(folder) / DEFAULT_STORAGE_FILE).exists()
    if storage.startswith("sqlite:///"):
        return Path(storage[len("sqlite:///") :]).exists()
    return is_url(storage) or Path(storage).exists()


def _plain(value: Any) -> Any:
    """``value`` as it reads back from a storage (JSON: tuples as lists)."""
    return json.loads(json.dumps(value))


def check_settings(storage, study_name: str, key: str, settings: dict) -> None:
    """``ValueError`` if ``storage`` holds a study ``study_name`` made with other ``settings`` (its user attribute
    ``key``): trials trained otherwise would be compared, or counted as cells of another grid.

    :param storage: an opened storage
    :param study_name: the study
    :param key: the user attribute that holds the settings
    :param settings: what this command would run (JSON data)
    """
    import optuna

    try:
        stored = optuna.load_study(study_name=study_name, storage=storage).user_attrs.get(key)
    except KeyError:  # no such study yet
        return
    settings = _plain(settings)
    if stored is not None and stored != settings:
        differ = sorted(k for k in set(stored) | set(settings) if stored.get(k) != settings.get(k))
        raise ValueError(
            f"study {study_name!r} holds a {key} with other settings (they differ in "
            f"{', '.join(differ)}); give another --study-name, or the same settings to continue it"
        )


def create_study(storage, study_name: str, key: str, settings: dict, sampler=None, pruner=None):
    """Create or load the study ``study_name`` (maximising), recording ``settings`` under the user attribute
    ``key`` when it is new (:func:`check_settings` compared them before)."""
    import optuna

    study = optuna.create_study(
        storage=storage,
        study_name=study_name,
        sampler=sampler,
        pruner=pruner,
        direction="maximize",
        load_if_exists=True,
    )
    if key not in study.user_attrs:
        study.set_user_attr(key, _plain(settings))
    return study


def count_states(study) -> dict[str, int]:
    """Number of trials per state name (``COMPLETE``, ``PRUNED``, ``FAIL``, ``RUNNING``, ``WAITING``)."""
    counts: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        counts[trial.state.name] = counts.get(trial.state.name, 0) + 1
    return counts


def train_command(
    env_id: str,
    conf: Optional[str],
    rule: Optional[str],
    overrides: Sequence[str],
    seed: int,
    n_timesteps: int,
    eval_freq: int,
    eval_episodes: int,
) -> str:
    """The ``sb3-spikeplastic train`` command that trains the same run as a trial or a grid cell (written to the
    run folder's ``command.txt``)."""
    argv = [
        "sb3-spikeplastic",
        "train",
        "--env",
        env_id,
        *(["--conf", str(conf)] if conf else []),
        *(["--rule", rule] if rule else []),
        "--seed",
        str(seed),
        "-n",
        str(n_timesteps),
        "--eval-freq",
        str(eval_freq),
        "--eval-episodes",
        str(eval_episodes),
        *(["--hyperparams", *overrides] if overrides else []),
    ]
    return shlex.join(argv)


def check_model(env_id: str, config: dict, device: str = "cpu") -> None:
    """Build the environments and the model of a resolved entry once, in memory, as ``train`` does before it
    writes anything: ``ValueError`` (one line) for combinations that only the constructors reject."""
    from ..zoo.experiment import Experiment

    try:
        Experiment(env_id, config, 0, Path("."), device=device, verbose=0, progress=False).setup()
    except (ValueError, TypeError, AssertionError) as exc:
        raise ValueError(" ".join(str(exc).split()) or type(exc).__name__) from None
    except Exception as exc:  # gymnasium's errors for bad env_kwargs
        if not type(exc).__module__.startswith("gymnasium"):
            raise
        raise ValueError(f"cannot make {env_id} with env_kwargs={config.get('env_kwargs')}: {exc}") from None


def worker_name() -> str:
    """``host:pid``: which process ran a trial (its user attribute ``worker``)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def one_line(exc: BaseException) -> str:
    """An exception as one line, ``Type: message``: the reason a trial failed (its user attribute ``error``)."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}".rstrip(": ")
