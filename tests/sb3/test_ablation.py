"""Plasticity ablations at evaluation (``frozen``, ``reset-every:N``, ``shuffled``): what each does to the network
state, that training ignores them, that they are saved with the model, and the ``--ablation`` option."""

import json

import numpy as np
import pytest
import torch
from helpers import tmaze, tmaze_model

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.ablation import AblatedState, Ablation, ablated
from sb3_spikeplastic.sb3.policy import SpikePlasticPolicy
from sb3_spikeplastic.snn.network import NetworkState, tensor_leaves
from sb3_spikeplastic.snn.plasticity import PlasticState
from sb3_spikeplastic.zoo.evaluation import evaluate_model

STEPS = 40  # two T-maze episodes and more: the environments' episodes end at different steps

#: ndp-bcm keeps a BCM threshold besides its traces; five plasticity updates per 25 ms frame test that ``frozen``
#: holds the traces inside an environment step too
PLASTIC = dict(rule="ndp-bcm", hidden_sizes=(16,), plasticity_interval=5)


@pytest.fixture(scope="module")
def plastic():
    model = tmaze_model(policy_kwargs=PLASTIC)
    with torch.no_grad():  # larger plasticity coefficients: the traces move the membranes within a few steps
        for layer in model.policy.snn.layers:
            layer.alpha.mul_(20.0)
    return model


def predicted(model, ablation=None, n_envs=2, steps=STEPS):
    """Deterministic actions and network states of ``steps`` steps of ``model.predict`` under ``ablation`` on
    freshly seeded T-mazes."""
    env, actions, states = tmaze(n_envs), [], []
    obs, state, starts = env.reset(), None, np.ones(n_envs, bool)
    with ablated(model, ablation):
        for _ in range(steps):
            action, state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
            actions.append(action)
            states.append(state.network if isinstance(state, AblatedState) else state)
            obs, _, starts, _ = env.step(action)
    return actions, states


def by_hand(policy, before, n_envs=2, steps=STEPS):
    """The same with ``policy.step`` and ``before(state, counts)`` applied after each episode-start reset, where
    ``counts`` are the environment steps since each episode's start."""
    env, actions, states = tmaze(n_envs), [], []
    obs, starts = env.reset(), np.ones(n_envs, bool)
    state, counts = policy.initial_state(n_envs), np.zeros(n_envs, int)
    for _ in range(steps):
        counts = np.where(starts, 0, counts)
        state = before(state.reset(torch.as_tensor(starts, dtype=torch.float32)), counts)
        with torch.no_grad():
            action, _, _, state, _ = policy.step(torch.as_tensor(obs), state, torch.zeros(n_envs), deterministic=True)
        actions.append(action.numpy())
        states.append(state)
        obs, _, starts, _ = env.step(action.numpy())
        counts = counts + 1
    return actions, states


def with_plastic(state, fn):
    """``state`` with ``fn`` applied to every trace and rule state."""
    layers = tuple(
        s._replace(plastic=PlasticState(fn(s.plastic.trace), tuple(fn(x) for x in s.plastic.extra)))
        for s in state.layers
    )
    return NetworkState(layers, state.noise_key)


def same(a, b) -> bool:
    """Bit-identical actions and states, step by step."""
    return all(np.array_equal(x, y) for x, y in zip(a[0], b[0])) and all(
        torch.equal(x, y) for s, t in zip(a[1], b[1]) for x, y in zip(tensor_leaves(s), tensor_leaves(t))
    )


def neurons(state):
    """The filter states and noise keys of ``state`` (all but the plastic state)."""
    return [*(x for s in state.layers for x in (*s.psp, *s.refractory)), state.noise_key]


def plastic_values(state):
    return torch.cat([x.flatten() for s in state.layers for x in tensor_leaves(s.plastic)])


@pytest.mark.parametrize("text", ["none", "frozen", "reset-every:50", "shuffled"])
def test_parse_and_str_round_trip(text):
    assert str(Ablation.parse(text)) == text and Ablation.parse(Ablation.parse(text)) == Ablation.parse(text)


@pytest.mark.parametrize(
    "bad, message",
    [
        ("freeze", "unknown ablation 'freeze'; accepted: none, frozen"),
        ("reset-every", "needs N"),
        ("reset-every:0", "needs N"),
        ("reset-every:x", "needs N"),
        ("frozen:3", "unknown ablation"),
        (3, "is not a string"),
    ],
)
def test_bad_values_are_one_line_errors(bad, message):
    with pytest.raises(ValueError, match=message) as info:
        Ablation.parse(bad)
    assert "\n" not in str(info.value)


def test_bad_fields_are_one_line_errors():
    with pytest.raises(ValueError, match="every=2 applies to mode 'reset-every' only"):
        Ablation("frozen", 2)
    with pytest.raises(ValueError, match="reset-every needs every=N, .* got None"):
        Ablation("reset-every")
    with pytest.raises(ValueError, match="unknown ablation mode 'freeze'; accepted: none, frozen, reset-every"):
        Ablation("freeze")


def test_static_network_is_unchanged_by_every_mode():
    model = tmaze_model("static")
    reference = predicted(model)
    for mode in ("frozen", "reset-every:1", "reset-every:3", "shuffled"):
        assert same(predicted(model, mode), reference), mode


