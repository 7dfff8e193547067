"""Optuna studies in a real PostgreSQL server (started by the ``postgres_url`` fixture), the way studies are shared
between machines, and the error for a server that cannot be reached."""

import pytest

from postgres_server import free_port

optuna = pytest.importorskip("optuna")
pytest.importorskip("psycopg2")

from sb3_spikeplastic.study.storage import open_storage  # noqa: E402


def test_study_round_trip(postgres_url, tmp_path):
    """Trials run through the project's storage (with heartbeats and retries) read back from another storage."""
    storage = open_storage(postgres_url, tmp_path, heartbeat_interval=1, grace_period=3, retry=True)
    study = optuna.create_study(study_name="smoke", storage=storage, direction="maximize")
    study.optimize(lambda trial: 1.0, n_trials=2)

    again = optuna.load_study(study_name="smoke", storage=open_storage(postgres_url, tmp_path))
    assert [t.state for t in again.trials] == [optuna.trial.TrialState.COMPLETE] * 2
    assert [t.value for t in again.trials] == [1.0, 1.0]
    assert again.best_value == 1.0


def _unreachable_error(tmp_path) -> str:
    """The message of ``open_storage`` for a PostgreSQL URL (with a password) where no server listens."""
    with pytest.raises(ValueError) as error:
        open_storage(f"postgresql+psycopg2://u:secret@127.0.0.1:{free_port()}/x", tmp_path)
    return str(error.value)


def test_unreachable_server_is_one_line(tmp_path):
    message = _unreachable_error(tmp_path)
    assert "\n" not in message and "127.0.0.1" in message


def test_unreachable_server_hides_password(tmp_path):
    assert "secret" not in _unreachable_error(tmp_path)
