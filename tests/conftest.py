"""Fixtures of the whole suite. Each test folder mirrors a subpackage (tests/snn, tests/sb3, tests/zoo, tests/study,
tests/envs); tests/study/conftest.py adds the study files and the PostgreSQL server, tests/envs/conftest.py the
action recorder. The small T-maze models are plain functions in tests/sb3/helpers.py (on pytest's pythonpath)."""

import io
import os
from pathlib import Path

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


@pytest.fixture(autouse=True, scope="session")
def _mujoco_warnings_routed():
    """MuJoCo's warnings routed as the command line routes them: HalfCheetah's deprecation notice would otherwise
    append to ./MUJOCO_LOG.TXT in the folder the suite runs from."""
    import mujoco

    from sb3_spikeplastic.envs import route_mujoco_warnings

    previous = mujoco.get_mju_user_warning()
    route_mujoco_warnings()
    yield
    mujoco.set_mju_user_warning(previous)


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


@pytest.fixture(
    params=[
        "cpu",
        pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")),
    ]
)
def device(request):
    """Every available device: ``cpu`` and, where present, ``cuda`` (a test per device)."""
    return request.param


#: The T-maze entry shrunk to one 64-step rollout per update (2 environments x 32 steps) and 16 hidden neurons:
#: ``--hyperparams`` of the commands that train spiking models in a second or two.
TINY_TMAZE = (
    "n_envs=2",
    "n_steps=32",
    "batch_size=32",
    "bptt_steps=16",
    "n_epochs=1",
    "policy_kwargs.hidden_sizes=[16]",
)


@pytest.fixture(scope="session")
def tiny_tmaze():
    """``--hyperparams`` overrides that make the T-maze entry train in a second or two (a list: ``*tiny_tmaze``)."""
    return list(TINY_TMAZE)


@pytest.fixture
def run_cli(capsys):
    """``run_cli(*argv)`` runs ``sb3-spikeplastic ARGV`` in this process and returns ``(exit status, stdout,
    stderr)``; the arguments may be paths or numbers."""
    from sb3_spikeplastic import cli

    def run(*argv):
        code = cli.main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture
def mujoco_log_in_tmp(tmp_path, monkeypatch):
    """The test's working directory is its ``tmp_path``: MuJoCo 4.0 warns that HalfCheetah's ``settotalmass`` is
    deprecated and appends that to ./MUJOCO_LOG.TXT."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _assert_png(image):
    """``image`` (PNG bytes, or the path of a PNG file) is a picture: over 5 kB, in colour, more than one colour."""
    import matplotlib.image

    if isinstance(image, (str, os.PathLike)):
        assert Path(image).is_file(), image
        image = Path(image).read_bytes()
    assert len(image) > 5_000
    pixels = matplotlib.image.imread(io.BytesIO(image), format="png")
    assert pixels.ndim == 3
    pixels = pixels.reshape(-1, pixels.shape[-1])
    assert (pixels != pixels[0]).any()  # more than one colour


@pytest.fixture(scope="session")
def assert_png():
    """``assert_png(image)``: fails unless ``image`` (PNG bytes or a path) is a picture of more than one colour."""
    return _assert_png
