"""Where a study keeps its raw data, and how it is read back.

::

    <folder>/runs/<env>/<variant>_s<seed>/ppo/<env>_<n>/    training runs (a run continued later adds a folder)
    <folder>/training/<env>/<variant>_s<seed>.csv           every evaluation during training: timesteps, episode,
                                                            return
    <folder>/episodes/<env>/<variant>@<budget>_s<seed>/     every evaluation's episodes:
        <evaluation>.csv                                    final: episode, return, length, success (and
                                                            steps:<key>, align:<key>, synops, plasticity_macs,
                                                            energy_nj where recorded)
        <evaluation>_<noise>.csv                            robustness: model, noise_type, sigma, episode, return
        <evaluation>.csv                                    sensitivity: element, sensitivity, obs_sd

Raw per-episode returns are the study's only data: :func:`read_study` reads back every file a study declares, and
:mod:`sb3_spikeplastic.study.report` derives every table, interval and figure from them. Every file is written
whole (into a temporary file, then renamed), so a killed worker never leaves half a file.
"""

from __future__ import annotations

import csv
import json
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .declaration import Study, model_name

#: Column prefixes of a final evaluation's raw file: a step-info key's value at every step of the episode (a JSON
#: list), and the final step's alignment key (a step index; empty for ``None``).
STEPS_COLUMN, ALIGN_COLUMN = "steps:", "align:"
#: Columns of a spiking model's energy per episode (:meth:`sb3_spikeplastic.snn.energy.EnergyMeter.episode`).
ENERGY_COLUMNS = ("synops", "plasticity_macs", "energy_nj")

_CHECKPOINT = re.compile(r"rl_model_(\d+)_steps\.zip")
_RUN = re.compile(r".+_\d+")


class StudyFolder:
    """The folders and files of one study (see the module docstring).

    :param root: the study's folder
    """

    def __init__(self, root: Path):
        self.root = Path(root)

    def run_root(self, env: str, variant: str, seed: int) -> Path:
        return self.root / "runs" / env / f"{variant}_s{seed}"

    def run_folders(self, env: str, variant: str, seed: int) -> list[Path]:
        """The run folders of a cell (``ppo/<training env>_<n>``), oldest first (a later one continues an earlier
        one)."""
        return sorted(
            (p for p in self.run_root(env, variant, seed).glob("ppo/*") if _RUN.fullmatch(p.name)),
            key=lambda p: int(p.name.rsplit("_", 1)[1]),
        )

    def checkpoints(self, env: str, variant: str, seed: int) -> dict[int, Path]:
        """Steps -> checkpoint, over every run folder of the cell (a later folder's wins)."""
        found = {}
        for folder in self.run_folders(env, variant, seed):
            for path in folder.glob("rl_model_*_steps.zip"):
                if match := _CHECKPOINT.fullmatch(path.name):
                    found[int(match.group(1))] = path
        return found

    def model_at(self, env: str, variant: str, seed: int, budget: int) -> Optional[Path]:
        """The checkpoint saved when the cell's training reached ``budget`` steps (the first at or after it)."""
        after = sorted((steps, path) for steps, path in self.checkpoints(env, variant, seed).items() if steps >= budget)
        return after[0][1] if after else None

    def training_file(self, env: str, variant: str, seed: int) -> Path:
        return self.root / "training" / env / f"{variant}_s{seed}.csv"

    def episodes_dir(self, env: str, variant: str, budget: int, seed: int) -> Path:
        return self.root / "episodes" / env / model_name(variant, budget, seed)

    def has_data(self) -> bool:
        return (self.root / "episodes").is_dir() or (self.root / "training").is_dir()


