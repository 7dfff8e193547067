"""A study's groups as its report compares them: a group is ``<variant>@<budget>`` (its models are the seeds), a
variant is ``plastic``, ``static`` or ``baselines`` by its entry, and the study file's ``report.compare`` names
variants or these kinds; :func:`comparisons` turns it into the pairs of groups compared, budget by budget.
"""

from __future__ import annotations

from collections.abc import Callable

from .declaration import Study, budget_label


def group_of(model: str) -> str:
    """The group of a model name: ``dp-oja@300k_s0`` -> ``dp-oja@300k``."""
    return model.rsplit("_s", 1)[0]


def variant_of(group: str) -> str:
    """The variant of a group: ``dp-oja@300k`` -> ``dp-oja``."""
    return group.split("@")[0]


def groups_of(study: Study) -> list[str]:
    """``<variant>@<budget>`` in report order: budgets ascending, then the study file's order of variants."""
    budgets = sorted({b for v in study.variants for b in study.budgets_of(v)})
    return [f"{v}@{budget_label(b)}" for b in budgets for v in study.variants if b in study.budgets_of(v)]


def _entry(study: Study, variant: str) -> dict:
    """The variant's resolved entry on the study's first environment; where resolving needs a package the report
    does not (sb3-contrib for a RecurrentPPO baseline), its file's entry with the variant's rule."""
    from ..zoo.zoo_yaml import load_hyperparams_file

    try:
        return study.config(study.envs[0], variant)
    except ValueError:
        data = load_hyperparams_file(study.conf_of(variant))
        entry = dict(data.get(study.train_env(study.envs[0], variant)) or data.get("default") or {})
        rule = study.variants[variant].rule
        if rule is not None:
            entry["policy_kwargs"] = {**(entry.get("policy_kwargs") or {}), "rule": rule}
        return entry


def kinds(study: Study) -> dict[str, str]:
    """Variant -> ``plastic``, ``static`` or ``baselines``, from its entry (the study's first env)."""
    out = {}
    for variant in study.variants:
        config = _entry(study, variant)
        if config.get("policy") != "SpikePlasticPolicy":
            out[variant] = "baselines"
        else:
            rule = (config.get("policy_kwargs") or {}).get("rule", "dp-oja")
            out[variant] = "static" if rule == "static" else "plastic"
    return out


def members(names: tuple[str, ...], kind: dict[str, str]) -> list[str]:
    """Variant names and groups (``plastic``, ``static``, ``spiking``, ``baselines``) -> variants."""
    out: list[str] = []
    for name in names:
        if name in kind:
            chosen = [name]
        elif name == "spiking":
            chosen = [v for v, k in kind.items() if k != "baselines"]
        else:
            chosen = [v for v, k in kind.items() if k == name]
        out += [v for v in chosen if v not in out]
    return out


def comparisons(
    study: Study, kind: dict[str, str], groups: list[str], has_data: Callable[[str], bool], matched_r0: bool = False
) -> list[tuple[str, str, list[str]]]:
    """``(label, reference group, groups compared)`` of every declared comparison, budget by budget: each variant
    against each reference of the same budget, then the variants pooled (when declared and more than one).

    :param study: the study.
    :param kind: variant -> ``plastic``, ``static`` or ``baselines`` (:func:`kinds`).
    :param groups: the groups that may be compared.
    :param has_data: whether a group has data to compare.
    :param matched_r0: the comparisons declared with ``matched_r0`` (their reference of the same budget is where
        :mod:`~sb3_spikeplastic.study.matched` starts from), else those without.
    """
    rows = []
    for budget in dict.fromkeys(g.split("@")[1] for g in groups):
        at_budget = {variant_of(g): g for g in groups if g.split("@")[1] == budget and has_data(g)}
        for comparison in (c for c in study.comparisons if c.matched_r0 == matched_r0):
            chosen = [v for v in members(comparison.variants, kind) if v in at_budget]
            for ref_variant in members(comparison.against, kind):
                if ref_variant not in at_budget:
                    continue
                reference = at_budget[ref_variant]
                mine = [v for v in chosen if v != ref_variant]
                rows += [(at_budget[v], reference, [at_budget[v]]) for v in mine]
                if comparison.pooled and len(mine) > 1:
                    rows.append(
                        (
                            f"{' + '.join(comparison.variants)}@{budget} (pooled: {', '.join(mine)})",
                            reference,
                            [at_budget[v] for v in mine],
                        )
                    )
    return rows
