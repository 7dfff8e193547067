"""SpikePlasticPolicy + recurrent PPO: replay exactness, state handling, SB3 integration, save/load, misuse."""

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3
import torch
from helpers import tmaze, tmaze_model, vec
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize

from sb3_spikeplastic import PPO, SpikePlasticPolicy
from sb3_spikeplastic.snn.network import tensor_leaves

SMALL = dict(hidden_sizes=(16,), steps=10, encoder_pop_size=8, action_pop_size=4)


def assert_replay_exact(model):
    """Every chunk of the last rollout, re-run from its snapshot, reproduces the rollout's log-probs and values."""
    policy, buf = model.policy, model.rollout_buffer
    n_batches = 0
    with torch.no_grad():
        for batch in buf.get_chunks(model.batch_size // model.bptt_steps):
            values, log_prob, _, _ = policy.evaluate_actions_sequence(
                batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks
            )
            ratio = torch.exp(log_prob - batch.old_log_prob.flatten())
            assert (ratio - 1).abs().max().item() <= 1e-5
            assert (values.flatten() - batch.old_values.flatten()).abs().max().item() <= 1e-5
            n_batches += 1
    assert n_batches == -(-buf.buffer_size * buf.n_envs // model.batch_size)  # every chunk was checked


@pytest.mark.parametrize("rule", ["dp-oja", "ndp-bcm", "static"])
def test_replay_exactness_spike_raster_episodes_end_inside_chunks(rule):
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(3),
        n_steps=48,
        batch_size=32,
        bptt_steps=16,
        n_epochs=1,
        learning_rate=0.0,
        seed=1,
        policy_kwargs=dict(rule=rule, hidden_sizes=(16,)),
    )
    model.learn(2 * 48 * 3)
    starts = model.rollout_buffer.episode_starts
    assert starts[1:].sum() > 0 and (starts[np.arange(48) % 16 != 0].sum() > 0)  # resets inside chunks
    assert_replay_exact(model)


def test_replay_exactness_population_encoded_discrete_and_ratio_one_in_training():
    # CartPole: vector observations (stochastic place-cell encoding), short episodes ending inside chunks.
    model = PPO(
        "SpikePlasticPolicy",
        vec(lambda: gym.make("CartPole-v1"), 2),
        n_steps=64,
        batch_size=32,
        bptt_steps=8,
        n_epochs=1,
        learning_rate=0.0,
        seed=0,
        policy_kwargs=dict(rule="ndp-oja", **SMALL),
    )
    model.learn(128)
    assert model.logger.name_to_value.get("train/clip_fraction", 0.0) == 0.0
    assert_replay_exact(model)


def test_replay_exactness_continuous_with_time_limit_truncation():
    env = vec(lambda: gym.make("Pendulum-v1", max_episode_steps=20), 2)
    model = PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=32,
        batch_size=16,
        bptt_steps=8,
        n_epochs=1,
        learning_rate=0.0,
        seed=0,
        policy_kwargs=dict(rule="dp-bcm", **SMALL),
    )
    model.learn(64)
    assert_replay_exact(model)


def test_rollout_state_reset_exactly_at_episode_starts():
    policy_kwargs = dict(rule="dp-oja", **SMALL)
    model = PPO(
        "SpikePlasticPolicy",
        vec(lambda: gym.make("CartPole-v1"), 2),
        n_steps=16,
        batch_size=16,
        bptt_steps=8,
        seed=0,
        policy_kwargs=policy_kwargs,
    )
    policy = model.policy
    obs = torch.zeros(2, 4, device=model.device)
    state = policy.initial_state(2)
    with torch.no_grad():
        for _ in range(3):
            _, _, _, state, _ = policy.step(obs, state, torch.zeros(2, device=model.device))
        reset = state.reset(torch.tensor([1.0, 0.0], device=model.device))
    fresh = policy.initial_state(2)
    for got, want, old in zip(tensor_leaves(reset.layers), tensor_leaves(fresh.layers), tensor_leaves(state.layers)):
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], old[1])
    assert torch.equal(reset.noise_key, state.noise_key)


def test_snapshots_only_at_chunk_starts_and_memory():
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(2),
        n_steps=32,
        batch_size=32,
        bptt_steps=16,
        seed=0,
        policy_kwargs=dict(rule="dp-oja", hidden_sizes=(16,)),
    )
    model.learn(64)
    buf = model.rollout_buffer
    assert len(buf.snapshots) == 32 // 16
    per_env = model.network_state.nbytes() / 2
    assert buf.snapshot_nbytes() == pytest.approx(2 * 2 * per_env)


