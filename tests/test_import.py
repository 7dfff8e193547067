import subprocess
import sys

import pytest


def test_envs_live_in_the_plugin_namespace(tmp_path):
    """``envs/`` installs as ``sb3_spikeplastic.envs`` only: outside the source tree no top-level ``envs`` exists."""
    import sb3_spikeplastic.envs  # noqa: F401

    code = "import importlib.util; print(importlib.util.find_spec('envs'))"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "None"


def _modules_after(code: str, tmp_path) -> set[str]:
    """Top-level modules loaded by ``code`` in a fresh interpreter."""
    script = code + "\nimport sys; print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_envs_stand_alone(tmp_path):
    """The environments (and their registration) need neither torch nor Stable-Baselines3."""
    loaded = _modules_after("import gymnasium, sb3_spikeplastic.envs; gymnasium.make('TMazeCue-v0').reset(seed=0)",
                            tmp_path)
    assert "gymnasium" in loaded and "torch" not in loaded and "stable_baselines3" not in loaded


def test_cli_help_does_not_load_torch(tmp_path):
    loaded = _modules_after("import contextlib, io\nfrom sb3_spikeplastic.cli import main\n"
                            "with contextlib.redirect_stdout(io.StringIO()):\n    assert main(['train', '--help']) == 0",
                            tmp_path)
    assert "torch" not in loaded and "stable_baselines3" not in loaded


def test_public_names_load_on_first_use():
    import sb3_spikeplastic
    from sb3_spikeplastic.sb3.policy import SpikePlasticPolicy

    assert sb3_spikeplastic.SpikePlasticPolicy is SpikePlasticPolicy
    assert "dp-oja" in sb3_spikeplastic.available_rules()
    assert set(sb3_spikeplastic.__all__) <= set(dir(sb3_spikeplastic))
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        sb3_spikeplastic.Nope