def read_robustness(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A robustness file: ``(sigmas, returns of shape (n_sigma, n_episodes))``, episodes in file order of their
    index (the same seeded episode at every sigma)."""
    by_sigma: dict[float, list[tuple[int, float]]] = defaultdict(list)
    with open(path) as f:
        for row in csv.DictReader(f):
            by_sigma[float(row["sigma"])].append((int(row["episode"]), float(row["return"])))
    sigmas = np.array(sorted(by_sigma))
    return sigmas, np.array([[r for _, r in sorted(by_sigma[s])] for s in sigmas])


def read_final(path: Path) -> dict:
    """A final-evaluation file: ``return``, ``length`` and ``success`` (arrays; NaN where the task reports none);
    ``steps`` (step-info key -> each episode's values, an array per episode), ``align`` (key -> each episode's
    step index or ``None``) and ``energy`` (:data:`ENERGY_COLUMNS` -> arrays; ``None`` where not recorded)."""
    with open(path) as f:
        reader = csv.DictReader(f)
        rows, columns = list(reader), reader.fieldnames or []
    out: dict = {
        key: np.array([float(r[key]) if r[key] != "" else np.nan for r in rows])
        for key in ("return", "length", "success")
    }
    out["steps"] = {
        c[len(STEPS_COLUMN) :]: [np.array(json.loads(r[c]), dtype=float) for r in rows]
        for c in columns
        if c.startswith(STEPS_COLUMN)
    }
    out["align"] = {
        c[len(ALIGN_COLUMN) :]: [int(r[c]) if r[c] != "" else None for r in rows]
        for c in columns
        if c.startswith(ALIGN_COLUMN)
    }
    recorded = all(c in columns for c in ENERGY_COLUMNS) and all(r[c] != "" for r in rows for c in ENERGY_COLUMNS)
    out["energy"] = {c: np.array([float(r[c]) for r in rows]) for c in ENERGY_COLUMNS} if recorded else None
    return out


def read_training(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A training-curve file: ``(timesteps, mean return of each evaluation)``, in step order."""
    returns: dict[int, list[float]] = defaultdict(list)
    with open(path) as f:
        for row in csv.DictReader(f):
            returns[int(row["timesteps"])].append(float(row["return"]))
    steps = np.array(sorted(returns))
    return steps, np.array([np.mean(returns[s]) for s in steps])


def read_sensitivity(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A sensitivity file: ``(sensitivity per element, the element's s.d. in the model's observation statistics)``
    (NaN where not recorded)."""
    with open(path) as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["element"]))
    return (
        np.array([float(r["sensitivity"]) for r in rows]),
        np.array([float(r["obs_sd"]) if r.get("obs_sd") not in (None, "") else np.nan for r in rows]),
    )


@dataclass
class StudyData:
    """What a study's folder holds, read once.

    :param robustness: (env, evaluation) -> model -> noise -> (sigmas, returns (n_sigma, n_episodes))
    :param final: (env, evaluation) -> model -> :func:`read_final`
    :param sensitivity: (env, evaluation) -> model -> (sensitivity per element, observation s.d. per element)
    :param training: env -> (variant, seed) -> (timesteps, mean return)
    :param missing: one line per missing cell or evaluation file
    """

    robustness: dict = field(default_factory=dict)
    final: dict = field(default_factory=dict)
    sensitivity: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)
    missing: list = field(default_factory=list)


def read_study(study: Study, folder: Path) -> StudyData:
    """Every raw file the study declares, and the list of those not there."""
    layout, data = StudyFolder(folder), StudyData()
    for env, variant, seed in study.cells():
        path = layout.training_file(env, variant, seed)
        if path.is_file():
            data.training.setdefault(env, {})[(variant, seed)] = read_training(path)
        elif study.eval_freq:
            data.missing.append(f"{env} {variant} seed {seed}: training curve")
        for budget in study.budgets_of(variant):
            model = model_name(variant, budget, seed)
            episodes = layout.episodes_dir(env, variant, budget, seed)
            for name, evaluation, files in study.evaluations_of(variant, seed, budget):
                for file in files:
                    path = episodes / file
                    if not path.is_file():
                        data.missing.append(f"{env} {model}: {file}")
                    elif evaluation.kind == "final":
                        data.final.setdefault((env, name), {})[model] = read_final(path)
                    elif evaluation.kind == "sensitivity":
                        data.sensitivity.setdefault((env, name), {})[model] = read_sensitivity(path)
                    else:
                        noise = file[len(name) + 1 : -len(".csv")]
                        runs = data.robustness.setdefault((env, name), {}).setdefault(model, {})
                        runs[noise] = read_robustness(path)
    return data
