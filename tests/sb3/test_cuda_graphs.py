"""CUDA-graph replay of the training pass (sb3_spikeplastic.sb3.cuda_graphs) against the eager pass.

The graph tests need a CUDA device; the state flattening and the capture-failure fallback run everywhere.
"""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from helpers import tmaze_model
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.cuda_graphs import GraphedRolloutStep, GraphedSequenceEvaluation, flatten_state

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def cuda_tmaze_model(device, **kw):
    return tmaze_model(n_envs=4, batch_size=64, n_epochs=2, use_action_masks=True, device=device, **kw)


def pendulum_model(device, rule="dp-bcm", **kw):
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=20)] * 2)
    return PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=32,
        batch_size=32,
        bptt_steps=16,
        n_epochs=2,
        seed=0,
        device=device,
        policy_kwargs=dict(rule=rule, hidden_sizes=(16,), steps=10, encoder_pop_size=8, action_pop_size=4),
        **kw,
    )


def first_batches(model, n=2):
    """The first ``n`` minibatches of one rollout (collected without training)."""
    _, callback = model._setup_learn(model.n_steps * model.n_envs)
    callback.on_training_start(locals(), globals())
    model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
    return list(model.rollout_buffer.get_chunks(model.batch_size // model.bptt_steps))[:n]


def test_flatten_state_round_trip():
    model = cuda_tmaze_model("cpu")
    state = model.policy.initial_state(3)
    leaves, rebuild = flatten_state(state)
    assert all(isinstance(t, torch.Tensor) for t in leaves)
    again = rebuild([t + 1 for t in leaves])
    assert type(again) is type(state)
    for a, b in zip(flatten_state(again)[0], leaves):
        assert torch.equal(a, b + 1)


def test_capture_failure_warns_once_and_falls_back(monkeypatch):
    model = cuda_tmaze_model("cpu")
    batch = first_batches(model, 1)[0]

    def no_graphs(*args, **kwargs):
        raise RuntimeError("operation not permitted when stream is capturing")

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", no_graphs)
    graphed = GraphedSequenceEvaluation(model.policy)
    args = (batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks)
    with pytest.warns(RuntimeWarning, match="capture failed.*same results") as record:
        got = graphed(*args)
        again = graphed(*args)
    assert len([w for w in record if issubclass(w.category, RuntimeWarning)]) == 1
    want = model.policy.evaluate_actions_sequence(*args)[:3]
    for g, a, w in zip(got, again, want):
        assert torch.equal(g, w) and torch.equal(a, w)


def outputs_and_gradients(model, evaluate):
    """``evaluate()``'s outputs and the parameter gradients of a loss over them, as detached copies (the autograd
    graph is gone on return: a live one would break a later capture)."""
    model.policy.zero_grad(set_to_none=True)
    values, log_prob, entropy = evaluate()
    (values.square().mean() + log_prob.mean() + 0.1 * entropy.mean()).backward()
    grads = [None if p.grad is None else p.grad.clone() for p in model.policy.parameters() if p.requires_grad]
    return [t.detach().clone() for t in (values, log_prob, entropy)], grads


@needs_cuda
@pytest.mark.parametrize("make_model", [cuda_tmaze_model, pendulum_model], ids=["tmaze-masks", "pendulum"])
def test_graph_replay_equals_eager_values_and_gradients(make_model):
    """Two different minibatches through one captured graph (the second is a pure replay with new inputs)."""
    model = make_model("cuda", cuda_graphs=False)
    graphed = GraphedSequenceEvaluation(model.policy)
    for batch in first_batches(model, 2):
        args = (batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks)
        graph_out, graph_grads = outputs_and_gradients(model, lambda: graphed(*args))
        eager_out, eager_grads = outputs_and_gradients(model, lambda: model.policy.evaluate_actions_sequence(*args)[:3])
        for a, b in zip(graph_out, eager_out):
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        assert any(g is not None and g.abs().max() > 0 for g in eager_grads)
        for a, b in zip(graph_grads, eager_grads):
            if b is None:
                assert a is None or a.abs().max() == 0
            else:
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    assert graphed.error is None and len(graphed._graphed) == 1


@needs_cuda
def test_capture_after_an_eager_training_pass():
    """An eager backward pass before the first capture (SB3's ``action_dist`` keeps its last distribution, and
    with it that pass's autograd graph) must not break the capture."""
    model = cuda_tmaze_model("cuda", cuda_graphs=False)
    model.learn(model.n_steps * model.n_envs)  # eager rollout and training
    batch = first_batches(model, 1)[0]
    args = (batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks)
    graphed = GraphedSequenceEvaluation(model.policy)
    graph_out, _ = outputs_and_gradients(model, lambda: graphed(*args))
    assert graphed.error is None
    eager_out, _ = outputs_and_gradients(model, lambda: model.policy.evaluate_actions_sequence(*args)[:3])
    for a, b in zip(graph_out, eager_out):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)


def rollout_inputs(model, n_steps=6, seed=0):
    """Observations, episode starts (one reset mid-way) and masks for ``n_steps`` steps of ``model``'s envs."""
    g = torch.Generator().manual_seed(seed)
    model.observation_space.seed(seed)
    n = model.n_envs
    obs = [
        torch.as_tensor(model.observation_space.sample()).float().expand(n, *model.observation_space.shape).clone()
        + 0.1 * torch.randn(n, *model.observation_space.shape, generator=g)
        for _ in range(n_steps)
    ]
    starts = torch.zeros(n_steps, n)
    starts[0] = 1
    starts[3, 0] = 1
    masks = None
    if model.use_action_masks:
        masks = torch.ones(n_steps, n, model.action_space.n, dtype=torch.bool)
        masks[:, 1:, 1] = False  # every env but the first may only take action 0
    return obs, starts, masks


def run_steps(step, model, deterministic):
    obs, starts, masks = rollout_inputs(model)
    device, state, results = model.device, model.policy.initial_state(model.n_envs), []
    for k in range(len(obs)):
        actions, values, log_prob, state, out = step(
            obs[k].to(device),
            state,
            starts[k].to(device),
            deterministic,
            None if masks is None else masks[k].to(device),
        )
        results.append([actions, values, log_prob, *flatten_state(state)[0], out.action, *out.rates])
    return results


def test_rollout_capture_failure_warns_once_and_falls_back(monkeypatch):
    model = cuda_tmaze_model("cpu")

    class NoGraph:
        def __init__(self):
            raise RuntimeError("CUDA graphs need a CUDA device")

    monkeypatch.setattr(torch.cuda, "CUDAGraph", NoGraph)
    monkeypatch.setattr(torch.cuda, "Stream", NoGraph)
    graphed = GraphedRolloutStep(model.policy)
    with pytest.warns(RuntimeWarning, match="capture failed.*same results") as record:
        got = run_steps(graphed, model, deterministic=True)
    assert len([w for w in record if issubclass(w.category, RuntimeWarning)]) == 1
    for a, b in zip(got, run_steps(model.policy.step, model, deterministic=True)):
        for x, y in zip(a, b):
            assert torch.equal(x, y)


@needs_cuda
@pytest.mark.parametrize("make_model", [cuda_tmaze_model, pendulum_model], ids=["tmaze-masks", "pendulum"])
def test_graphed_rollout_step_equals_eager_when_deterministic(make_model):
    model = make_model("cuda")
    graphed = GraphedRolloutStep(model.policy)
    with torch.no_grad():
        eager = run_steps(model.policy.step, model, deterministic=True)
    got = run_steps(graphed, model, deterministic=True)
    for a, b in zip(got, eager):
        for x, y in zip(a, b):
            torch.testing.assert_close(x, y, rtol=1e-6, atol=1e-7)
    assert graphed.error is None and len(graphed._graphs) == 1


@needs_cuda
def test_graphed_rollout_step_samples_fresh_actions_and_respects_masks():
    model = cuda_tmaze_model("cuda")
    graphed = GraphedRolloutStep(model.policy)
    obs, starts, masks = rollout_inputs(model)
    state = model.policy.initial_state(model.n_envs)
    draws = torch.stack(
        [graphed(obs[1].cuda(), state, starts[1].cuda(), False, masks[1].cuda())[0] for _ in range(40)]
    ).cpu()
    assert (draws[:, 1:] == 0).all()  # closed actions are never taken
    assert 0 < draws[:, 0].float().mean() < 1  # the open env's action varies between replays


@needs_cuda
def test_learning_with_graphs_replays_and_trains():
    """``learn`` on CUDA captures each graph once and then only replays; the model trains and stays finite. (Not
    bitwise reproducible between runs: the backward of a gather adds with atomics on the GPU, graphs or not.)"""
    model = cuda_tmaze_model("cuda")
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(3 * model.n_steps * model.n_envs)
    assert model._graphed_step.error is None and len(model._graphed_step._graphs) == 1
    assert model._graphed_evaluation.error is None and len(model._graphed_evaluation._graphed) == 1
    after = model.policy.state_dict()
    assert any(not torch.equal(after[k], before[k]) for k in after)
    for key, value in after.items():
        assert torch.isfinite(value.float()).all(), key


@needs_cuda
@pytest.mark.parametrize("graphed", ["rollout", "training"])
def test_failed_capture_leaves_the_generator_usable_and_learning_goes_on(monkeypatch, graphed):
    """A real capture failure (a host synchronisation inside the captured pass, after its random sampling): one
    warning, the pass runs eagerly from then on, random ops on the device keep working, and the model trains."""
    model = cuda_tmaze_model("cuda")
    name = "_step" if graphed == "rollout" else "_evaluate_sequence"
    original = getattr(model.policy, name)

    def synchronising(*args, **kwargs):
        out = original(*args, **kwargs)
        if torch.cuda.is_current_stream_capturing():
            out[1].sum().item()  # waits for the device: not capturable, invalidates the capture
        return out

    monkeypatch.setattr(model.policy, name, synchronising)
    before = [p.detach().clone() for p in model.policy.parameters()]
    with pytest.warns(RuntimeWarning, match="capture failed"):
        model.learn(3 * model.n_steps * model.n_envs)
    broken = model._graphed_step if graphed == "rollout" else model._graphed_evaluation
    assert broken.error is not None
    torch.randn(8, device="cuda").sum().item()  # the generator is not left in capture mode
    model.learn(model.n_steps * model.n_envs, reset_num_timesteps=False)
    after = list(model.policy.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(after, before))
    assert all(torch.isfinite(p).all() for p in after)


@needs_cuda
def test_models_built_one_after_another_capture_their_graphs():
    """Several models trained in one process: an earlier model, garbage by then, must not be collected during a
    later model's capture (destroying its graphs would invalidate the capture)."""
    for rule in ("static", "dp-oja", "ndp-oja", "ndp-bcm"):
        model = pendulum_model("cuda", rule)
        model.learn(2 * model.n_steps * model.n_envs)
        assert model._graphed_step.error is None and model._graphed_evaluation.error is None, rule
