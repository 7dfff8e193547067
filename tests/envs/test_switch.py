"""DynamicsSwitch, make_switch_env and the HalfCheetahSwitch-v5 id: a change of dynamics during an episode."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from sb3_spikeplastic.envs import SWITCH_KINDS, DynamicsSwitch, FrictionNoise, TMazeCueEnv, make_switch_env

MODEL_KINDS = ("actuator_gain", "friction", "mass")
ARRAY = {"actuator_gain": "actuator_gear", "friction": "dof_damping", "mass": "body_mass"}
ACTIONS = np.random.default_rng(0).uniform(-1, 1, size=(40, 6)).astype(np.float32)
pytestmark = pytest.mark.usefixtures("mujoco_log_in_tmp")  # HalfCheetah writes ./MUJOCO_LOG.TXT


def cheetah(max_episode_steps: int = 1000) -> gymnasium.Env:
    return gymnasium.make("HalfCheetah-v5", max_episode_steps=max_episode_steps)


def draws(env: gymnasium.Env, seed: int, episodes: int = 5) -> list:
    """``(switch step, target, factor)`` of ``episodes`` resets, the first one seeded."""
    out = []
    for episode in range(episodes):
        _, info = env.reset(seed=seed if episode == 0 else None)
        out.append((info["switch_step"], info["switch_target"], info["switch_factor"]))
    return out


def changed(nominal: np.ndarray, kind: str, target: int, factor: float) -> np.ndarray:
    """The model array the switch should write: the target's entry (every entry for friction) times the factor."""
    out = nominal.copy()
    if kind == "friction":
        out[:] = nominal * factor
    else:
        out[target] = nominal[target] * factor
    return out


@pytest.mark.parametrize("kind", SWITCH_KINDS)
def test_the_same_seed_gives_the_same_draws_and_another_seed_others(kind):
    first = draws(DynamicsSwitch(cheetah(), kind), 0)
    assert first == draws(DynamicsSwitch(cheetah(), kind), 0)
    assert first != draws(DynamicsSwitch(cheetah(), kind), 1)
    assert len(set(first)) == 5  # every episode draws afresh
    lo, hi = {"actuator_gain": (0, 5), "friction": (-1, -1), "action_flip": (0, 5), "mass": (1, 7)}[kind]
    for step, target, factor in first:
        assert 300 <= step <= 700 and lo <= target <= hi
        assert factor == -1.0 if kind == "action_flip" else 0.2 <= factor <= 0.5


def test_draws_cover_the_window_and_targets_inclusively_and_are_paired_across_kinds():
    env = DynamicsSwitch(cheetah(), "mass", window=(3, 6))
    seen = draws(env, 0, episodes=300)
    assert {s for s, _, _ in seen} == {3, 4, 5, 6}
    assert {t for _, t, _ in seen} == set(range(1, 8))  # every body but the world
    actuators = draws(DynamicsSwitch(cheetah(), "actuator_gain", window=(3, 6)), 0, episodes=300)
    assert {t for _, t, _ in actuators} == set(range(6))
    # The draws do not depend on the kind: the same seed switches at the same steps with the same factors.
    assert [(s, f) for s, _, f in actuators] == [(s, f) for s, _, f in seen]
    fixed = draws(DynamicsSwitch(cheetah(), "mass", window=(3, 6), target=2), 0, episodes=300)
    assert [(s, 2, f) for s, _, f in seen] == fixed
    assert {f for *_, f in draws(DynamicsSwitch(cheetah(), factor_range=[0.3, 0.3]), 0)} == {0.3}


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_the_model_is_nominal_for_switch_step_steps_and_changed_from_the_next_one(kind):
    env = DynamicsSwitch(cheetah(), kind, window=(10, 20))
    model = env.unwrapped.model
    nominal = {name: getattr(model, name).copy() for name in ARRAY.values()}
    _, info = env.reset(seed=5)
    s, target, factor = info["switch_step"], info["switch_target"], info["switch_factor"]
    assert info["switched"] is False and info["elapsed_steps"] == 0
    assert 10 <= s <= 20 and factor != 1.0
    expected = changed(nominal[ARRAY[kind]], kind, target, factor)
    for k in range(1, 31):
        _, _, _, _, info = env.step(ACTIONS[k])
        assert info["elapsed_steps"] == k and info["switched"] is (k > s)
        assert (info["switch_step"], info["switch_target"], info["switch_factor"]) == (s, target, factor)
        assert info["switch_kind"] == kind
        now = getattr(model, ARRAY[kind])
        assert np.array_equal(now, expected if k > s else nominal[ARRAY[kind]]), k
        for name, values in nominal.items():  # nothing else changes
            if name != ARRAY[kind]:
                assert np.array_equal(getattr(model, name), values)
    if kind == "friction":  # the root has no damping; the six joints are damped less (factor < 1)
        assert np.array_equal(model.dof_damping[:3], [0, 0, 0])
        assert np.all(model.dof_damping[3:] < nominal["dof_damping"][3:])