def test_save_load_identical_deterministic_actions_and_learn_continues(tmp_path):
    model = PPO(
        "SpikePlasticPolicy",
        vec(lambda: gym.make("Pendulum-v1"), 1),
        n_steps=32,
        batch_size=32,
        bptt_steps=8,
        seed=0,
        policy_kwargs=dict(rule="ndp-oja", rule_kwargs=dict(modulation="tanh"), neuron=dict(theta=8.0), **SMALL),
    )
    model.learn(32)
    model.save(tmp_path / "m.zip")
    loaded = PPO.load(tmp_path / "m.zip")
    assert loaded.policy.snn_config == model.policy.snn_config
    assert loaded.policy.snn.neuron.theta == 8.0

    def rollout(m):
        env = gym.make("Pendulum-v1")
        obs, _ = env.reset(seed=3)
        state, actions = None, []
        for t in range(50):
            a, state = m.predict(obs, state=state, episode_start=np.array([t == 0]), deterministic=True)
            actions.append(a)
            obs, *_ = env.step(a)
        return np.array(actions)

    np.testing.assert_array_equal(rollout(model), rollout(loaded))
    loaded.set_env(vec(lambda: gym.make("Pendulum-v1"), 1))
    loaded.learn(32, reset_num_timesteps=False)
    assert loaded.num_timesteps == 64


def test_evaluate_policy_eval_callback_and_vecnormalize(tmp_path):
    def make():
        return gym.make("Pendulum-v1", max_episode_steps=16)

    train_env = VecNormalize(vec(make, 2))
    eval_env = VecNormalize(vec(make, 1), training=False, norm_reward=False)
    model = PPO(
        "SpikePlasticPolicy",
        train_env,
        n_steps=16,
        batch_size=16,
        bptt_steps=8,
        seed=0,
        policy_kwargs=dict(rule="dp-oja", **SMALL),
    )
    callback = EvalCallback(
        eval_env, eval_freq=8, n_eval_episodes=2, best_model_save_path=str(tmp_path), log_path=str(tmp_path), verbose=0
    )
    model.learn(64, callback=callback)
    assert (tmp_path / "best_model.zip").exists()
    # evaluated mid-rollout (every 8 of 16 rollout steps) without touching the rollout state
    assert len(callback.evaluations_results) == 4 and np.isfinite(callback.last_mean_reward)
    mean, std = evaluate_policy(model, eval_env, n_eval_episodes=3)
    assert np.isfinite(mean) and np.isfinite(std)


def test_vanilla_sb3_ppo_refuses_spike_policy():
    with pytest.raises(TypeError, match="sb3_spikeplastic import PPO"):
        stable_baselines3.PPO("SpikePlasticPolicy", tmaze(1))
    model = stable_baselines3.PPO(SpikePlasticPolicy, tmaze(1), n_steps=16, batch_size=16)
    with pytest.raises(RuntimeError, match="sb3_spikeplastic import PPO"):
        model.learn(16)


def test_drop_in_for_sb3_policies():
    model = PPO("MlpPolicy", vec(lambda: gym.make("CartPole-v1"), 1), n_steps=32, batch_size=16, seed=0)
    model.learn(64)
    assert model.num_timesteps == 64


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(n_steps=30, bptt_steps=16, batch_size=16), "n_steps=30 must be a multiple of bptt_steps=16"),
        (dict(n_steps=32, bptt_steps=16, batch_size=24), "batch_size=24"),
        (dict(n_steps=32, bptt_steps=16, batch_size=128), "exceeds the rollout size"),
    ],
)
def test_bad_chunking_is_a_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PPO("SpikePlasticPolicy", tmaze(2), **kwargs)


def test_unknown_rule_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown rule 'hebb'.*dp-oja"):
        PPO("SpikePlasticPolicy", tmaze(1), n_steps=16, batch_size=16, bptt_steps=16, policy_kwargs=dict(rule="hebb"))


