"""A run's hyperparameters in TensorBoard, written once as a Markdown table (the TEXT tab)."""

from __future__ import annotations

from typing import Any, Mapping

from stable_baselines3.common.logger import Logger, TensorBoardOutputFormat


def flatten_config(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings flattened to dotted keys (``policy_kwargs.rule``)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten_config(value, name + "."))
        else:
            flat[name] = value
    return flat


def hyperparameter_markdown(config: Mapping[str, Any]) -> str:
    """A Markdown table (``| hyperparameter | value |``) of a (nested) configuration."""
    lines = ["| hyperparameter | value |", "|---|---|"]
    for key, value in flatten_config(config).items():
        text = str(value).replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {key} | {text} |")
    return "\n".join(lines)


def write_hyperparameters(
    logger: Logger, config: Mapping[str, Any], tag: str = "hyperparameters", step: int = 0
) -> bool:
    """Write ``config`` as a Markdown table to the TensorBoard outputs of an SB3 ``logger`` (TensorBoard's TEXT
    tab). Returns whether there was a TensorBoard output to write to."""
    written = False
    for output in logger.output_formats:
        if isinstance(output, TensorBoardOutputFormat):
            output.writer.add_text(tag, hyperparameter_markdown(config), step)
            output.writer.flush()
            written = True
    return written
