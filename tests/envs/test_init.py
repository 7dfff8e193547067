"""The environments package (``sb3_spikeplastic.envs``): it registers every id, again silently when reloaded,
imports neither torch nor the rest of the plugin, and routes MuJoCo's warnings away from ./MUJOCO_LOG.TXT."""

import ast
import importlib
import sys
import warnings
from pathlib import Path

import gymnasium
import pytest

import sb3_spikeplastic.envs

IDS = ("TMazeCue-v0", "TMazeCueNoisy-v0", "NoisyHalfCheetah-v5", "HalfCheetahSwitch-v5")


def test_importing_registers_every_id_and_a_reload_is_silent(monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the ids are registered already: gymnasium would warn if registered again
        importlib.reload(sb3_spikeplastic.envs)
    for env_id in IDS:
        monkeypatch.delitem(gymnasium.registry, env_id)  # put back after the test
    importlib.reload(sb3_spikeplastic.envs)
    assert [env_id for env_id in IDS if env_id in gymnasium.registry] == list(IDS)
    assert gymnasium.registry["TMazeCueNoisy-v0"].kwargs == {"noise": "high"}


def test_envs_import_neither_torch_nor_the_plugin():
    allowed = {*sys.stdlib_module_names, "gymnasium", "numpy", "mujoco", "sb3_spikeplastic"}
    for source in Path(sb3_spikeplastic.envs.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module]
            else:
                continue
            for name in names:
                assert name.split(".")[0] in allowed, (source.name, name)
                if name.startswith("sb3_spikeplastic"):
                    assert name.startswith("sb3_spikeplastic.envs"), (source.name, name)


def test_route_mujoco_warnings_drops_the_halfcheetah_deprecation_and_the_log_file(mujoco_log_in_tmp):
    """Without the route, every HalfCheetah build appends MuJoCo's `settotalmass` deprecation to ./MUJOCO_LOG.TXT;
    with it, nothing is written and no Python warning is raised; MuJoCo's other warnings become RuntimeWarnings."""
    import mujoco

    from sb3_spikeplastic.envs import route_mujoco_warnings

    previous = mujoco.get_mju_user_warning()
    try:
        mujoco.set_mju_user_warning(None)  # MuJoCo's own handler, whatever an earlier test installed
        gymnasium.make("HalfCheetah-v5").close()
        assert (mujoco_log_in_tmp / "MUJOCO_LOG.TXT").exists()
        (mujoco_log_in_tmp / "MUJOCO_LOG.TXT").unlink()
        route_mujoco_warnings()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            gymnasium.make("HalfCheetah-v5").close()
        assert not (mujoco_log_in_tmp / "MUJOCO_LOG.TXT").exists()
        with pytest.warns(RuntimeWarning, match="^MuJoCo: too many contacts$"):
            mujoco.get_mju_user_warning()("too many contacts\n")
    finally:
        mujoco.set_mju_user_warning(previous)