def test_action_masks_force_ignored_actions_and_remove_their_policy_gradient(tmp_path):
    """T-maze: only the decision frame's action counts; masked steps sample action 0 with log-prob 0, replay
    exactly from the snapshots, and contribute no gradient; the decision steps still do. The setting survives
    save/load."""
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(3),
        n_steps=48,
        batch_size=48,
        bptt_steps=16,
        n_epochs=1,
        learning_rate=0.0,
        seed=1,
        use_action_masks=True,
        policy_kwargs=dict(hidden_sizes=(16,)),
    )
    model.learn(2 * 48 * 3)
    buf = model.rollout_buffer
    open_both = buf.action_masks[:, :, 1]
    decisions = np.nonzero(buf.episode_starts[1:])  # the step before an episode start is a decision
    assert open_both[:-1][decisions].all() and 0 < open_both.sum() < open_both.size / 10
    assert (buf.actions[..., 0][~open_both] == 0).all() and (buf.log_probs[~open_both] == 0).all()
    assert (buf.log_probs[open_both] < -0.1).any()  # decisions are drawn from both actions
    assert_replay_exact(model)
    batch = next(buf.get_chunks(3))
    _, log_prob, _, _ = model.policy.evaluate_actions_sequence(
        batch.observations, batch.actions, batch.episode_starts, batch.states, batch.action_masks
    )
    opened = batch.action_masks[..., 1].flatten()
    weight = model.policy.snn.layers[0].weight
    (masked_grad,) = torch.autograd.grad(log_prob[~opened].sum(), weight, retain_graph=True)
    (decision_grad,) = torch.autograd.grad(log_prob[opened].sum(), weight)
    assert masked_grad.abs().max().item() == 0.0 and decision_grad.abs().max().item() > 0.0
    model.save(tmp_path / "masked.zip")
    assert PPO.load(tmp_path / "masked.zip", env=tmaze(3)).use_action_masks is True


def test_action_masks_need_an_env_that_provides_them():
    cartpole = vec(lambda: gym.make("CartPole-v1"), 1)
    with pytest.raises(ValueError, match="no action_masks\\(\\) method"):
        PPO(
            "SpikePlasticPolicy",
            cartpole,
            n_steps=16,
            batch_size=16,
            bptt_steps=16,
            use_action_masks=True,
            policy_kwargs=SMALL,
        )
    with pytest.raises(ValueError, match="needs a recurrent SpikePlasticPolicy.*MaskablePPO"):
        PPO("MlpPolicy", tmaze(1), n_steps=16, batch_size=16, use_action_masks=True)


def test_unknown_grad_clip_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown grad_clip 'layer'; accepted: global, per-parameter"):
        PPO("SpikePlasticPolicy", tmaze(1), n_steps=16, batch_size=16, bptt_steps=16, grad_clip="layer")


def clip_model(mode: str, max_grad_norm: float) -> PPO:
    """A small T-maze model whose gradients the clip tests set by hand."""
    return PPO(
        "SpikePlasticPolicy",
        tmaze(1),
        n_steps=16,
        batch_size=16,
        bptt_steps=16,
        max_grad_norm=max_grad_norm,
        grad_clip=mode,
        policy_kwargs=dict(hidden_sizes=[8]),
    )


@pytest.mark.parametrize("mode", ["global", "per-parameter"])
def test_grad_clip_modes(mode):
    """Global: one factor for all tensors (SB3). Per-parameter: each tensor's norm capped on its own, small
    gradients untouched. Both return the global pre-clip norm (logged as train/grad_norm) and keep each tensor's."""
    model = clip_model(mode, max_grad_norm=1.0)
    params = [p for p in model.policy.parameters()]
    g = torch.Generator().manual_seed(0)
    for i, p in enumerate(params):
        p.grad = (torch.randn(p.shape, generator=g) * (1e6 if i == 0 else 1e-3)).to(p.device)
    before = [p.grad.clone() for p in params]
    total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(b) for b in before])).item()
    assert model._clip_gradients() == pytest.approx(total, rel=1e-5)
    # Each parameter's pre-clip norm, by name, for train/grad_norm/<parameter>.
    names = [name for name, _ in model.policy.named_parameters()]
    assert list(model._parameter_grad_norms) == names
    for name, b in zip(names, before):
        assert model._parameter_grad_norms[name] == [pytest.approx(torch.linalg.vector_norm(b).item(), rel=1e-6)]
    norms = [torch.linalg.vector_norm(p.grad).item() for p in params]
    if mode == "global":
        assert sum(n * n for n in norms) ** 0.5 == pytest.approx(1.0, rel=1e-4)
        torch.testing.assert_close(params[1].grad, before[1] / total)
    else:
        assert norms[0] == pytest.approx(1.0, rel=1e-4)
        for p, b in zip(params[1:], before[1:]):
            torch.testing.assert_close(p.grad, b)  # below the bound: unchanged


