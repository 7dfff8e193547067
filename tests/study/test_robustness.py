"""The Fig. 4 F-H robustness protocol: end to end with PPO, recurrent state, VecNormalize, CSV and Markdown."""

import csv
import math

import gymnasium
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_spikeplastic.study.robustness import RobustnessRow, evaluate_robustness, format_table, write_csv, write_report

SHORT = {"max_episode_steps": 5}
pytestmark = pytest.mark.usefixtures("mujoco_log_in_tmp")  # HalfCheetah writes ./MUJOCO_LOG.TXT


class RecurrentStub:
    """A constant-action stand-in for a recurrent model: its state counts the steps of the current episode.

    It checks that within an evaluation it always gets back the state it returned.
    """

    def __init__(self, action: float = 0.5) -> None:
        self.action = action
        self.returned = None  # the state of the last call
        self.states = []
        self.observations = []

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        assert deterministic
        if state is None:  # the first step of an evaluation: every environment starts an episode
            assert episode_start.all()
        else:
            assert state is self.returned
        steps = np.where(episode_start, 0, 0 if state is None else state) + 1
        self.returned = steps
        self.states.append(steps.copy())
        self.observations.append(observation.copy())
        return np.full((len(observation), 6), self.action, np.float32), steps


def test_end_to_end_with_ppo(tmp_path):
    env = gymnasium.make("HalfCheetah-v5", max_episode_steps=20)
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu").learn(64)
    normalized_env = VecNormalize(DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5", max_episode_steps=20)]))
    normalized = PPO("MlpPolicy", normalized_env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    normalized.learn(64)
    normalized_env.save(tmp_path / "vecnormalize.pkl")

    models = {"mlp": model, "mlp-normalized": normalized}
    stats = {"mlp-normalized": tmp_path / "vecnormalize.pkl"}
    kwargs = dict(n_episodes=2, vec_normalize_stats=stats, env_kwargs={"max_episode_steps": 20})
    rows = evaluate_robustness(models, "HalfCheetah-v5", "action", [0.5, 0.1], progress_bar=True, **kwargs)

    assert [(r.model, r.sigma) for r in rows] == [(m, s) for m in models for s in (0.0, 0.1, 0.5)]
    assert all(r.n_episodes == 2 and r.noise_type == "action" for r in rows)
    # the noise-free cell is SB3's own evaluation of the plain environment, seeded alike
    plain = DummyVecEnv([lambda: Monitor(gymnasium.make("HalfCheetah-v5", max_episode_steps=20))])
    plain.seed(0)
    returns, _ = evaluate_policy(model, plain, n_eval_episodes=2, deterministic=True, return_episode_rewards=True)
    assert (rows[0].mean_return, rows[0].std_return) == pytest.approx((np.mean(returns), np.std(returns)))
    assert all(r.ratio == 1.0 for r in rows if r.sigma == 0.0)
    for r in rows:
        baseline = next(b for b in rows if b.model == r.model and b.sigma == 0.0)
        assert r.ratio == pytest.approx(1 + (r.mean_return - baseline.mean_return) / abs(baseline.mean_return))
    again = evaluate_robustness(models, "HalfCheetah-v5", "action", [0.5, 0.1], progress_bar=False, **kwargs)
    assert again == rows  # seeded: every cell is reproducible

    path = write_csv(rows, tmp_path / "out" / "robustness.csv")
    with path.open() as f:
        read = list(csv.DictReader(f))
    assert len(read) == 6 and float(read[0]["ratio"]) == 1.0 and read[1]["sigma"] == "0.1"
    table = format_table(rows).splitlines()
    assert len(table) == 2 + 6 and table[2].startswith("| mlp | action | 0 |")


@pytest.mark.parametrize("noise_type", ["action", "friction"])  # a constant policy ignores observations
def test_recurrent_state_is_threaded_and_reset_at_episode_starts(noise_type):
    stub = RecurrentStub()
    rows = evaluate_robustness(
        {"stub": stub},
        "HalfCheetah-v5",
        noise_type,
        [1.0],
        n_episodes=4,
        n_envs=2,
        progress_bar=False,
        env_kwargs=SHORT,
    )
    counts = np.array(stub.states)
    assert counts.max() == SHORT["max_episode_steps"]  # carried through every episode, reset after its end
    assert [r.n_episodes for r in rows] == [4, 4] and rows[0].ratio == 1.0
    assert rows[1].mean_return != rows[0].mean_return


def test_obs_indices_limit_the_observation_noise_to_those_elements():
    stub = RecurrentStub()  # constant actions: the trajectory is the same at every sigma
    evaluate_robustness(
        {"stub": stub},
        "HalfCheetah-v5",
        "obs",
        [1.0],
        n_episodes=1,
        progress_bar=False,
        env_kwargs=SHORT,
        obs_indices=[2, 5],
    )
    clean, noisy = np.split(np.concatenate(stub.observations), 2)
    changed = np.flatnonzero((clean != noisy).any(axis=0))
    assert changed.tolist() == [2, 5]


def test_vec_normalize_statistics_are_used_frozen(tmp_path):
    venv = VecNormalize(DummyVecEnv([lambda: gymnasium.make("HalfCheetah-v5")]), clip_obs=10.0)
    venv.obs_rms.mean[:] = 100.0  # far from any observation: normalised observations clip at -10
    venv.save(tmp_path / "stats.pkl")
    stub = RecurrentStub()
    evaluate_robustness(
        {"stub": stub},
        "HalfCheetah-v5",
        "obs",
        [0.1],
        n_episodes=2,
        progress_bar=False,
        env_kwargs=SHORT,
        vec_normalize_stats={"stub": tmp_path / "stats.pkl"},
    )
    assert np.all(np.concatenate(stub.observations) == -10.0)


@pytest.mark.parametrize(
    "kwargs, bad",
    [
        ({"noise_type": "gravity"}, "'gravity'"),
        ({"sigmas": [0.1, -0.2]}, "-0.2"),
        ({"n_episodes": 0}, "0"),
        ({"vec_normalize_stats": {"other": None}}, "other"),
        ({"noise_type": "friction", "friction_target": "frictionloss"}, "'frictionloss'"),
        ({"obs_indices": [4, 17]}, "17"),
        ({"noise_type": "action", "obs_indices": [4]}, "'action'"),
    ],
)
def test_bad_arguments_name_the_value(kwargs, bad):
    arguments = {"models": {"stub": RecurrentStub()}, "env_id": "HalfCheetah-v5", "noise_type": "obs", "sigmas": [0.1]}
    with pytest.raises(ValueError) as excinfo:
        evaluate_robustness(**{**arguments, **kwargs})
    assert bad in str(excinfo.value)
    if bad == "'gravity'":
        assert all(name in str(excinfo.value) for name in ("'obs'", "'action'", "'friction'"))


def test_return_ratio_reads_as_kept_performance_for_negative_returns_too():
    from sb3_spikeplastic.study.robustness import return_ratio

    assert return_ratio(100.0, 200.0) == pytest.approx(0.5)  # the paper's quotient for positive returns
    assert return_ratio(-1.62, -5.33) == pytest.approx(1 + 3.71 / 5.33)  # less negative: better, above 1
    assert return_ratio(-10.66, -5.33) == pytest.approx(0.0)  # twice as negative: below 1
    assert math.isnan(return_ratio(3.0, 0.0))


def test_report_is_written_as_csv_markdown_and_figure(tmp_path):
    rows = [RobustnessRow("oja", "obs", sigma, mean, 1.0, 3, mean / 10.0) for sigma, mean in ((0.0, 10.0), (0.2, 7.5))]
    table, paths = write_report(rows, tmp_path / "out", "HalfCheetah-v5", "obs", 3)
    stem = tmp_path / "out" / "robustness_HalfCheetah-v5_obs"
    assert paths == [stem.with_suffix(".csv"), stem.with_suffix(".md"), stem.with_suffix(".png")]
    assert table == format_table(rows) and stem.with_suffix(".md").read_text() == table + "\n"
    with stem.with_suffix(".csv").open() as f:
        read = list(csv.DictReader(f))
    assert [(r["sigma"], r["mean_return"], r["ratio"]) for r in read] == [
        ("0.0", "10.0", "1.0"),
        ("0.2", "7.5", "0.75"),
    ]
    assert stem.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_every_episode_is_kept_in_environment_order_and_written(tmp_path):
    """Returns are sorted by (episode within its environment, environment): positions 0 and 2 are environment 0's
    two episodes, exactly what an evaluation of environment 0 alone (seeded alike) returns."""
    from sb3_spikeplastic.study.robustness import write_episodes_csv

    rows = evaluate_robustness(
        {"stub": RecurrentStub()},
        "HalfCheetah-v5",
        "friction",
        [0.3],
        n_episodes=4,
        n_envs=2,
        seed=7,
        progress_bar=False,
        env_kwargs=SHORT,
    )
    assert [len(r.returns) for r in rows] == [4, 4]
    assert all(r.mean_return == pytest.approx(np.mean(r.returns)) for r in rows)
    alone = evaluate_robustness(
        {"stub": RecurrentStub()},
        "HalfCheetah-v5",
        "friction",
        [0.3],
        n_episodes=2,
        n_envs=1,
        seed=7,
        progress_bar=False,
        env_kwargs=SHORT,
    )
    for together, single in zip(rows, alone):
        assert together.returns[0::2] == pytest.approx(single.returns)
    assert rows[1].returns[0] != rows[1].returns[1]  # the two environments differ: the order is not trivially right

    path = write_episodes_csv(rows, tmp_path / "episodes.csv")
    with path.open() as f:
        read = list(csv.DictReader(f))
    assert [(r["sigma"], r["episode"]) for r in read] == [(s, str(k)) for s in ("0.0", "0.3") for k in range(4)]
    assert [float(r["return"]) for r in read] == pytest.approx([*rows[0].returns, *rows[1].returns])
