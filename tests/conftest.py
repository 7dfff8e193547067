import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    """One intra-op thread for the whole suite, as the CLI and the experiments use: the network's small ops gain
    nothing from more, and on a loaded machine OpenMP spinning makes them 10x+ slower (measured here: 2 threads
    next to a busy process, 0.5 s -> 9 s per test)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
