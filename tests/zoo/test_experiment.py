"""``train``'s checks as a Python call: bad input raises ``ValueError`` before the run folder is created."""

import pytest

from sb3_spikeplastic.zoo.experiment import continued_run, train_command


@pytest.mark.parametrize("options, message", [
    ({"env": "TMazeCue-v0", "eval_freq": -1}, r"^--eval-freq=-1 must be >= 0$"),
    ({"env": "TMazeCue-v0", "rule": "hebb"}, "unknown rule 'hebb'"),
    ({"env": "TMazeCue-v0", "hyperparams": ["policy_kwargs.hidden_sizes=[16]", "bptt_steps=32", "batch_size=48"]},
     r"^invalid configuration for TMazeCue-v0: batch_size=48"),
    ({"env": "HalfCheetah-v5", "conf": "mlp", "figure_freq": 1}, "--figure-freq needs policy SpikePlasticPolicy"),
])
def test_bad_options_raise_before_anything_is_written(options, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        train_command(log_folder=str(tmp_path / "logs"), tensorboard_log=str(tmp_path / "tb"), **options)
    assert list(tmp_path.iterdir()) == []


def test_a_continued_run_keeps_its_configuration(tmp_path):
    with pytest.raises(ValueError, match="continues a run with its own configuration"):
        continued_run(str(tmp_path), "TMazeCue-v0", overridden=True)
    with pytest.raises(FileNotFoundError, match="no run folder or model file"):
        continued_run(str(tmp_path / "nowhere"), "TMazeCue-v0")