@pytest.mark.parametrize("mode", ["global", "per-parameter"])
def test_grad_clip_equals_the_per_tensor_loop(mode):
    """The clip's one-call norms and scaling give the same gradients bit for bit as clipping each tensor on its
    own (vector_norm per tensor, then mul_ by the clamped factor)."""
    model = clip_model(mode, max_grad_norm=0.5)
    params = list(model.policy.parameters())
    g = torch.Generator().manual_seed(1)
    for i, p in enumerate(params):
        p.grad = torch.randn(p.shape, generator=g) * 10.0 ** (i % 5 - 2)
    expected = [p.grad.clone() for p in params]
    norms = [torch.linalg.vector_norm(e) for e in expected]
    total = torch.linalg.vector_norm(torch.stack(norms)).item()
    for e, norm in zip(expected, norms):
        if mode == "global":
            e.mul_(min(0.5 / (total + 1e-6), 1.0))
        else:
            e.mul_(torch.clamp(0.5 / (norm + 1e-6), max=1.0))
    assert model._clip_gradients() == total
    for p, e in zip(params, expected):
        assert torch.equal(p.grad, e)


def test_target_kl_stops_before_the_step_that_would_exceed_it():
    """With a KL budget no step can meet, training takes the first minibatch's step (its KL is 0: nothing has
    changed yet) and stops at the second, before stepping (SB3's early-stop semantics)."""
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(2),
        n_steps=16,
        batch_size=16,
        bptt_steps=8,
        n_epochs=3,
        seed=0,
        target_kl=1e-12,
        learning_rate=0.05,
        policy_kwargs=dict(hidden_sizes=[8]),
    )
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(32)  # one rollout, two minibatches per epoch
    after = model.policy.state_dict()
    assert any(not torch.equal(after[k], before[k]) for k in before)
    assert {int(state["step"]) for state in model.policy.optimizer.state.values()} == {1}
    assert model.logger.name_to_value["train/approx_kl"] > 1.5e-12


def test_cuda_graphs_setting_survives_save_and_load(tmp_path):
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(1),
        n_steps=16,
        batch_size=16,
        bptt_steps=16,
        cuda_graphs=False,
        policy_kwargs=dict(hidden_sizes=(8,)),
    )
    model.save(tmp_path / "eager.zip")
    loaded = PPO.load(tmp_path / "eager.zip", env=tmaze(1))
    assert loaded.cuda_graphs is False and loaded._graphed_step is None and loaded._graphed_evaluation is None


def test_alpha_lr_scale_steps_alpha_at_its_own_rate_and_survives_schedules_and_save(tmp_path):
    """Adam's first step moves every element by ~lr (its update is lr * g / |g|): with ``alpha_lr_scale=10`` the
    plasticity coefficients move 10x further than W, the ratio holds when the schedule changes the rate, and it is
    saved with the model."""
    model = PPO(
        "SpikePlasticPolicy",
        tmaze(1),
        n_steps=16,
        batch_size=16,
        bptt_steps=16,
        n_epochs=1,
        seed=0,
        learning_rate=1e-3,
        max_grad_norm=1e9,
        policy_kwargs=dict(hidden_sizes=[8], plastic_layers=[0], alpha_lr_scale=10.0),
    )
    layer = model.policy.snn.layers[0]
    alpha, weight = layer.alpha.detach().clone(), layer.weight.detach().clone()
    model.learn(16)  # one rollout, one minibatch: one Adam step
    assert (layer.alpha - alpha).abs().max().item() == pytest.approx(1e-2, rel=1e-2)
    assert (layer.weight - weight).abs().max().item() == pytest.approx(1e-3, rel=1e-2)
    model.lr_schedule = lambda _: 2e-3
    model._update_learning_rate(model.policy.optimizer)
    assert sorted(g["lr"] for g in model.policy.optimizer.param_groups) == pytest.approx([2e-3, 2e-2])
    model.save(tmp_path / "m.zip")
    loaded = PPO.load(tmp_path / "m.zip")
    assert loaded.policy.snn_config["alpha_lr_scale"] == 10.0
    assert sorted(g["lr_scale"] for g in loaded.policy.optimizer.param_groups) == [1.0, 10.0]


