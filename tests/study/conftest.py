"""Fixtures of the study tests: the tiny CartPole hyperparameter file and study that the commands run in seconds,
and a real PostgreSQL server (``postgres_url``).

The server runs from a fresh folder under /tmp (data, unix socket, log), listens on 127.0.0.1 only, trusts every
local connection and is stopped, and its folder removed, when the test ends, failed or not. PostgreSQL refuses to
run as root: as root, its commands run as the ``postgres`` system user (created if missing).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shlex
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Iterator, List, Optional

import pytest

#: A CartPole hyperparameter file of a few hundred steps (MlpPolicy: no spike kernels to compile), for commands
#: that train many short runs (optimize, study).
TINY_CARTPOLE = """CartPole-v1:
  policy: MlpPolicy
  n_timesteps: 512
  n_envs: 2
  n_steps: 32
  batch_size: 32
  n_epochs: 1
"""
#: A study of two variants, two seeds and two budgets of ``cartpole.yml`` (TINY_CARTPOLE), with evaluations during
#: training, a final evaluation, a robustness evaluation and a comparison in its report.
TINY_STUDY = {
    "conf": "cartpole.yml",
    "envs": ["CartPole-v1"],
    "seeds": [0, 1],
    "budgets": [128, 256],
    "eval_freq": 64,
    "eval_episodes": 2,
    "variants": {
        "small": {"hyperparams": ["policy_kwargs.net_arch=[8]"]},
        "large": {"hyperparams": ["policy_kwargs.net_arch=[16]"]},
    },
    "evaluations": {
        "final": {"episodes": 4, "seed": 100},
        "robustness": {"noises": ["obs"], "sigmas": [0, 0.5], "episodes": 3, "n_envs": 3},
    },
    "report": {"learned_threshold": 0, "compare": [{"variants": ["large"], "against": "small"}]},
}

#: Seconds the server may take to start (pg_ctl's wait); each command is stopped 15 s after that.
TIMEOUT = 60
#: The database created in the server, the one of the yielded URL.
DATABASE = "studies"
USER = "postgres"


def find_postgres_bin() -> Optional[Path]:
    """The folder of ``initdb`` and ``pg_ctl``: from PATH, else the newest ``/usr/lib/postgresql/*/bin`` (Debian
    keeps them off PATH); ``None`` where PostgreSQL is not installed."""
    initdb = shutil.which("initdb")
    if initdb:
        folder = Path(initdb).resolve().parent  # through a symlink to the folder with the other programs
        if (folder / "pg_ctl").exists():
            return folder

    def version(folder: Path) -> tuple:
        return tuple(int(part) for part in folder.parent.name.split(".") if part.isdigit())

    folders = [p.parent for p in Path("/usr/lib/postgresql").glob("*/bin/initdb") if (p.parent / "pg_ctl").exists()]
    return max(folders, key=version, default=None)


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _as_postgres(command: List[str]) -> List[str]:
    """``command`` run as the ``postgres`` user where this process is root (the server refuses root), else as is."""
    if os.geteuid() != 0:
        return command
    if shutil.which("runuser"):
        return ["runuser", "-u", USER, "--", *command]
    return ["su", "-s", "/bin/sh", USER, "-c", shlex.join(command)]


def _postgres_user() -> pwd.struct_passwd:
    """The ``postgres`` system user (Debian's package creates it), created here if missing."""
    try:
        return pwd.getpwnam(USER)
    except KeyError:
        subprocess.run(
            ["useradd", "--system", "--user-group", "--no-create-home", "--shell", "/bin/sh", USER],
            check=True,
            capture_output=True,
            timeout=TIMEOUT,
        )
        return pwd.getpwnam(USER)


def _run(command: List[str], cwd: Path, what: str) -> None:
    """Run ``command``; ``RuntimeError`` with its output when it fails or takes over ``TIMEOUT`` + 15 seconds."""
    try:
        done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT + 15)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{what} took over {TIMEOUT + 15} s: {shlex.join(command)}") from None
    if done.returncode != 0:
        raise RuntimeError(f"{what} failed ({done.returncode}): {shlex.join(command)}\n{done.stdout}{done.stderr}")


