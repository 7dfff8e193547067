"""Energy of the plasticity rules on the high-noise T-maze: spikes and synaptic operations (SynOps) per environment
step of trained models, the neuromorphic form of the paper's claim that neuromodulation lowers firing (§3.1,
Fig. 2 C-D).

Reads every run folder under ``--runs`` that has a held-out evaluation with energy (``final_eval.json`` written by
``sb3-spikeplastic grid``, or the ``-o`` JSON of ``sb3-spikeplastic evaluate``; both carry ``energy``) and writes
to ``--out``:

* ``energy.md`` / ``energy.csv`` — per rule: held-out success per seed, and per environment step the hidden and
  output spikes, the SynOps into the output layer (the part the rule's firing decides: the input layer's SynOps
  are the input population's spikes × 64, the same for every rule) and all SynOps; mean ± s.d. over seeds; and
  the SynOps per step during the last quarter of training (``snn/synops_per_step`` of ``progress.csv``);
* ``energy.png`` — those SynOps per rule, one dot per seed.

Usage::

    sb3-spikeplastic grid experiments/tmaze_energy.yml -f logs --workers 2
    python experiments/tmaze_energy.py --runs logs/grid/tmaze_energy/runs --out results/tmaze_energy
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from sb3_spikeplastic.experiment import rule_label
from sb3_spikeplastic.run_folder import read_run_args, read_run_config

RULE_ORDER = ("static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm", "ndp-oja+tanh", "ndp-bcm+tanh")


def variant(config: dict) -> str:
    """The rule, with ``+tanh`` for the NDP stabiliser."""
    rule_kwargs = (config.get("policy_kwargs") or {}).get("rule_kwargs") or {}
    return rule_label(config) + ("+tanh" if rule_kwargs.get("modulation") == "tanh" else "")


def training_synops(run: Path) -> float:
    """Mean ``snn/synops_per_step`` over the last quarter of the run's rollouts."""
    with open(run / "progress.csv") as f:
        values = [float(r["snn/synops_per_step"]) for r in csv.DictReader(f) if r.get("snn/synops_per_step")]
    return float(np.mean(values[-max(1, len(values) // 4):])) if values else float("nan")


def plasticity_macs(env_id: str, rule: str) -> float:
    """The plasticity's MACs per environment step of the entry's network with ``rule`` (``+tanh`` allowed): they
    depend on the network's shape and rule only (:func:`sb3_spikeplastic.energy.plasticity_operations`)."""
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_spikeplastic import PPO, load_hyperparams
    from sb3_spikeplastic.energy import plasticity_operations

    h = load_hyperparams(env_id, rule=rule.split("+")[0])
    if rule.endswith("+tanh"):
        h.model_kwargs["policy_kwargs"].setdefault("rule_kwargs", {})["modulation"] = "tanh"
    model = PPO(h.policy, make_vec_env(env_id, n_envs=h.n_envs, env_kwargs=h.env_kwargs), **h.model_kwargs)
    return float(sum(plasticity_operations(model.policy.snn)))


def collect(runs: Path) -> list[dict]:
    rows = []
    for config_file in sorted(runs.rglob("*/config.yml")):
        run = config_file.parent.parent
        result = next((run / name for name in ("final_eval.json", "heldout.json") if (run / name).exists()), None)
        env_id, config = read_run_config(run)
        if result is None or env_id is None:
            continue
        data = json.loads(result.read_text())
        energy = data.get("energy")
        if energy is None:
            continue
        spikes, synops = energy["spikes_per_step"], energy["synops_per_step"]
        rows.append(dict(env=env_id, rule=variant(config), seed=read_run_args(run, env_id).get("seed"),
                         success=data.get("success_rate"), input_spikes=spikes[0],
                         network_spikes=energy["total_spikes_per_step"], output_synops=synops[-1],
                         synops=energy["total_synops_per_step"], training_synops=training_synops(run), run=str(run)))
    return rows


def with_energy(rows: list[dict]) -> list[dict]:
    """``rows`` with the plasticity's MACs per step and the energy estimate (nJ per step) of each."""
    from sb3_spikeplastic.energy import energy_estimate

    macs = {}
    for row in rows:
        key = (row["env"], row["rule"])
        if key not in macs:
            macs[key] = plasticity_macs(*key)
        estimate = energy_estimate([float(row["synops"])], [macs[key]])
        row.update(plasticity_macs=macs[key], synops_nj=estimate["synops_nj"], energy_nj=estimate["total_nj"])
    return rows


def read_csv(path: Path) -> list[dict]:
    """Rows of an ``energy.csv`` written before, numbers as numbers."""
    with open(path) as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for key in ("seed",):
            row[key] = int(row[key])
        for key in ("success", "input_spikes", "network_spikes", "output_synops", "synops", "training_synops"):
            row[key] = float(row[key])
    return rows


def mean_sd(values: list[float], digits: int = 0) -> str:
    return f"{np.mean(values):,.{digits}f} ± {np.std(values):,.{digits}f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, default=Path("results/tmaze_energy/runs"))
    parser.add_argument("--out", type=Path, default=Path("results/tmaze_energy"))
    parser.add_argument("--from-csv", type=Path, help="tabulate an energy.csv written before instead of --runs")
    args = parser.parse_args(argv)
    rows = read_csv(args.from_csv) if args.from_csv else collect(args.runs)
    rows = with_energy(rows) if rows else rows
    if not rows:
        print(f"no evaluated run folders with energy under {args.runs}")
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "energy.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    rules = [r for r in RULE_ORDER if any(row["rule"] == r for row in rows)]
    lines = ["| rule | seeds | held-out success (per seed) | hidden + output spikes / step | SynOps into the output "
             "layer / step | all SynOps / step | all SynOps / step, last quarter of training | plasticity MACs / step "
             "| energy nJ / step: SynOps + plasticity |",
             "|---|---|---|---|---|---|---|---|---|"]
    for rule in rules:
        mine = sorted((r for r in rows if r["rule"] == rule), key=lambda r: r["seed"])
        successes = " / ".join(f"{r['success']:.2f}" for r in mine)
        lines.append(f"| {rule} | {len(mine)} | {successes} | "
                     f"{mean_sd([r['network_spikes'] for r in mine])} | {mean_sd([r['output_synops'] for r in mine])} "
                     f"| {mean_sd([r['synops'] for r in mine])} | {mean_sd([r['training_synops'] for r in mine])} "
                     f"| {mine[0]['plasticity_macs']:,.0f} | {np.mean([r['synops_nj'] for r in mine]):.1f} + "
                     f"{np.mean([r['energy_nj'] - r['synops_nj'] for r in mine]):.1f} = "
                     f"{np.mean([r['energy_nj'] for r in mine]):.1f} |")
    envs = sorted({r["env"] for r in rows})
    inputs = [r["input_spikes"] for r in rows]
    table = "\n".join(lines)
    note = (f"\n\n{', '.join(envs)}; per environment step (25 ms) and environment; the input population fires "
            f"{np.mean(inputs):.0f} spikes per step whatever the rule. Plasticity MACs: the trace update and the "
            "efficacy of every plastic synapse at each update and the modulatory signal (`sb3_spikeplastic.energy`); "
            "energy at 0.9 pJ per SynOp (an accumulate) and 4.6 pJ per MAC (32-bit float, 45 nm: Horowitz, 2014).\n")
    (args.out / "energy.md").write_text(table + note)
    print(table + note)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    for ax, key, label in ((axes[0], "output_synops", "SynOps into the output layer / step"),
                           (axes[1], "synops", "all SynOps / step")):
        for k, rule in enumerate(rules):
            values = [r[key] for r in rows if r["rule"] == rule]
            ax.scatter([k] * len(values), values, color=f"C{k}", zorder=3)
            ax.hlines(np.mean(values), k - 0.3, k + 0.3, color=f"C{k}")
        ax.set_xticks(range(len(rules)), rules, rotation=30, ha="right")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"{', '.join(envs)}: synaptic operations of the trained models (held-out episodes)")
    fig.savefig(args.out / "energy.png", dpi=120)
    print(f"wrote {args.out / 'energy.md'}, energy.csv, energy.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
