"""Do the traces do the work? An evaluation with ``ablation`` set against its plain counterpart, model by model and
episode by episode: ``ablation_<evaluation>.md`` and ``.csv`` of :mod:`sb3_spikeplastic.study.report`.

The counterpart is the evaluation the ablated one names with ``against``, else the first one of the same kind and
model, the same protocol (sigmas, episodes, episode seeds, noise settings; every noise of the ablated one) and the
same ``clip_obs``, without ablation. Both evaluate a model on the same episode seeds, so each episode of the ablated
evaluation has its twin in the plain one: the difference plain - ablated is bootstrapped paired, seeds first, then
episodes, the same drawn episodes for both (the two stacked on a leading axis of each seed's data,
:mod:`sb3_spikeplastic.study.intervals`). One row per spiking plastic group (``<variant>@<budget>``) and one for the
plastic variants of a budget pooled (:func:`sb3_spikeplastic.study.groups.kinds`); robustness: R0, the AUC of the
ratio to R0 and the return at the largest sigma, per noise type (a model with plain R0 below the learned threshold
is listed apart, as in ``table.md``); final: the return, the success rate and each step-info key's episode mean,
and for an evaluation with ``bins`` the drop and recovery after the aligned change.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Optional

import numpy as np

from ..zoo.evaluation import REWARD_KEY
from .adaptation import episode_drop_recovery
from .declaration import Evaluation, Study, model_name
from .groups import group_of, groups_of, variant_of
from .intervals import bootstrap_mean_intervals, fmt, verdict
from .layout import StudyData
from .protocol import auc, ratio_to_r0

#: A quantity of a table: (CSV key, column title, decimals, per-seed value from per-seed means ``(..., k, L)``).
Quantity = tuple[str, str, int, Callable[[np.ndarray], np.ndarray]]


def counterpart(study: Study, name: str) -> Optional[str]:
    """The plain evaluation the ablated evaluation ``name`` is paired with (``None``: none declared).

    :param study: the study
    :param name: an evaluation with ``ablation``
    """
    e = study.evaluations[name]
    if e.against is not None:
        return e.against
    bare = replace(e.protocol, noises=())
    return next(
        (
            other
            for other, p in study.evaluations.items()
            if p.ablation is None
            and (p.kind, p.model, p.clip_obs) == (e.kind, e.model, e.clip_obs)
            and replace(p.protocol, noises=()) == bare
            and set(e.protocol.noises) <= set(p.protocol.noises)
        ),
        None,
    )


def _reading(ablation: str) -> str:
    """What the ablation does to a spiking model, and how the table's differences read: the table's first lines.

    :param ablation: the mode as declared, e.g. ``frozen`` or ``reset-every:10``
    """
    mode, _, every = ablation.partition(":")
    done, participle = {
        "frozen": ("every trace and rule state held at zero, the network running on its weights alone", "frozen"),
        "reset-every": (f"every trace and rule state reset to zero every {every} environment steps", "reset"),
        "shuffled": ("each environment running on another environment's traces", "shuffled"),
    }[mode]
    return (
        f"The same models on the same episode seeds with their plasticity ablated ({ablation}): {done}. Each "
        f"difference is plain - ablated; positive: the model loses this much when its traces are {participle}. "
        "[95 % interval]: paired two-stage bootstrap over seeds, then episodes (the same episodes for both); "
        "a verdict only where the interval excludes 0."
    )


def _rows(study: Study, kind: dict[str, str], seeds_of: Callable[[str], list]) -> list[tuple[str, list]]:
    """``(label, seeds)`` of every plastic group with data, budget by budget, each budget's plastic variants pooled
    after them when more than one (as ``report.compare``'s pooled rows).

    :param study: the study (its groups' order)
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param seeds_of: a group -> its models' paired data, or their names (empty: no row)
    """
    plastic = [g for g in groups_of(study) if kind[variant_of(g)] == "plastic" and seeds_of(g)]
    rows = []
    for budget in dict.fromkeys(g.split("@")[1] for g in plastic):
        mine = [g for g in plastic if g.split("@")[1] == budget]
        rows += [(g, seeds_of(g)) for g in mine]
        if len(mine) > 1:
            pooled = f"plastic@{budget} (pooled: {', '.join(variant_of(g) for g in mine)})"
            rows.append((pooled, [s for g in mine for s in seeds_of(g)]))
    return rows


def _statistics(value: Callable[[np.ndarray], np.ndarray]) -> list:
    """The plain, ablated and paired-difference statistics of a quantity over a row's seeds."""
    return [
        lambda m: value(m[..., 0, :]).mean(axis=-1),
        lambda m: value(m[..., 1, :]).mean(axis=-1),
        lambda m: (value(m[..., 0, :]) - value(m[..., 1, :])).mean(axis=-1),
    ]


def _table(
    rows: list[tuple[str, list]],
    quantities: list[Quantity],
    ablation: str,
    boot: dict,
    row: dict,
    subsets: Optional[dict[str, dict[str, list]]] = None,
) -> tuple[list[str], list[dict]]:
    """The Markdown table and CSV rows of some rows of paired seeds (each seed's data: plain and ablated on the
    first axis, episodes last).

    :param rows: ``(label, seeds)``
    :param quantities: the columns
    :param ablation: the ablation mode (the columns' and verdicts' word)
    :param boot: the bootstrap's keyword arguments
    :param row: the leading columns of every CSV row
    :param subsets: quantity key -> row label -> the seeds that quantity is computed on where not all of the row's
        (none: ``-`` in its cells); the CSV's ``<key>_seeds`` column counts them
    """
    subsets = subsets or {}
    lines = [
        "| model | seeds | "
        + " | ".join(f"{t} plain | {t} {ablation} | {t} difference [95 % interval] | {t}" for _, t, _, _ in quantities)
        + " |",
        "|---|---|" + "---|---|---|---|" * len(quantities),
    ]
    csv_rows = []
    for label, seeds in rows:
        own = {key: subsets[key][label] for key, *_ in quantities if label in subsets.get(key, {})}
        # The draws depend on the seeds alone, so each quantity's interval is the same computed with the others.
        shared = [q for q in quantities if q[0] not in own]
        found = dict(zip([q[0] for q in shared], _triples(seeds, shared, boot) if shared else []))
        for key, subset in own.items():
            found[key] = _triples(subset, [q for q in quantities if q[0] == key], boot)[0] if subset else None
        cells, out = [], dict(row, model=label, seeds=len(seeds))
        for key, _, digits, _ in quantities:
            if key in subsets:
                out[f"{key}_seeds"] = len(own.get(key, seeds))
            if found[key] is None:
                cells.append("- | - | - | -")
                continue
            plain, ablated, difference = found[key]
            word = verdict(difference, *(("loses more", "loses less") if key == "auc" else ("lower", "higher")))
            word = word if word == "not resolved" else f"{ablation}: {word}"
            among = f" ({len(own[key])} of {len(seeds)} seeds)" if key in own else ""
            estimates = f"{plain.estimate:.{digits}f} | {ablated.estimate:.{digits}f}"
            cells.append(f"{estimates} | {fmt(difference, digits)} | {word}{among}")
            out.update(
                {f"{key}_plain": round(plain.estimate, 6), f"{key}_ablated": round(ablated.estimate, 6)},
                **{f"{key}_difference_{k}": round(v, 6) for k, v in difference._asdict().items()},
                **{f"{key}_verdict": word},
            )
        lines.append(f"| {label} | {len(seeds)} | " + " | ".join(cells) + " |")
        csv_rows.append(out)
    return lines, csv_rows


def _triples(seeds: list, quantities: list[Quantity], boot: dict) -> list[tuple]:
    """``(plain, ablated, difference)`` intervals of each quantity over ``seeds``."""
    intervals = bootstrap_mean_intervals(seeds, [f for *_, value in quantities for f in _statistics(value)], **boot)
    return [tuple(intervals[3 * i : 3 * i + 3]) for i in range(len(quantities))]


def _robustness_quantities(sigmas: np.ndarray) -> list[Quantity]:
    """R0, the AUC of the ratio to R0 (each model's own R0) and the return at the largest sigma.

    :param sigmas: the evaluation's sigmas, 0 first
    """
    return [
        ("r0", "R0", 0, lambda x: x[..., 0]),
        ("auc", "AUC", 3, lambda x: auc(ratio_to_r0(x), sigmas)),
        (f"return_at_sigma_{sigmas[-1]:g}", f"return at sigma {sigmas[-1]:g}", 0, lambda x: x[..., -1]),
    ]


def _pairs(
    study: Study, env: str, name: str, plain: str, runs: dict, kind: dict[str, str]
) -> tuple[dict[str, list[str]], list[str]]:
    """The plastic models the ablated evaluation ``name`` applies to, per raw file: noise (``""`` for ``final``) ->
    the models with both evaluations' data, and one line per model and file where one of the two is not there.

    :param study: the study
    :param env: the environment
    :param name: the ablated evaluation
    :param plain: its plain counterpart
    :param runs: evaluation name -> model -> its data (:class:`sb3_spikeplastic.study.layout.StudyData`)
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    """
    paired: dict[str, list[str]] = {}
    missing = []
    for cell_env, variant, seed in study.cells():
        if cell_env != env or kind[variant] != "plastic":
            continue
        for budget in study.budgets_of(variant):
            model = model_name(variant, budget, seed)
            for file in (f for n, _, files in study.evaluations_of(variant, seed, budget) if n == name for f in files):
                noise = file[len(name) + 1 : -len(".csv")]
                absent = [
                    f"{n}_{noise}.csv" if noise else f"{n}.csv"
                    for n in (plain, name)
                    if model not in runs[n] or (noise and noise not in runs[n][model])
                ]
                if absent:
                    missing.append(f"{model}: {', '.join(absent)}")
                else:
                    paired.setdefault(noise, []).append(model)
    return paired, missing


def _final_section(
    study: Study,
    evaluation: Evaluation,
    models: list[str],
    plain: dict,
    ablated: dict,
    kind: dict[str, str],
    boot: dict,
    head: dict,
) -> tuple[list[str], list[dict]]:
    """The table of a final evaluation: the return, the success rate (where every episode has one) and the episode
    mean of each of the ablated evaluation's ``info_keys`` that every model's two files keep.

    :param study: the study (its groups, the learned threshold)
    :param evaluation: the ablated evaluation
    :param models: the paired models
    :param plain: model -> its plain evaluation (:func:`~sb3_spikeplastic.study.layout.read_final`)
    :param ablated: model -> its ablated evaluation, likewise
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param boot: the bootstrap's keyword arguments
    :param head: the leading columns of every CSV row
    """
    both = [runs[m] for runs in (plain, ablated) for m in models]
    columns = [("return", "return", lambda d: d["return"])]
    if all(np.isfinite(d["success"]).all() for d in both):
        columns.append(("success", "success", lambda d: d["success"]))
    columns += [
        (f"mean_{k}", f"mean {k}", lambda d, k=k: np.array([e.mean() for e in d["steps"][k]]))
        for k in evaluation.info_keys
        if all(k in d["steps"] for d in both)
    ]
    values = {m: np.stack([[get(runs[m]) for *_, get in columns] for runs in (plain, ablated)]) for m in models}
    quantities = [(key, title, 3, lambda x, i=i: x[..., i]) for i, (key, title, _) in enumerate(columns)]
    rows = _rows(study, kind, lambda g: [values[m] for m in models if group_of(m) == g])
    if not rows:
        return [], []
    section, csv_rows = _table(rows, quantities, evaluation.ablation, boot, dict(head, noise=""))
    lines = ["", *section]
    if evaluation.bins is not None and all(REWARD_KEY in d["steps"] and evaluation.align in d["align"] for d in both):
        pairs = {m: np.stack([episode_drop_recovery(runs[m], evaluation) for runs in (plain, ablated)]) for m in models}
        adaptation, adaptation_rows = _adaptation_section(study, evaluation, pairs, kind, boot)
        lines += adaptation
        by_label = {r["model"]: r for r in csv_rows}
        for r in adaptation_rows:  # the same row of the CSV, with the drop's and recovery's columns
            by_label[r.pop("model")].update({f"adaptation_{k}" if k == "seeds" else k: v for k, v in r.items()})
    return lines, csv_rows


def _adaptation_section(
    study: Study, evaluation: Evaluation, pairs: dict[str, np.ndarray], kind: dict[str, str], boot: dict
) -> tuple[list[str], list[dict]]:
    """The drop and recovery after the aligned change (:mod:`sb3_spikeplastic.study.adaptation`), plain - ablated,
    paired by episode over the episodes that both evaluations measure: recovery that survives the ablation is not
    the traces' doing.

    :param study: the study (its groups)
    :param evaluation: the ablated final evaluation (``bins``, ``align``, ``recovery``)
    :param pairs: model -> its episodes' drops and recoveries, plain and ablated: ``(2, 2, episodes)``, NaN where
        an episode has none (:func:`~sb3_spikeplastic.study.adaptation.episode_drop_recovery`)
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param boot: the bootstrap's keyword arguments
    """
    kept = {m: np.isfinite(pair).all(axis=(0, 1)) for m, pair in pairs.items()}
    values = {m: pair[..., kept[m]] for m, pair in pairs.items() if kept[m].any()}
    rows = _rows(study, kind, lambda g: [values[m] for m in values if group_of(m) == g])
    if not rows:
        return [], []
    early, late = evaluation.recovery
    quantities = [("drop", "drop", 3, lambda x: x[..., 0]), ("recovery", "recovery", 3, lambda x: x[..., 1])]
    section, csv_rows = _table(rows, quantities, evaluation.ablation, boot, {})
    lines = [
        "",
        f"## After the change at {evaluation.align!r}",
        "",
        f"drop: mean step reward over the first {early} steps after the change / the episode's reference before it; "
        f"recovery: (mean over the episode's last {late} steps - mean over the first {early} after the change) / "
        "reference (adaptation_<evaluation>.md). Paired over the episodes both evaluations measure (a reference > "
        f"{evaluation.min_reference:g} and at least {early + late} steps after the change in both).",
        "",
        *section,
    ]
    return lines, csv_rows


def _robustness_section(
    study: Study,
    evaluation: Evaluation,
    paired: dict[str, list[str]],
    plain: dict,
    ablated: dict,
    kind: dict[str, str],
    boot: dict,
    head: dict,
) -> tuple[list[str], list[dict]]:
    """The tables of a robustness evaluation, one per noise type, and the models whose plain R0 is below the
    learned threshold, left out.

    :param study: the study (its groups, the learned threshold)
    :param evaluation: the ablated evaluation
    :param paired: noise -> the paired models
    :param plain: model -> noise -> (sigmas, returns) of its plain evaluation
    :param ablated: model -> noise -> (sigmas, returns) of its ablated evaluation
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param boot: the bootstrap's keyword arguments
    :param head: the leading columns of every CSV row
    """
    # R0 from the first noise a model has (sigma 0: the same episodes under every noise).
    r0 = {m: next(plain[m][n][1][0].mean() for n in plain[m]) for models in paired.values() for m in models}
    failed = sorted(m for m, value in r0.items() if value < study.learned_threshold)
    # Ablated, a model that no longer runs has no fraction of its R0 to keep: its AUC is left out, its R0 and
    # return at the largest sigma are not.
    stopped = sorted(
        m
        for m in r0
        if m not in failed and next(ablated[m][n][1][0].mean() for n in ablated[m]) < study.learned_threshold
    )
    lines, csv_rows = [], []
    for noise in evaluation.protocol.noises:
        models = [m for m in paired.get(noise, []) if m not in failed]
        values = {m: np.stack([plain[m][noise][1], ablated[m][noise][1]]) for m in models}
        named = _rows(study, kind, lambda g: [m for m in models if group_of(m) == g])
        rows = [(label, [values[m] for m in mine]) for label, mine in named]
        subsets = {
            "auc": {
                label: [values[m] for m in mine if m not in stopped]
                for label, mine in named
                if any(m in stopped for m in mine)
            }
        }
        if rows:
            quantities = _robustness_quantities(plain[models[0]][noise][0])
            section, noise_rows = _table(rows, quantities, evaluation.ablation, boot, dict(head, noise=noise), subsets)
            lines += ["", f"## {noise} noise", "", *section]
            csv_rows += noise_rows
    if stopped:
        lines += [
            "",
            f"R0 below {study.learned_threshold:g} {evaluation.ablation} (the network no longer runs: no fraction of "
            f"R0 to keep), left out of the AUC columns only: {', '.join(stopped)}.",
        ]
    if failed:
        lines += ["", f"Did not learn (plain R0 < {study.learned_threshold:g}), left out: {', '.join(failed)}."]
    return lines, csv_rows


def ablation_table(
    study: Study, data: StudyData, env: str, name: str, kind: dict[str, str], boot: dict
) -> Optional[tuple[str, list[dict]]]:
    """The ablation table of the evaluation ``name`` on ``env``: Markdown text and CSV rows; ``None`` where it has
    no ablation or no plain counterpart.

    :param study: the study
    :param data: its raw files (:func:`sb3_spikeplastic.study.layout.read_study`)
    :param env: the environment
    :param name: an evaluation of the study
    :param kind: variant -> ``plastic``, ``static`` or ``baselines``
    :param boot: the bootstrap's keyword arguments
    """
    evaluation, plain = study.evaluations[name], counterpart(study, name)
    if evaluation.ablation is None or plain is None:
        return None
    store = data.final if evaluation.kind == "final" else data.robustness
    runs = {n: store.get((env, n), {}) for n in (plain, name)}
    paired, missing = _pairs(study, env, name, plain, runs, kind)
    head = dict(env=env, evaluation=name, against=plain, ablation=evaluation.ablation)
    section, csv_rows = (
        _final_section(study, evaluation, paired.get("", []), runs[plain], runs[name], kind, boot, head)
        if evaluation.kind == "final"
        else _robustness_section(study, evaluation, paired, runs[plain], runs[name], kind, boot, head)
    )
    lines = [
        f"# {env}: evaluation {name!r} ({evaluation.ablation}) against {plain!r}",
        "",
        _reading(evaluation.ablation),
    ]
    lines += section
    if missing:
        lines += ["", "## Missing", "", "Left out: one of the two evaluations' raw files is not there.", ""]
        lines += [f"* {m}" for m in missing]
    return "\n".join(lines) + "\n", csv_rows
