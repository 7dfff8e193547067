import subprocess
import sys


def test_envs_live_in_the_plugin_namespace(tmp_path):
    """``envs/`` installs as ``sb3_spikeplastic.envs`` only: outside the source tree no top-level ``envs`` exists."""
    import sb3_spikeplastic.envs  # noqa: F401

    code = "import importlib.util; print(importlib.util.find_spec('envs'))"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "None"
