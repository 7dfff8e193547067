"""``sb3-spikeplastic enjoy``: episodes played with the recurrent state carried, videos (one frame per reset and per
step), the choice of MuJoCo's OpenGL backend, and bad input."""

import importlib.util
import os
import re
from pathlib import Path

import gymnasium
import imageio
import numpy as np
import pytest

from sb3_spikeplastic import cli
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.zoo import enjoy

#: .mp4 videos need the ffmpeg binary of imageio-ffmpeg (the test extras install it; a GIF needs only Pillow)
needs_ffmpeg = pytest.mark.skipif(
    importlib.util.find_spec("imageio_ffmpeg") is None, reason="imageio-ffmpeg is not installed"
)


@pytest.fixture(scope="module")
def tmaze_run(tmp_path_factory, tiny_tmaze):
    """A run folder of a spiking plastic PPO trained for 64 steps on the T-maze."""
    logs = tmp_path_factory.mktemp("enjoy") / "logs"
    argv = [
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "64",
        "--seed",
        "0",
        "-f",
        logs,
        "--hyperparams",
        *tiny_tmaze,
        "-v",
        "0",
        "--no-progress",
    ]
    assert cli.main([str(a) for a in argv]) == 0
    return logs / "ppo" / "TMazeCue-v0_1"


def episode_lengths(out: str) -> list[int]:
    return [int(n) for n in re.findall(r"^episode \d+: return \S+, (\d+) steps", out, flags=re.M)]


@needs_ffmpeg
def test_tmaze_video_has_one_frame_per_reset_and_per_step(tmaze_run, tmp_path, run_cli):
    video = tmp_path / "videos" / "tmaze.mp4"
    code, out, err = run_cli("enjoy", "--run", tmaze_run, "--n-episodes", "2", "--video", video, "--no-progress")
    assert code == 0, err
    lengths = episode_lengths(out)
    assert len(lengths) == 2 and all(16 <= n <= 19 for n in lengths)  # the T-maze's 16, 17 or 19 frames
    assert "success rate" in out and f"wrote {video}: {sum(lengths) + 2} frames" in out
    with imageio.get_reader(video) as reader:
        assert reader.count_frames() == sum(lengths) + 2  # the rule: n_1 + n_2 steps + one reset frame each
        assert reader.get_meta_data()["fps"] == 4  # a 25 ms frame shown for 250 ms: ten times slower than real time
        # 40 neurons x 25 ms, 8 x 8 pixels each, under an 18 px strip naming the populations
        assert reader.get_meta_data()["size"] == (320, 218)
    assert sorted(p.name for p in video.parent.iterdir()) == ["tmaze.mp4"]  # no temporary file left


def test_tmaze_gif_with_fps_and_size(tmaze_run, tmp_path, run_cli):
    video = tmp_path / "tmaze.gif"
    code, out, err = run_cli(
        "enjoy",
        "--run",
        tmaze_run,
        "--video",
        video,
        "--fps",
        "5",
        "--size",
        "80",
        "50",
        "--seed",
        "3",
        "--stochastic",
        "--no-progress",
    )
    assert code == 0, err
    frames = imageio.v3.imread(video, index=None)
    # random spike rasters are never identical from one frame to the next, so the GIF keeps every frame
    assert frames.shape == (episode_lengths(out)[0] + 1, 50, 80, 3)
    assert imageio.v3.immeta(video)["duration"] == 200  # ms per frame at 5 fps


@needs_ffmpeg
def test_raster_beside_the_frames_while_the_network_records(tmaze_run, tmp_path, run_cli):
    from sb3_spikeplastic import PPO

    model = PPO.load(tmaze_run / "TMazeCue-v0.zip")
    snn = model.policy.snn
    player = enjoy.Player(model, "TMazeCue-v0", video=tmp_path / "raster.mp4", raster=True)
    (episode,) = player.run(progress=False)
    assert not snn._forward_hooks and not snn._forward_pre_hooks  # detached afterwards
    with imageio.get_reader(tmp_path / "raster.mp4") as reader:
        frames = np.stack(list(reader.iter_data()))
    # 320 px of maze (218 high with its caption), a 4 px gap, 200 ms (8 steps of 25 ms) of 16 hidden neurons
    assert frames.shape == (episode.length + 1, 218, 524, 3)
    assert frames[0, :, 330:].max() < 128 and frames[-1, :, 330:].max() > 200  # empty at reset, spikes later

    mlp = PPO("MlpPolicy", "TMazeCue-v0", n_steps=16, batch_size=16)
    mlp.save(tmp_path / "mlp.zip")
    code, _, err = run_cli(
        "enjoy", "--model", tmp_path / "mlp.zip", "--env", "TMazeCue-v0", "--video", tmp_path / "mlp.mp4", "--raster"
    )
    assert code == 2 and "--raster needs a SpikePlasticPolicy model, not ActorCriticPolicy" in err
    assert not (tmp_path / "mlp.mp4").exists()