def test_frozen_runs_on_the_weights_alone(plastic):
    static = tmaze_model(policy_kwargs={**PLASTIC, "rule": "static"})
    state = {k: v for k, v in plastic.policy.state_dict().items() if k in static.policy.state_dict()}
    static.policy.load_state_dict(state)  # the same W (and decoder, critic), no alpha
    actions, states = predicted(plastic, "frozen")
    static_actions, static_states = predicted(static)
    assert same((actions, [neurons(s) for s in states]), (static_actions, [neurons(s) for s in static_states]))
    assert all(not plastic_values(s).any() for s in states)  # traces and BCM thresholds stay zero
    assert not same(predicted(plastic), (actions, states))  # the unablated network's traces do change its activity


def test_reset_every_one_zeroes_the_plastic_state_before_every_step(plastic):
    zeroed = by_hand(plastic.policy, lambda state, counts: with_plastic(state, torch.zeros_like))
    assert same(predicted(plastic, "reset-every:1"), zeroed)


def test_reset_every_n_counts_steps_from_each_episode_start(plastic):
    n = 5

    def reset_every(state, counts):
        keep = torch.as_tensor(counts % n != 0, dtype=torch.float32)
        return with_plastic(state, lambda x: x * keep.view(-1, *[1] * (x.dim() - 1)))

    ablated_run, reference = predicted(plastic, f"reset-every:{n}"), predicted(plastic)
    assert same(ablated_run, by_hand(plastic.policy, reset_every))
    assert same((ablated_run[0][:n], ablated_run[1][:n]), (reference[0][:n], reference[1][:n]))
    assert plastic_values(reference[1][n - 1]).abs().max() > 1e-3  # traces that the reset then removes
    assert not torch.equal(plastic_values(ablated_run[1][n]), plastic_values(reference[1][n]))


def test_shuffled_runs_each_environment_on_the_other_ones_traces(plastic):
    swapped = by_hand(plastic.policy, lambda state, counts: with_plastic(state, lambda x: x[[1, 0]]))
    ablated_run = predicted(plastic, "shuffled")
    assert same(ablated_run, swapped) and not same(ablated_run, predicted(plastic))
    with pytest.raises(ValueError, match=r"'shuffled' needs 2 or more environments .*got n_envs=1"):
        predicted(plastic, "shuffled", n_envs=1, steps=1)


def test_the_mode_is_saved_with_the_model_and_evaluation_gives_it_back(plastic, tmp_path):
    model = tmaze_model(policy_kwargs=dict(hidden_sizes=(16,), ablation="shuffled"))
    assert model.policy.ablation == Ablation("shuffled")
    model.policy.ablation = "reset-every:7"
    model.save(tmp_path / "m.zip")
    assert PPO.load(tmp_path / "m.zip").policy.ablation == Ablation("reset-every", 7)
    model.policy.save(tmp_path / "policy.zip")
    assert SpikePlasticPolicy.load(tmp_path / "policy.zip").ablation == Ablation("reset-every", 7)
    model.policy.ablation = None
    model.save(tmp_path / "m.zip")
    assert PPO.load(tmp_path / "m.zip").policy.ablation == Ablation()
    evaluate_model(plastic, tmaze(2), 2, ablation="frozen")
    assert plastic.policy.ablation == Ablation()  # its own again


def test_learn_ignores_the_mode():
    reference = tmaze_model().learn(64)
    model = tmaze_model()
    model.policy.ablation = "frozen"
    with pytest.warns(UserWarning, match=r"policy.ablation='frozen' is ignored by learn\(\)"):
        model.learn(64)
    expected = reference.policy.state_dict()
    assert all(torch.equal(v, expected[k]) for k, v in model.policy.state_dict().items())


def test_command_line(tmp_path, run_cli):
    tmaze_model().save(tmp_path / "m.zip")
    model = ["--model", tmp_path / "m.zip", "--env", "TMazeCue-v0", "--env-kwargs", "neurons_per_population=4"]
    code, out, _ = run_cli(
        "evaluate", *model, "--episodes", "2", "--ablation", "frozen", "-o", tmp_path / "eval.json", "--no-progress"
    )
    assert code == 0 and "over 2 episodes (deterministic, ablation frozen)" in out
    assert json.loads((tmp_path / "eval.json").read_text())["ablation"] == "frozen"
    code, out, _ = run_cli(
        "robustness",
        "--models",
        f"a={tmp_path / 'm.zip'}",
        "--env",
        "TMazeCue-v0",
        "--env-kwargs",
        "neurons_per_population=4",
        "--noise",
        "obs",
        "--sigmas",
        "0.1",
        "--episodes",
        "2",
        "--n-envs",
        "2",
        "--ablation",
        "reset-every:5",
        "-o",
        tmp_path / "r",
        "--no-progress",
    )
    assert code == 0 and "| a | obs | 0.1 |" in out
    assert (tmp_path / "r" / "robustness_TMazeCue-v0_obs_reset-every-5.csv").is_file()
    PPO("MlpPolicy", "CartPole-v1", n_steps=16, batch_size=16).save(tmp_path / "mlp.zip")
    for argv, message in [
        (["evaluate", *model, "--ablation", "bogus"], "unknown ablation 'bogus'; accepted:"),
        (["evaluate", *model, "--ablation", "shuffled"], "'shuffled' needs 2 or more"),
        (
            ["evaluate", "--model", tmp_path / "mlp.zip", "--env", "CartPole-v1", "--ablation", "frozen"],
            "ablation 'frozen' needs a spiking plastic policy",
        ),
        (
            [
                "robustness",
                "--models",
                f"a={tmp_path / 'm.zip'}",
                "--env",
                "TMazeCue-v0",
                "--noise",
                "obs",
                "--ablation",
                "reset-every:-1",
            ],
            "needs N",
        ),
    ]:
        code, out, err = run_cli(*argv)
        assert code == 2 and message in err and err.count("\n") == 1, (argv, err)
