"""The package as installed: where the environments live, what importing it loads (torch and Stable-Baselines3
only on first use of a public name) and its public names."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_envs_live_in_the_plugin_namespace(tmp_path):
    """``envs/`` installs as ``sb3_spikeplastic.envs`` only: outside the source tree no top-level ``envs`` exists."""
    import sb3_spikeplastic.envs  # noqa: F401

    code = "import importlib.util; print(importlib.util.find_spec('envs'))"
    # outside the source tree: neither the working directory nor a PYTHONPATH entry is the checkout
    paths = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and Path(p).resolve() != ROOT]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True, env=env
    )
    assert out.stdout.strip() == "None"


def _modules_after(code: str, tmp_path) -> set[str]:
    """Top-level modules loaded by ``code`` in a fresh interpreter."""
    script = code + "\nimport sys; print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_envs_stand_alone(tmp_path):
    """The environments (and their registration) need neither torch nor Stable-Baselines3."""
    loaded = _modules_after(
        "import gymnasium, sb3_spikeplastic.envs; gymnasium.make('TMazeCue-v0').reset(seed=0)", tmp_path
    )
    assert "gymnasium" in loaded and "torch" not in loaded and "stable_baselines3" not in loaded


def test_cli_help_does_not_load_torch(tmp_path):
    loaded = _modules_after(
        "import contextlib, io\nfrom sb3_spikeplastic.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    assert main(['train', '--help']) == 0",
        tmp_path,
    )
    assert "torch" not in loaded and "stable_baselines3" not in loaded


def test_public_names_load_on_first_use(tmp_path):
    import sb3_spikeplastic
    from sb3_spikeplastic.sb3.ablation import Ablation, ablated
    from sb3_spikeplastic.sb3.modulation import ModulationSource, register_modulation_source
    from sb3_spikeplastic.sb3.policy import SpikePlasticPolicy
    from sb3_spikeplastic.sb3.ppo import PPO
    from sb3_spikeplastic.snn.plasticity import PlasticityRule, available_rules, register_rule
    from sb3_spikeplastic.zoo.config import load_hyperparams

    public = {
        "PPO": PPO,
        "SpikePlasticPolicy": SpikePlasticPolicy,
        "PlasticityRule": PlasticityRule,
        "register_rule": register_rule,
        "available_rules": available_rules,
        "load_hyperparams": load_hyperparams,
        "Ablation": Ablation,
        "ablated": ablated,
        "ModulationSource": ModulationSource,
        "register_modulation_source": register_modulation_source,
    }
    assert sorted(sb3_spikeplastic.__all__) == sorted(public)
    for name, value in public.items():
        assert getattr(sb3_spikeplastic, name) is value, name
    assert "dp-oja" in sb3_spikeplastic.available_rules()
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        sb3_spikeplastic.Nope
    # dir() lists the public names before they are loaded (in a fresh interpreter, before torch is)
    code = "import sb3_spikeplastic, sys; print(' '.join(dir(sb3_spikeplastic)), 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    *names, torch_loaded = out.stdout.split()
    assert set(public) <= set(names) and torch_loaded == "False"
