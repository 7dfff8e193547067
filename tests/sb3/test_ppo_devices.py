"""PPO on every available device (the ``device`` fixture: ``cpu`` and, where present, ``cuda``): it trains there,
saves, and the model loads on the CPU with the same parameters and acts."""

import torch
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv


def test_ppo_learns_saves_and_loads_across_devices(device, tmp_path):
    """Two rollouts and updates on the device (action masks, plastic traces and the chunked buffer included);
    the saved model loads on the CPU with the same parameters and acts."""
    env = DummyVecEnv([lambda: TMazeCueEnv(neurons_per_population=4)] * 2)
    model = PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=32,
        batch_size=32,
        bptt_steps=16,
        n_epochs=2,
        seed=0,
        use_action_masks=True,
        device=device,
        policy_kwargs=dict(rule="ndp-oja", hidden_sizes=(16,)),
    )
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(64)
    assert model.device.type == device
    assert all(p.device.type == device for p in model.policy.parameters())
    assert any(not torch.equal(v, before[k]) for k, v in model.policy.state_dict().items())  # it trained
    model.save(tmp_path / "model.zip")
    loaded = PPO.load(tmp_path / "model.zip", device="cpu")
    for key, value in model.policy.state_dict().items():
        assert torch.equal(loaded.policy.state_dict()[key], value.cpu()), key
    obs = env.reset()
    actions, state = loaded.predict(
        obs,
        episode_start=torch.ones(2).numpy().astype(bool),
        deterministic=True,
        action_masks=env.env_method("action_masks"),
    )
    assert actions.shape == (2,) and state is not None
