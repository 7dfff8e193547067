"""The HalfCheetah grid's bookkeeping: which runs it trains, continues or leaves, and which model it evaluates at
each budget."""

import pytest
from helpers import load_experiment


@pytest.fixture(scope="module")
def grid():
    return load_experiment("halfcheetah_grid")


def fake_run(out, name, index, steps, checkpoints, final=True):
    """A run folder as ``train`` leaves it: checkpoints, and the final model with its args.yml if ``final``."""
    folder = out / "runs" / name / "ppo" / f"HalfCheetah-v5_{index}"
    (folder / "HalfCheetah-v5").mkdir(parents=True)
    (folder / "HalfCheetah-v5" / "args.yml").write_text(f"n_timesteps: {steps}\n")
    for step in checkpoints:
        (folder / f"rl_model_{step}_steps.zip").write_bytes(b"")
    if final:
        (folder / "HalfCheetah-v5.zip").write_bytes(b"")
    return folder


def test_runs_shorter_than_n_are_continued_and_every_budget_is_found(grid, tmp_path):
    short = fake_run(tmp_path, "static_0", 1, 300_000, range(50_000, 300_001, 50_000))
    cut = fake_run(tmp_path, "dp-oja_0", 1, 1_000_000, (50_000, 100_000), final=False)
    long_run = fake_run(tmp_path, "mlp_0", 1, 1_000_000, range(50_000, 1_000_001, 50_000))
    args = grid.argparse.Namespace(out=tmp_path, n_timesteps=1_000_000, eval_freq=50_000, eval_episodes=5,
                                   save_freq=50_000, hyperparams=[], budgets=[300_000, 1_000_000])
    assert [grid.trained_steps(v, 0, args) for v in ("static", "dp-oja", "mlp", "dp-bcm")] == [300_000, 0,
                                                                                             1_000_000, 0]
    for variant, folder in (("static", short), ("dp-oja", cut)):  # both continue from their own run folder
        command = grid.train_command(variant, 0, args)
        assert command[command.index("--trained-agent") + 1] == str(folder)
        assert command[command.index("-n") + 1] == "1000000"
    assert "--trained-agent" not in grid.train_command("dp-bcm", 0, args)

    # the continued run: a second folder with the later checkpoints; the 300k model stays the first run's
    fake_run(tmp_path, "static_0", 2, 1_000_000, range(350_000, 1_000_001, 50_000))
    assert grid.trained_steps("static", 0, args) == 1_000_000
    found = grid.models(args)
    assert found["static@300k_s0"] == short / "rl_model_300000_steps.zip"
    assert found["static@1M_s0"].name == "rl_model_1000000_steps.zip" and "_2" in found["static@1M_s0"].parent.name
    assert found["mlp@1M_s0"] == long_run / "rl_model_1000000_steps.zip"
    assert not any(name.startswith("dp-oja") for name in found)  # no final model: not evaluated yet


def test_an_interrupted_run_is_continued_from_its_saved_model_and_not_evaluated(grid, tmp_path):
    """``train`` stopped by a signal saves its model and INTERRUPTED.txt, with args.yml naming the full length:
    the run is neither finished nor credited with that length, and continues from that folder."""
    fake_run(tmp_path, "static_0", 1, 300_000, range(50_000, 300_001, 50_000))
    cut = fake_run(tmp_path, "static_0", 2, 1_000_000, ())  # stopped before its first checkpoint
    (cut / "INTERRUPTED.txt").write_text("interrupted after 333,824 of 1,000,000 steps\n")
    args = grid.argparse.Namespace(out=tmp_path, n_timesteps=1_000_000, eval_freq=50_000, eval_episodes=5,
                                   save_freq=50_000, hyperparams=[], budgets=[300_000, 1_000_000])
    assert grid.trained_steps("static", 0, args) == 0
    command = grid.train_command("static", 0, args)
    assert command[command.index("--trained-agent") + 1] == str(cut)
    assert not any(name.startswith("static") for name in grid.models(args))


def test_control_models_are_the_chosen_runs_that_reached_the_budget(grid, tmp_path):
    reached = fake_run(tmp_path, "mlp_1", 1, 300_000, range(50_000, 300_001, 50_000))
    fake_run(tmp_path, "mlp_2", 1, 1_000_000, (50_000,), final=False)  # still short of 300k
    fake_run(tmp_path, "static_1", 1, 300_000, range(50_000, 300_001, 50_000))  # not among the variants
    args = grid.argparse.Namespace(out=tmp_path, variants=["mlp"], seeds=[0, 1, 2], budget=300_000)
    assert list(grid.control_models(args)) == [("mlp@300k_s1", reached / "rl_model_300000_steps.zip")]