def test_play_carries_the_recurrent_state_and_restarts_it_each_episode():
    class Recorder:
        """A stand-in model: counts its calls in the state and records what it is given."""

        use_action_masks = True

        def __init__(self):
            self.calls = []

        def predict(self, obs, state=None, episode_start=None, deterministic=False, action_masks=None):
            self.calls.append((state, bool(episode_start[0]), obs.shape, action_masks[0].tolist()))
            return np.array([1]), (0 if state is None else state) + 1

    model, frames = Recorder(), []
    env = gymnasium.make("TMazeCue-v0", render_mode="rgb_array")
    episodes = list(enjoy.play(model, env, n_episodes=2, seed=0, on_frame=frames.append))
    n1, n2 = (e.length for e in episodes)
    assert [c[0] for c in model.calls] == [None, *range(1, n1 + n2)]  # the state is handed back at every step
    assert [c[1] for c in model.calls] == [True] + [False] * (n1 - 1) + [True] + [False] * (n2 - 1)
    assert model.calls[0][2] == (1, 25, 40)  # one batched observation
    assert [c[3] for c in model.calls[:n1]] == [[True, False]] * (n1 - 1) + [[True, True]]  # the env's masks
    assert len(frames) == n1 + n2 + 2 and not any(e.cut for e in episodes)
    assert [e.success for e in episodes] == [e.episode_return > 0 for e in episodes]
    cut = list(enjoy.play(Recorder(), env, n_episodes=1, max_steps=3))[0]
    assert (cut.length, cut.success, cut.cut) == (3, None, True)


def test_tmaze_video_frames_are_captioned_with_the_populations(tmaze_run):
    """A strip above the maze names each population over its columns (white text on black); narrow frames
    (``--size`` below 240 px) get none."""
    from sb3_spikeplastic import PPO

    player = enjoy.Player(PPO.load(tmaze_run / "TMazeCue-v0.zip"), "TMazeCue-v0", video=Path("unused.mp4"))
    player.env.reset(seed=0)
    frame = player._frame(player.env.render())
    strip = frame[:18]
    assert frame.shape == (218, 320, 3) and strip.max() > 200  # text drawn
    for quarter in range(4):  # each population's caption sits over its own columns
        assert strip[:, quarter * 80 + 20 : quarter * 80 + 60].max() > 200
    assert (frame[18:] == player.env.render()).all()
    player.size = (160, 100)
    assert player._frame(player.env.render()).shape == (100, 160, 3)
    player.env.close()


