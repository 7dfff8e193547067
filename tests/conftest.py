import os

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    """One intra-op thread for the whole suite, as the CLI and the study workers use: the network's small ops gain
    nothing from more, and on a loaded machine OpenMP spinning makes them 10x+ slower (measured here: 2 threads
    next to a busy process, 0.5 s -> 9 s per test)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _built(monkeypatch, cuda: bool):
    """The compiled ops (built on first use, even where ``SB3_SPIKEPLASTIC_NO_COMPILE`` is set), or a skip naming
    the build error."""
    import warnings

    from sb3_spikeplastic.snn import _fast

    monkeypatch.delenv(_fast.NO_COMPILE_ENV, raising=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ops = _fast.load_cuda_ops() if cuda else _fast.load_ops()
    if ops is None:
        pytest.skip(f"{'CUDA' if cuda else 'compiled'} ops unavailable: {_fast.build_error(cuda=cuda)}")
    return ops


@pytest.fixture
def compiled_ops(monkeypatch):
    """The compiled CPU ops; skips where they cannot be built."""
    return _built(monkeypatch, cuda=False)


@pytest.fixture
def compiled_cuda_ops(monkeypatch):
    """The compiled CUDA ops; skips without a CUDA device or where they cannot be built."""
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    return _built(monkeypatch, cuda=True)


@pytest.fixture
def postgres_url(tmp_path):
    """The URL of a real PostgreSQL server's empty database, started for the test and stopped after it
    (tests/postgres_server.py). Skips where PostgreSQL is not installed, except in CI (``CI=true``), which installs
    it: a skip there would hide a failed install."""
    from postgres_server import find_postgres_bin, postgres_server

    if find_postgres_bin() is None:
        message = "PostgreSQL server not installed (apt-get install postgresql)"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    with postgres_server(tmp_path) as url:
        yield url
