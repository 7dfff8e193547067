"""The CPU settings of spiking models (flush-to-zero, the block cache) hold only while a model trains or evaluates:
building a model changes no process-wide setting, and each is put back as it was. In subprocesses: both settings
are process-wide."""

import ast
import os
import subprocess
import sys

import pytest

from sb3_spikeplastic.snn import _fast

SETTINGS = """
import sys, torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from sb3_spikeplastic import PPO
from sb3_spikeplastic.snn.cpu_settings import block_cache_active, flush_denormal_enabled
from sb3_spikeplastic.zoo.run_folder import cpu_settings_of
torch.set_num_threads(1)
flags = dict(flush_denormal=sys.argv[1] == "on", keep_freed_memory=sys.argv[1] == "on")
if sys.argv[2] == "user-flush":
    torch.set_flush_denormal(True)
seen = {}


def state():
    return flush_denormal_enabled(), block_cache_active()


class Inside(BaseCallback):
    def _on_step(self):
        seen["learn"] = state()
        return True


seen["start"] = state()
env = make_vec_env("TMazeCue-v0", n_envs=2, env_kwargs=dict(neurons_per_population=4))
model = PPO("SpikePlasticPolicy", env, n_steps=32, batch_size=32, bptt_steps=16, n_epochs=1,
            policy_kwargs=dict(hidden_sizes=(16,)), device="cpu", **flags)
seen["built"] = state()
model.learn(64, callback=Inside())
seen["learned"] = state()
with cpu_settings_of(model):
    seen["evaluating"] = state()
seen["evaluated"] = state()
mlp = PPO("MlpPolicy", make_vec_env("CartPole-v1", n_envs=1), n_steps=16, batch_size=16)
mlp.learn(16)
with cpu_settings_of(mlp):
    seen["mlp"] = state()
print(seen)
"""


def settings_seen(flags: str, start: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != _fast.NO_COMPILE_ENV}
    result = subprocess.run(
        [sys.executable, "-c", SETTINGS, flags, start], capture_output=True, text=True, timeout=300, env=env
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return ast.literal_eval(result.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def compiled():
    if _fast.load_ops() is None:
        pytest.skip(f"compiled ops unavailable: {_fast.build_error()}")


def test_settings_hold_only_inside_learn_and_evaluation(compiled):
    seen = settings_seen("on", "plain")
    off = (False, False)
    assert seen["start"] == seen["built"] == off  # building a model changes nothing
    assert seen["learn"] == (True, True)
    assert seen["learned"] == off  # both put back
    assert seen["evaluating"] == (True, False)  # flush-to-zero, no block cache outside training
    assert seen["evaluated"] == off
    assert seen["mlp"] == off  # SB3's own policies run as they are


def test_a_model_told_not_to_leaves_the_settings_alone(compiled):
    seen = settings_seen("off", "plain")
    assert {name: value for name, value in seen.items()} == dict.fromkeys(seen, (False, False))


def test_the_users_own_flush_mode_is_kept(compiled):
    seen = settings_seen("on", "user-flush")
    assert seen["start"] == seen["built"] == seen["learned"] == seen["evaluated"] == (True, False)
    assert seen["learn"] == (True, True)


HEAP = """
import os, sys, torch
from sb3_spikeplastic.snn.cpu_settings import keep_freed_memory, spiking_cpu_settings


def rss_mib():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


keep_freed_memory()  # freed blocks below 32 MiB stay in the heap
before = rss_mib()
with spiking_cpu_settings(cache_blocks=sys.argv[1] == "cache"):
    blocks = [torch.ones(2 * 1024**2) for _ in range(24)]  # 24 blocks of 8 MiB, every page touched
    del blocks
print(rss_mib() - before)
"""


def resident_growth_mib(cache: str) -> float:
    env = {k: v for k, v in os.environ.items() if k != _fast.NO_COMPILE_ENV}
    result = subprocess.run([sys.executable, "-c", HEAP, cache], capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    return float(result.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap")
def test_taking_the_block_cache_down_returns_the_freed_heap(compiled):
    # Without the cache the freed 192 MiB stay resident under keep_freed_memory's thresholds (the control); with
    # it, its exit hands them back, so the next training's blocks do not land beside them.
    assert resident_growth_mib("no-cache") > 150
    assert resident_growth_mib("cache") < 40