def test_tmaze_render_shows_the_outcome_after_the_decision():
    env = TMazeCueEnv(render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (25 * 8, 40 * 8, 3)  # 8x8 pixels per neuron-millisecond
    # Each population's spikes in its colour on its own dark band: left cue blue, right orange, decision white.
    spikes = env._frames[0] > 0
    for population, colour in enumerate([(60, 140, 255), (255, 150, 40), (255, 255, 255), (150, 150, 150)]):
        columns = slice(population * 10, (population + 1) * 10)
        t, n = np.argwhere(spikes[:, columns])[0] if spikes[:, columns].any() else (None, None)
        if t is not None:
            assert tuple(first[t * 8, (population * 10 + n) * 8]) == colour
    while True:
        _, reward, terminated, _, _ = env.step(env.correct_action)
        if terminated:
            break
    last = env.render().reshape(-1, 3)
    lit = last[(last == (0, 200, 0)).all(axis=1)]
    assert reward == 1 and len(lit)  # right: green spikes
    assert not ((last == (230, 0, 0)).all(axis=1)).any() and not ((last == (60, 140, 255)).all(axis=1)).any()
    assert len(lit) < last.shape[0]  # the bands stay dark
    assert env.metadata["render_fps"] == 4 and TMazeCueEnv.metadata.get("render_fps") is None


def test_frozen_vecnormalize_statistics_normalise_the_observations(tmp_path):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    stats = VecNormalize(DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5")]))
    stats.obs_rms.mean[:] = 1.0
    stats.obs_rms.var[:] = 4.0
    stats.save(tmp_path / "vecnormalize.pkl")
    env = gymnasium.make("HalfCheetah-v5")

    class Recorder:
        observation_space, action_space = env.observation_space, env.action_space
        seen = []

        def predict(self, obs, state=None, episode_start=None, deterministic=False):
            self.seen.append(obs[0])
            return np.zeros((1, 6), dtype=np.float32), None

    player = enjoy.Player(Recorder(), "HalfCheetah-v5", vecnormalize=tmp_path / "vecnormalize.pkl")
    raw_env = gymnasium.make("HalfCheetah-v5")
    raw, _ = raw_env.reset(seed=0)
    player.run(n_episodes=1, max_steps=2, progress=False)
    expected = np.clip((raw - 1.0) / np.sqrt(4.0 + 1e-8), -10, 10)
    np.testing.assert_allclose(Recorder.seen[0], expected, rtol=1e-5)
    assert len(Recorder.seen) == 2


def test_mujoco_gl_order_user_then_egl_then_osmesa(monkeypatch):
    tried = []

    def works(backend):
        tried.append(backend)
        return backend == "osmesa"

    monkeypatch.setenv("MUJOCO_GL", "glfw")
    assert enjoy.select_mujoco_gl(works) == "osmesa" and os.environ["MUJOCO_GL"] == "osmesa"
    assert tried == ["glfw", "egl", "osmesa"]
    monkeypatch.delenv("MUJOCO_GL")
    tried.clear()
    with pytest.raises(RuntimeError, match=r"tried MUJOCO_GL=egl, osmesa\): install EGL .*libegl1.* OSMesa"):
        enjoy.select_mujoco_gl(lambda backend: tried.append(backend) and False)
    assert tried == ["egl", "osmesa"] and "MUJOCO_GL" not in os.environ


BAD_ENJOY = [
    (["--video", "afile/x.mp4"], "--video 'afile/x.mp4' lies under the file 'afile'"),
    (["--video", "videos"], "--video 'videos' is a folder, not a file"),
    (["--n-episodes", "0"], "--n-episodes=0 must be >= 1"),
    (["--max-steps", "0"], "--max-steps=0 must be >= 1"),
    (["--video", "x.xyz"], "--video 'x.xyz': unknown video format '.xyz'; accepted: .mp4, .gif"),
    (["--video", "x"], "unknown video format '(no extension)'; accepted: .mp4, .gif"),
    (["--video", "x.mp4", "--fps", "0"], "--fps 0.0 must be a finite number > 0"),
    (["--video", "x.mp4", "--size", "8", "600"], "--size 8 600: width and height must be >= 16 pixels"),
    (["--fps", "10", "--raster"], "--fps, --raster: only with a video; give --video FILE too"),
    (["--env", "HalfCheetah-v5", "--video", "x.gif"], "does not fit HalfCheetah-v5 (observations"),
]


@pytest.mark.parametrize("argv, message", BAD_ENJOY)
def test_bad_enjoy_input_exits_2_with_one_line_and_writes_nothing(
    argv, message, tmaze_run, tmp_path, run_cli, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    (tmp_path / "videos").mkdir()
    code, out, err = run_cli("enjoy", "--run", tmaze_run, *argv, "--no-progress")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("sb3-spikeplastic: error: ") and not out, err
    assert message in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "videos"]  # nothing written
    assert not any((tmp_path / "videos").iterdir())


def test_missing_video_packages_name_the_extra(tmaze_run, tmp_path, run_cli, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "imageio_ffmpeg", None)  # as if it were not installed
    code, _, err = run_cli("enjoy", "--run", tmaze_run, "--video", tmp_path / "x.mp4")
    assert code == 2 and err.strip() == (
        "sb3-spikeplastic: error: --video .mp4 needs imageio_ffmpeg (not installed): "
        'pip install "sb3-spikeplastic[video]"'
    )
    assert not list(tmp_path.iterdir())


@needs_ffmpeg
def test_halfcheetah_video(tmp_path, run_cli, monkeypatch):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from sb3_spikeplastic import PPO

    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))  # enjoy sets it: restored afterwards
    try:
        enjoy.select_mujoco_gl()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    env = DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5")])
    model = PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=16,
        batch_size=16,
        bptt_steps=16,
        policy_kwargs=dict(hidden_sizes=[8], steps=5, encoder_pop_size=4, action_pop_size=2),
    )
    model.save(tmp_path / "cheetah.zip")
    VecNormalize(env).save(tmp_path / "vecnormalize.pkl")  # found beside the model
    video = tmp_path / "cheetah.mp4"
    code, out, err = run_cli(
        "enjoy",
        "--model",
        tmp_path / "cheetah.zip",
        "--env",
        "HalfCheetah-v5",
        "--max-steps",
        "4",
        "--video",
        video,
        "--size",
        "64",
        "48",
        "--no-progress",
    )
    assert code == 0, err
    assert "VecNormalize: " in out and "episode 1: return" in out and "4 steps (cut by --max-steps)" in out
    with imageio.get_reader(video) as reader:
        frames = np.stack(list(reader.iter_data()))
    assert frames.shape == (5, 48, 64, 3) and frames.std() > 10  # a scene, not a blank image


def test_default_first_episode_ends_as_most_episodes_do(tmaze_run, run_cli):
    code, out, err = run_cli("enjoy", "--run", tmaze_run, "--no-progress")
    assert code == 0, err
    chosen = re.search(r"first episode: seed (\d) \((\d+) of 10 episodes from seed 0 succeeded", out)
    assert chosen, out
    majority_succeeded = int(chosen.group(2)) * 2 >= 10
    assert re.search(r"episode 1: return \S+, \d+ steps, (success|failure)", out).group(1) == (
        "success" if majority_succeeded else "failure"
    ), out