@contextlib.contextmanager
def postgres_server(tmp_path: Path) -> Iterator[str]:
    """Start a PostgreSQL server with an empty database ``studies``; yield its SQLAlchemy URL
    (``postgresql+psycopg2://postgres@127.0.0.1:PORT/studies``).

    The server's folder is a fresh one under /tmp, not ``tmp_path``: the ``postgres`` user may not be able to reach
    ``tmp_path``, and a unix socket path must be short. At exit the server is stopped (``immediate``: its data is
    thrown away), its log copied to ``tmp_path / "postgres.log"`` (kept by pytest for a failed test) and its folder
    removed.

    :raises RuntimeError: PostgreSQL is not installed, or the server did not start (with its output)
    """
    bin_dir = find_postgres_bin()
    if bin_dir is None:
        raise RuntimeError("PostgreSQL server not installed: no initdb/pg_ctl on PATH or in /usr/lib/postgresql")
    root = Path(tempfile.mkdtemp(prefix="pg-test-", dir="/tmp" if os.path.isdir("/tmp") else None))
    data, log = root / "data", root / "server.log"
    port = free_port()
    try:
        if os.geteuid() == 0:
            user = _postgres_user()
            os.chown(root, user.pw_uid, user.pw_gid)
        _run(
            _as_postgres(
                [
                    str(bin_dir / "initdb"),
                    "-D",
                    str(data),
                    "-A",
                    "trust",
                    "-U",
                    USER,
                    "-E",
                    "UTF8",
                    "--locale=C",
                    "--no-sync",
                ]
            ),
            root,
            "initdb",
        )
        options = f"-c listen_addresses=127.0.0.1 -p {port} -k {root} -c fsync=off"
        try:
            _run(
                _as_postgres(
                    [
                        str(bin_dir / "pg_ctl"),
                        "-D",
                        str(data),
                        "-l",
                        str(log),
                        "-o",
                        options,
                        "-w",
                        "-t",
                        str(TIMEOUT),
                        "start",
                    ]
                ),
                root,
                "pg_ctl start",
            )
        except RuntimeError as exc:
            raise RuntimeError(f"{exc}\nserver log:\n{log.read_text() if log.exists() else '(none)'}") from None
        _run([str(bin_dir / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", USER, DATABASE], root, "createdb")
        yield f"postgresql+psycopg2://{USER}@127.0.0.1:{port}/{DATABASE}"
    finally:
        if (data / "postmaster.pid").exists():  # also after a start that failed or timed out
            with contextlib.suppress(RuntimeError):
                _run(
                    _as_postgres([str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop"]),
                    root,
                    "pg_ctl stop",
                )
        if log.exists():
            with contextlib.suppress(OSError):
                shutil.copyfile(log, Path(tmp_path) / "postgres.log")
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="session")
def tiny_cartpole():
    """The text of a CartPole hyperparameter file of 512 steps with MlpPolicy (runs of a second or two)."""
    return TINY_CARTPOLE


@pytest.fixture
def files(tmp_path, tiny_cartpole):
    """The test's ``tmp_path``, holding ``cartpole.yml`` (``tiny_cartpole``), the file the tiny studies name."""
    (tmp_path / "cartpole.yml").write_text(tiny_cartpole)
    return tmp_path


@pytest.fixture(scope="session")
def tiny_study():
    """The tiny study (``TINY_STUDY``) as a study file's mapping, shared by the session: deep-copy it to change it."""
    return TINY_STUDY


@pytest.fixture
def unused_port():
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    return free_port()


@pytest.fixture
def postgres_url(tmp_path):
    """The URL of a real PostgreSQL server's empty database, started for the test and stopped after it. Skips where
    PostgreSQL is not installed, except in CI (``CI=true``), which installs it: a skip there would hide a failed
    install."""
    if find_postgres_bin() is None:
        message = "PostgreSQL server not installed (apt-get install postgresql)"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    with postgres_server(tmp_path) as url:
        yield url