def test_alpha_lr_scale_default_keeps_one_parameter_group():
    """Scale 1 keeps the single group of models saved before the option existed (their optimizers still load)."""
    model = PPO(
        "SpikePlasticPolicy", tmaze(1), n_steps=16, batch_size=16, bptt_steps=16, policy_kwargs=dict(hidden_sizes=[8])
    )
    assert len(model.policy.optimizer.param_groups) == 1


@pytest.mark.parametrize("bad", [0, -1.0, float("inf"), "10", True])
def test_bad_alpha_lr_scale_is_a_clear_error(bad):
    with pytest.raises(ValueError, match=r"alpha_lr_scale=.* must be a positive finite number"):
        PPO(
            "SpikePlasticPolicy",
            tmaze(1),
            n_steps=16,
            batch_size=16,
            bptt_steps=16,
            policy_kwargs=dict(hidden_sizes=[8], alpha_lr_scale=bad),
        )


def test_chunks_per_pass_gives_the_whole_minibatchs_gradient_and_statistics(monkeypatch):
    """A minibatch of 4 chunks run as 4 passes of one chunk: the accumulated gradient of every parameter and the
    logged statistics equal those of one pass over the 4 chunks."""
    model = tmaze_model(n_envs=2, n_steps=32, batch_size=64, bptt_steps=16, max_grad_norm=1e12)
    model.learn(64)
    monkeypatch.setattr(model.policy.optimizer, "step", lambda: None)
    batch = next(iter(model.rollout_buffer.get_chunks(4)))
    evaluate = model._training_evaluation()
    results = []
    for chunks in (None, 1):
        model.chunks_per_pass = chunks
        stats, stepped = model._update_minibatch(batch, evaluate, 0.2, None)
        results.append((stats, [p.grad.clone() for p in model.policy.parameters()]))
        assert stepped
    (whole, whole_grads), (parts, part_grads) = results
    assert sum(float(g.abs().sum()) for g in whole_grads) > 0
    for a, b in zip(whole_grads, part_grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    for key in ("policy_loss", "value_loss", "entropy_loss", "approx_kl", "loss", "grad_norm"):
        assert parts[key] == pytest.approx(whole[key], rel=1e-4, abs=1e-7), key


@pytest.mark.parametrize("value", [3, 0, "half"])
def test_chunks_per_pass_must_divide_the_minibatch(value):
    with pytest.raises(
        ValueError,
        match=rf"chunks_per_pass={value!r} must divide the chunks per minibatch, "
        r"batch_size // bptt_steps = 4, or be None or 'auto'",
    ):
        tmaze_model(n_envs=2, n_steps=32, batch_size=64, bptt_steps=16, chunks_per_pass=value)


def test_auto_chunks_per_pass_keeps_the_graph_within_the_budget(monkeypatch):
    """``"auto"`` (the default) runs a small network's minibatch in one pass, and splits it into the largest
    divisor of its chunk count whose estimated graph fits the budget; the choice is logged."""
    import sb3_spikeplastic.sb3.ppo as ppo_module

    # 8 chunks per minibatch; on the CPU (elsewhere "auto" is always one pass: no compiled ops' graph to size)
    model = tmaze_model(n_envs=2, n_steps=32, batch_size=64, bptt_steps=8, device="cpu")
    assert model.chunks_per_pass == "auto" and model._pass_size() is None
    per_chunk = model.bptt_steps * model.policy.snn.backward_bytes_per_step()
    for budget_chunks, expected in ((8, None), (7, 4), (3, 2), (1, 1), (0.5, 1)):
        monkeypatch.setattr(ppo_module, "AUTO_PASS_GRAPH_BYTES", budget_chunks * per_chunk)
        assert model._pass_size() == expected, budget_chunks
    monkeypatch.setattr(ppo_module, "AUTO_PASS_GRAPH_BYTES", 3 * per_chunk)
    splits = []
    split = ppo_module.ChunkSamples.split
    monkeypatch.setattr(ppo_module.ChunkSamples, "split", lambda batch, n: splits.append(n) or split(batch, n))
    model.learn(64)
    assert splits and set(splits) == {2}
    assert model.logger.name_to_value["train/chunks_per_pass"] == 2  # the update's records, not yet dumped
