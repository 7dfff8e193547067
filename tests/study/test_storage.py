"""The studies' storage: Optuna studies in a real PostgreSQL server (started by the ``postgres_url`` fixture), the
way studies are shared between machines, the error for a server that cannot be reached, and the install hint where
Optuna is missing."""

import sys

import pytest

from sb3_spikeplastic.study.storage import open_storage


@pytest.fixture
def optuna():
    """Optuna, with psycopg2 for PostgreSQL URLs (skips without them)."""
    pytest.importorskip("psycopg2")
    return pytest.importorskip("optuna")


def test_study_round_trip(optuna, postgres_url, tmp_path):
    """Trials run through the project's storage (with heartbeats and retries) read back from another storage."""
    storage = open_storage(postgres_url, tmp_path, heartbeat_interval=1, grace_period=3, retry=True)
    study = optuna.create_study(study_name="smoke", storage=storage, direction="maximize")
    study.optimize(lambda trial: 1.0, n_trials=2)

    again = optuna.load_study(study_name="smoke", storage=open_storage(postgres_url, tmp_path))
    assert [t.state for t in again.trials] == [optuna.trial.TrialState.COMPLETE] * 2
    assert [t.value for t in again.trials] == [1.0, 1.0]
    assert again.best_value == 1.0


@pytest.fixture
def unreachable_error(optuna, unused_port, tmp_path) -> str:
    """The message of ``open_storage`` for a PostgreSQL URL (with a password) where no server listens."""
    with pytest.raises(ValueError) as error:
        open_storage(f"postgresql+psycopg2://u:secret@127.0.0.1:{unused_port}/x", tmp_path)
    return str(error.value)


def test_unreachable_server_is_one_line(unreachable_error):
    assert "\n" not in unreachable_error and "127.0.0.1" in unreachable_error


def test_unreachable_server_hides_password(unreachable_error):
    assert "secret" not in unreachable_error


def test_optimize_without_optuna_is_the_install_hint(tmp_path, run_cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna fails as if it were not installed
    code, out, err = run_cli("optimize", "--env", "TMazeCue-v0", "-f", tmp_path / "logs")
    assert code == 2 and err.count("\n") == 1, err
    assert 'need Optuna: pip install "sb3-spikeplastic[optimize]"' in err and "Traceback" not in err
    assert not (tmp_path / "logs").exists()