@pytest.mark.parametrize("kind", SWITCH_KINDS)
def test_step_switch_step_plus_one_is_the_first_under_the_new_dynamics(kind):
    """The wrapped run equals, bit for bit, a bare run whose model (or action) is changed by hand after exactly
    ``switch_step`` steps; and it leaves the unchanged run at step ``switch_step + 1``, not before."""
    env = DynamicsSwitch(cheetah(), kind, window=(12, 12))
    obs, info = env.reset(seed=3)
    target, factor = info["switch_target"], info["switch_factor"]
    wrapped = [obs] + [env.step(a)[0] for a in ACTIONS]

    def by_hand(switch: bool) -> list:
        bare = cheetah()
        out = [bare.reset(seed=3)[0]]
        model = bare.unwrapped.model
        for k, a in enumerate(ACTIONS):  # k steps taken before this one
            if switch and k == 12 and kind != "action_flip":
                array = getattr(model, ARRAY[kind])
                array[:] = changed(array, kind, target, factor)
            if switch and k >= 12 and kind == "action_flip":
                a = a.copy()
                a[target] = -a[target]
            out.append(bare.step(a)[0])
        return out

    expected, unchanged = by_hand(True), by_hand(False)
    assert all(np.asarray(x).tobytes() == np.asarray(y).tobytes() for x, y in zip(wrapped, expected))
    assert all(np.array_equal(x, y) for x, y in zip(wrapped[:13], unchanged[:13]))  # reset and 12 nominal steps
    assert not np.array_equal(wrapped[13], unchanged[13])


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_reset_and_close_restore_the_nominal_values_without_drift(kind):
    env = DynamicsSwitch(cheetah(30), kind, window=(5, 10))
    model = env.unwrapped.model
    nominal = getattr(model, ARRAY[kind]).copy()
    factors = []
    for episode in range(3):
        _, info = env.reset(seed=1 if episode == 0 else None)
        assert np.array_equal(getattr(model, ARRAY[kind]), nominal)
        factors.append((info["switch_target"], info["switch_factor"]))
        truncated = False
        while not truncated:
            *_, truncated, info = env.step(np.zeros(6, np.float32))
        assert info["switched"] and info["elapsed_steps"] == 30
        # Each episode's change starts from the nominal values, not from the last episode's.
        assert np.array_equal(getattr(model, ARRAY[kind]), changed(nominal, kind, *factors[-1]))
    assert len(set(factors)) == 3
    env.close()
    assert np.array_equal(getattr(model, ARRAY[kind]), nominal)


def test_action_flip_flips_exactly_the_chosen_dimension_from_the_switch_step_on(action_recorder):
    recorder = action_recorder(cheetah())
    env = DynamicsSwitch(recorder, "action_flip", window=(4, 8), target=2)
    _, info = env.reset(seed=0)
    s = info["switch_step"]
    sent = [a.copy() for a in ACTIONS[:20]]
    for a in sent:
        env.step(a)
    assert all(np.array_equal(a, b) for a, b in zip(sent, ACTIONS))  # the caller's actions are left as they are
    received = np.array(recorder.actions)
    assert received.dtype == np.float32
    assert np.array_equal(received[:s], ACTIONS[:s])
    flipped = ACTIONS[s:20].copy()
    flipped[:, 2] *= -1
    assert np.array_equal(received[s:], flipped)
    assert info["switch_target"] == 2 and info["switch_factor"] == -1.0


def test_a_switch_outside_friction_noise_scales_the_noisy_damping():
    env = DynamicsSwitch(FrictionNoise(cheetah(), 0.3), "friction", window=(0, 0))
    model = env.unwrapped.model
    nominal = model.dof_damping.copy()
    for seed in (0, 1):
        _, info = env.reset(seed=seed)
        noisy = nominal.copy()
        noisy[3:] = nominal[3:] * info["friction_factors"]
        assert np.array_equal(model.dof_damping, noisy)
        env.step(np.zeros(6, np.float32))
        assert np.array_equal(model.dof_damping, noisy * info["switch_factor"])


@pytest.mark.filterwarnings("ignore:.*is different from the unwrapped version")
@pytest.mark.filterwarnings("ignore:.*Box observation space m")  # HalfCheetah's observation space is unbounded
@pytest.mark.parametrize("kind", SWITCH_KINDS)
def test_halfcheetah_switch_is_made_from_yaml_lists_and_passes_the_env_checkers(kind):
    kwargs = dict(kind=kind, window=[0, 3], factor_range=[0.5, 0.5])
    env = gymnasium.make("HalfCheetahSwitch-v5", **kwargs)
    assert env.spec.max_episode_steps == 1000
    assert [w.name for w in env.spec.additional_wrappers] == ["DynamicsSwitch"]
    _, info = env.reset(seed=0)
    assert info["switch_kind"] == kind and info["switch_factor"] == (-1.0 if kind == "action_flip" else 0.5)
    check_env(gymnasium.make("HalfCheetahSwitch-v5", **kwargs), skip_render_check=True)
    sb3_check_env(gymnasium.make("HalfCheetahSwitch-v5", **kwargs))


