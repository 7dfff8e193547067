"""Matplotlib figures: one episode's network activity, training curves, robustness to noise.

Every function returns a ``matplotlib.figure.Figure`` built without ``pyplot`` (no GUI backend, no global figure
registry): save it with ``fig.savefig(path)`` (Agg renderer) or log it with SB3's ``Figure`` logger type.

:func:`plot_command` is ``sb3-spikeplastic plot``: the training curves of run folders (:func:`read_runs`) and a
line of statistics per run (:func:`curve_summaries`).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, Union

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

if TYPE_CHECKING:  # pragma: no cover
    from .recording import EpisodeActivity

_GROUP_COLOURS = ("tab:blue", "tab:red", "tab:green", "0.55", "tab:purple", "tab:orange")
_LAYER_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def _raster(ax, spikes: np.ndarray, colour="k", groups=None, max_points: int = 400_000) -> None:
    """Spike raster of ``(time, n)`` on ``ax`` (time in ms on x, neuron on y)."""
    t, n = np.nonzero(spikes > 0)
    if len(t) > max_points:  # keep the figure light: thin uniformly
        keep = np.linspace(0, len(t) - 1, max_points).astype(int)
        t, n = t[keep], n[keep]
    size = 4.0 if spikes.shape[1] <= 80 else 1.0
    if groups:
        for k, (label, first, stop) in enumerate(groups):
            sel = (n >= first) & (n < stop)
            ax.scatter(
                t[sel],
                n[sel],
                s=size,
                marker="|" if spikes.shape[1] <= 80 else ".",
                linewidths=0.8,
                color=_GROUP_COLOURS[k % len(_GROUP_COLOURS)],
                label=label,
                rasterized=True,
            )
        # Above the axes, not over the raster's last steps (where the T-maze's decision cue fires).
        ax.legend(
            loc="lower right",
            bbox_to_anchor=(1.0, 1.0),
            fontsize=7,
            markerscale=3,
            ncol=len(groups),
            frameon=False,
            borderaxespad=0.1,
        )
    else:
        ax.scatter(
            t, n, s=size, marker="|" if spikes.shape[1] <= 80 else ".", linewidths=0.8, color=colour, rasterized=True
        )
    ax.set_ylim(spikes.shape[1] - 0.5, -0.5)
    ax.yaxis.set_major_locator(MaxNLocator(nbins=4, integer=True))


def _row_subset(spikes: np.ndarray, max_rows: int) -> tuple[np.ndarray, str]:
    """At most ``max_rows`` evenly spaced neurons of ``(time, n)`` spikes (a raster of hundreds of rows at a few
    hundred pixels is solid ink), and the count for the axis label."""
    n = spikes.shape[1]
    if n <= max_rows:
        return spikes, str(n)
    rows = np.unique(np.linspace(0, n - 1, max_rows).round().astype(int))
    return spikes[:, rows], f"{len(rows)} of {n}"


def _step_lines(ax, n_steps: int, T: int) -> None:
    if 1 < n_steps <= 60:
        ax.vlines(
            np.arange(1, n_steps) * T, 0, 1, transform=ax.get_xaxis_transform(), colors="0.85", linewidth=0.6, zorder=0
        )


def activity_figure(
    activity: "EpisodeActivity",
    title: Optional[str] = None,
    n_synapses: int = 5,
    n_membrane: int = 4,
    max_trace_layers: int = 3,
    max_rows: int = 150,
) -> Figure:
    """One episode's activity: input, hidden and output spike rasters, the membrane potential of a few output
    neurons, the traces ``E`` of the ``n_synapses`` synapses of each plastic layer that moved most, and the
    neuromodulatory signals (mean and range over neurons) of modulated layers. Faint vertical lines separate
    environment steps.

    :param activity: from :func:`sb3_spikeplastic.zoo.recording.record_episode`.
    :param title: the figure's title (the episode's return, actions and outcome are appended).
    :param n_synapses: synapses shown per plastic layer.
    :param n_membrane: output neurons whose membrane potential is shown.
    :param max_trace_layers: plastic layers shown (the first ones).
    :param max_rows: neurons shown per raster at most (evenly spaced; the axis label says how many of how many).
    """
    T, n_steps = activity.steps_per_env_step, activity.n_steps
    total = activity.input_spikes.shape[0]
    n_layers = len(activity.spikes)
    trace_layers = [i for i, tr in enumerate(activity.traces) if tr is not None][:max_trace_layers]
    modulated = [i for i, m in enumerate(activity.modulation) if m is not None]
    heights = [2.0] + [1.6] * (n_layers - 1) + [1.3, 1.3] + [1.2] * len(trace_layers) + ([1.1] if modulated else [])
    height = sum(heights) + 0.3 * len(heights) + 0.9
    # Fixed margins (in inches) instead of a layout engine: drawing this figure is on the training path.
    # The title and the input raster's legend share a band above the first axes.
    height += 0.3
    fig = Figure(figsize=(11, height))
    fig.subplots_adjust(left=0.085, right=0.985, top=1 - 0.75 / height, bottom=0.5 / height, hspace=0.3)
    axes = fig.subplots(len(heights), 1, sharex=True, gridspec_kw={"height_ratios": heights})
    axes = np.atleast_1d(axes)
    row = 0

    ax = axes[row]
    if activity.input_groups:  # coloured groups: every neuron, as the groups' bounds index them
        _raster(ax, activity.input_spikes, groups=activity.input_groups)
        shown_in = str(activity.input_spikes.shape[1])
    else:
        subset, shown_in = _row_subset(activity.input_spikes, max_rows)
        _raster(ax, subset)
    ax.set_ylabel(f"input\n({shown_in})")
    row += 1
    for i in range(n_layers - 1):
        ax = axes[row]
        subset, shown = _row_subset(activity.spikes[i], max_rows)
        _raster(ax, subset, colour=_LAYER_COLOURS[i % len(_LAYER_COLOURS)])
        rate = activity.spikes[i].mean() if activity.spikes[i].size else 0.0
        ax.set_ylabel(f"hidden {i + 1}\n({shown})")
        ax.text(1.0, 1.0, f"{rate:.3f} spikes/ms", transform=ax.transAxes, ha="right", va="bottom", fontsize=7)
        row += 1
    out_spikes = activity.spikes[-1]
    ax = axes[row]
    subset, shown = _row_subset(out_spikes, max_rows)
    _raster(ax, subset, colour="tab:purple")
    ax.set_ylabel(f"output\n({shown})")
    row += 1

    ax = axes[row]
    membrane = activity.membrane[-1]
    counts = out_spikes.sum(0)
    shown = np.argsort(-counts, kind="stable")[:n_membrane]
    time = np.arange(total)
    for k, j in enumerate(sorted(shown)):
        ax.plot(time, membrane[:, j], linewidth=0.7, label=f"out {j}")
    ax.axhline(activity.theta, color="k", linestyle="--", linewidth=0.7, label="θ")
    ax.set_ylabel("output\nmembrane u")
    ax.legend(loc="upper right", fontsize=7, ncol=min(len(shown) + 1, 6))
    row += 1

    interval_ends = (np.arange(total // activity.interval) + 1) * activity.interval
    for i in trace_layers:
        ax = axes[row]
        trace = activity.traces[i]  # (n_intervals, n_out, n_in)
        flat = trace.reshape(trace.shape[0], -1)
        moved = np.abs(flat).max(0)
        top = np.argsort(-moved, kind="stable")[:n_synapses]
        for s in top:
            post, pre = divmod(int(s), trace.shape[2])
            ax.step(
                np.concatenate([[0], interval_ends]),
                np.concatenate([[0.0], flat[:, s]]),
                where="post",
                linewidth=0.9,
                label=f"{post}←{pre}",
            )
        ax.set_ylabel(f"E layer {i}\n(top {len(top)})")
        ax.legend(loc="upper left", fontsize=6, ncol=len(top), title="post←pre", title_fontsize=6)
        row += 1

    if modulated:
        ax = axes[row]
        for i in modulated:
            m = activity.modulation[i]  # (n_intervals, n)
            colour = _LAYER_COLOURS[i % len(_LAYER_COLOURS)]
            ax.step(interval_ends, m.mean(1), where="pre", color=colour, linewidth=1.0, label=f"layer {i} mean")
            ax.fill_between(interval_ends, m.min(1), m.max(1), step="pre", color=colour, alpha=0.2)
        ax.set_ylabel("modulatory\nsignal M")  # W_m r, or tanh(W_m r) with the stabiliser
        ax.legend(loc="upper left", fontsize=7)
        row += 1

    for ax in axes:
        _step_lines(ax, n_steps, T)
    axes[-1].set_xlabel(f"time (ms; {n_steps} environment steps of T = {T} ms)")
    axes[-1].set_xlim(0, total)

    parts = [title] if title else []
    if activity.rule:
        parts.append(f"rule {activity.rule}")
    parts.append(f"return {activity.episode_return:.3g} over {n_steps} steps" + ("" if activity.done else " (cut)"))
    if activity.info.get("is_success") is not None:
        decided = activity.actions[-1]
        correct = activity.info.get("correct_action")
        side = {0: "left", 1: "right"}
        text = f"decision {side.get(decided, decided)}"
        if correct is not None:
            text += f" (correct: {side.get(correct, correct)})"
        parts.append(text)
    fig.suptitle("  ·  ".join(parts), fontsize=10, x=0.085, y=1 - 0.12 / height, ha="left", va="top")
    return fig


def _moving_average(y: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or len(y) == 0:
        return y
    window = min(window, len(y))
    kernel = np.ones(window)
    # Mean over the available samples at the start (no zero padding bias).
    return np.convolve(y, kernel, "full")[: len(y)] / np.convolve(np.ones(len(y)), kernel, "full")[: len(y)]


def read_monitor_files(folder: Union[str, os.PathLike]) -> dict[str, np.ndarray]:
    """The episodes of all SB3 Monitor files (``*.monitor.csv``) in ``folder``, merged in order of completion.

    :return: ``r`` (returns), ``l`` (lengths), ``t`` (seconds since the earliest file's start) and
        ``is_success`` (1, 0, or NaN where not reported) arrays; empty arrays if no episode finished.
    """
    rows: list[tuple[float, float, float, float]] = []
    files = sorted(Path(folder).glob("*monitor.csv"))
    starts = []
    for path in files:
        with open(path, newline="") as f:
            first = f.readline()
            t_start = float(json.loads(first[1:]).get("t_start", 0.0)) if first.startswith("#") else 0.0
            starts.append(t_start)
            for row in csv.DictReader(f):
                success = (row.get("is_success") or "").strip()
                rows.append(
                    (
                        float(row["t"]) + t_start,
                        float(row["r"]),
                        float(row["l"]),
                        {"true": 1.0, "1": 1.0, "1.0": 1.0, "false": 0.0, "0": 0.0, "0.0": 0.0}.get(
                            success.lower(), math.nan
                        ),
                    )
                )
    rows.sort(key=lambda r: r[0])
    data = np.array(rows, dtype=float).reshape(-1, 4)
    origin = min(starts) if starts else 0.0
    return {"t": data[:, 0] - origin, "r": data[:, 1], "l": data[:, 2], "is_success": data[:, 3]}


def training_curves_figure(
    runs: Mapping[str, Mapping[str, np.ndarray]], x: str = "timesteps", smooth: int = 10, title: Optional[str] = None
) -> Figure:
    """Episode return (and success rate, when any run's Monitor files have ``is_success``) of several runs.

    :param runs: label -> Monitor data (:func:`read_monitor_files`: arrays ``r``, ``l``, ``t`` and optionally
        ``is_success``, in order of completion).
    :param x: ``"timesteps"`` (cumulative episode lengths), ``"episodes"`` or ``"walltime"`` (hours).
    :param smooth: moving-average window in episodes (1: raw only).
    :param title: the figure's title.
    """
    has_success = any("is_success" in df and not np.isnan(df["is_success"]).all() for df in runs.values())
    fig = Figure(figsize=(9, 6.5 if has_success else 4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(2 if has_success else 1, 1, sharex=True))
    for k, (label, df) in enumerate(runs.items()):
        colour = f"C{k % 10}"
        if x == "timesteps":
            xs = np.cumsum(df["l"])
        elif x == "episodes":
            xs = np.arange(1, len(df["r"]) + 1)
        else:
            xs = np.asarray(df["t"]) / 3600.0
        returns = np.asarray(df["r"], dtype=float)
        if smooth > 1:  # the raw returns, faint behind the average
            axes[0].plot(xs, returns, color=colour, alpha=0.08, linewidth=0.5)
        axes[0].plot(xs, _moving_average(returns, smooth), color=colour, linewidth=1.4, label=label)
        if has_success and "is_success" in df:
            success = np.asarray(df["is_success"], dtype=float)
            valid = ~np.isnan(success)
            if valid.any():
                axes[1].plot(
                    xs[valid], _moving_average(success[valid], smooth), color=colour, linewidth=1.4, label=label
                )
    axes[0].set_ylabel(
        "episode return" + (f"\n(moving average of {smooth};\nfaint: every episode)" if smooth > 1 else "")
    )
    axes[0].legend(loc="best", fontsize=8)
    axes[0].grid(alpha=0.3)
    if has_success:
        axes[1].set_ylabel("success rate" + (f"\n(moving average of {smooth})" if smooth > 1 else ""))
        axes[1].set_ylim(-0.02, 1.02)
        axes[1].axhline(0.5, color="0.6", linestyle=":", linewidth=0.8)
        axes[1].grid(alpha=0.3)
    axes[-1].set_xlabel({"timesteps": "environment steps", "episodes": "episodes", "walltime": "wall time (h)"}[x])
    if title:
        fig.suptitle(title)
    return fig


def read_runs(folders: Sequence[Union[str, os.PathLike]]) -> dict[str, dict[str, np.ndarray]]:
    """The Monitor data (:func:`read_monitor_files`) of run folders, labelled by folder name and rule (the full
    path where two folders share a name); ``ValueError`` for a folder without finished episodes."""
    from .config import rule_label
    from .run_folder import read_run_config

    runs = {}
    for folder in folders:
        p = Path(folder)
        if not p.is_dir():
            raise ValueError(f"no run folder {str(folder)!r}")
        if not list(p.glob("*monitor.csv")):
            raise ValueError(f"no Monitor files (*.monitor.csv) in {str(folder)!r}")
        try:
            data = read_monitor_files(p)
        except (ValueError, KeyError) as exc:
            raise ValueError(f"unreadable Monitor file in {str(folder)!r}: {exc}") from None
        if len(data["r"]) == 0:
            raise ValueError(f"no finished episodes in the Monitor files of {str(folder)!r}")
        label = p.name
        config = read_run_config(p)[1]
        if config:
            label += f" ({rule_label(config)})"
        if label in runs:
            label = str(p)
        runs[label] = data
    return runs


def curve_summaries(runs: Mapping[str, Mapping[str, np.ndarray]], last: int = 100) -> list[str]:
    """One line per run: its episodes and steps, the mean return of its ``last`` episodes and, where reported,
    the success rate of its ``last`` episodes that report success."""
    lines = []
    for label, data in runs.items():
        tail = slice(-last, None)
        line = (
            f"{label}: {len(data['r'])} episodes, {int(data['l'].sum()):,} steps, mean return of the last "
            f"{len(data['r'][tail])}: {data['r'][tail].mean():.3f}"
        )
        success = data["is_success"][~np.isnan(data["is_success"])]
        if len(success):
            line += f", success rate of the last {len(success[tail])}: {success[tail].mean():.3f}"
        lines.append(line)
    return lines


def plot_command(
    runs: Sequence[Union[str, os.PathLike]],
    output: Union[str, os.PathLike] = "training_curves.png",
    x: str = "timesteps",
    smooth: int = 20,
    title: Optional[str] = None,
) -> Callable[[], int]:
    """``sb3-spikeplastic plot`` with these options: the run folders are read (``ValueError``, nothing written);
    returns the plot, which writes :func:`training_curves_figure` to ``output``, prints :func:`curve_summaries`
    and returns 0."""
    from .inputs import check_int, check_output_path

    if x not in ("timesteps", "episodes", "walltime"):
        raise ValueError(f"unknown --x {x!r}; accepted: timesteps, episodes, walltime")
    check_int("--smooth", smooth, 1)
    check_output_path(output, "-o/--output", directory=False)
    data = read_runs(runs)

    def plot() -> int:
        import matplotlib

        matplotlib.use("Agg")
        fig = training_curves_figure(data, x=x, smooth=smooth, title=title)
        out = Path(output)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=120)
        print("\n".join(curve_summaries(data)))
        print(f"wrote {out}")
        return 0

    return plot
