"""The hyperparameters as a Markdown table (TensorBoard's text tab)."""

from sb3_spikeplastic.zoo.hparams import hyperparameter_markdown


def test_hyperparameter_markdown_flattens_and_escapes():
    table = hyperparameter_markdown({"a": 1, "b": {"c": [1, 2], "d": "x|y"}, "e": {}})
    assert table.splitlines() == [
        "| hyperparameter | value |",
        "|---|---|",
        "| a | 1 |",
        "| b.c | [1, 2] |",
        "| b.d | x\\|y |",
        "| e | {} |",
    ]