def test_halfcheetah_switch_defaults_and_spec_recreate_the_run():
    env = gymnasium.make("HalfCheetahSwitch-v5")
    switch = env.env.env.env
    assert isinstance(switch, DynamicsSwitch)
    assert (switch.kind, switch.window, switch.factor_range, switch.target) == (
        "actuator_gain",
        (300, 700),
        (0.2, 0.5),
        None,
    )

    def rollout(e):
        obs = [e.reset(seed=4)[0]] + [e.step(a)[0] for a in ACTIONS]
        return obs, e.get_wrapper_attr("switch_step")

    made = gymnasium.make("HalfCheetahSwitch-v5", kind="mass", window=[10, 20], target=5)
    first, again = rollout(made), rollout(gymnasium.make(made.spec))
    assert first[1] == again[1] and all(np.array_equal(x, y) for x, y in zip(first[0], again[0]))


def test_make_switch_env_wraps_an_id_or_an_environment():
    env = make_switch_env("HalfCheetah-v5", kind="friction", window=[1, 40], max_episode_steps=40)
    assert isinstance(env, DynamicsSwitch) and env.spec.max_episode_steps == 40 and env.max_episode_steps == 40
    bare = cheetah()
    wrapped = make_switch_env(bare, kind="mass", window=(2, 2), factor_range=(2.0, 2.0), target=1)
    assert wrapped.env is bare
    wrapped.reset(seed=0)
    mass = bare.unwrapped.model.body_mass[1]
    for _ in range(3):
        wrapped.step(np.zeros(6, np.float32))
    assert bare.unwrapped.model.body_mass[1] == 2.0 * mass


@pytest.mark.parametrize(
    "make, bad, accepted",
    [
        (
            lambda: DynamicsSwitch(cheetah(), "gravity"),
            "'gravity'",
            "'actuator_gain', 'friction', 'action_flip', 'mass'",
        ),
        (lambda: DynamicsSwitch(cheetah(), window=(700, 300)), "[700, 300]", "0 <= lo <= hi <= max_episode_steps=1000"),
        (lambda: DynamicsSwitch(cheetah(), window=(-1, 3)), "[-1, 3]", "0 <= lo <= hi"),
        (lambda: DynamicsSwitch(cheetah(200), window=[300, 700]), "[300, 700]", "max_episode_steps=200"),
        (lambda: DynamicsSwitch(cheetah(), window=[300]), "[300]", "two integers"),
        (lambda: DynamicsSwitch(cheetah(), window=[3.5, 7]), "[3.5, 7]", "two integers"),
        (lambda: DynamicsSwitch(cheetah(), factor_range=(0.0, 0.5)), "[0.0, 0.5]", "0 < lo <= hi"),
        (lambda: DynamicsSwitch(cheetah(), factor_range=(0.5, 0.2)), "[0.5, 0.2]", "0 < lo <= hi"),
        (lambda: DynamicsSwitch(cheetah(), factor_range=(0.2, float("inf"))), "inf", "finite"),
        (lambda: DynamicsSwitch(cheetah(), target=6), "target=6", "[0, 5]"),
        (lambda: DynamicsSwitch(cheetah(), "action_flip", target=-1), "target=-1", "[0, 5]"),
        (lambda: DynamicsSwitch(cheetah(), "mass", target=0), "target=0", "[1, 7]"),
        (lambda: DynamicsSwitch(cheetah(), "mass", target=1.0), "target=1.0", "[1, 7]"),
        (lambda: DynamicsSwitch(cheetah(), "friction", target=2), "target=2", "None"),
        (lambda: DynamicsSwitch(TMazeCueEnv(), "mass"), "TMazeCueEnv", "MuJoCo"),
        (lambda: DynamicsSwitch(TMazeCueEnv(), "action_flip"), "Discrete(2)", "1-D Box"),
        (lambda: make_switch_env("HalfCheetah-v5", kind="wind"), "'wind'", "'mass'"),
        (lambda: make_switch_env(cheetah(), max_episode_steps=5), "max_episode_steps", "environment id"),
        (lambda: gymnasium.make("HalfCheetahSwitch-v5", window=[0, 1001]), "[0, 1001]", "max_episode_steps=1000"),
    ],
)
def test_bad_arguments_name_the_value_and_the_accepted_ones(make, bad, accepted):
    with pytest.raises(ValueError) as excinfo:
        make()
    message = str(excinfo.value)
    assert bad in message and accepted in message and "\n" not in message, message
