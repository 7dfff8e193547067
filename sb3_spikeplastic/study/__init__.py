"""Studies and their analysis, the highest layer below the command line: a declared file of variants x
environments x seeds x budgets x evaluations, trained and evaluated by workers that share an Optuna storage, and a
report derived from the raw episodes alone.

* :mod:`~sb3_spikeplastic.study.declaration` — the study file (:class:`Study`) and its checks
* :mod:`~sb3_spikeplastic.study.protocol` — the robustness protocol of Fig. 4 (:class:`Protocol`, :data:`FIG4`)
* :mod:`~sb3_spikeplastic.study.layout` — where the raw data lives and how it is read
* :mod:`~sb3_spikeplastic.study.engine` — the shared queue of cells and the workers
* :mod:`~sb3_spikeplastic.study.cell` — the work of one cell: training to its budgets, its evaluations
* :mod:`~sb3_spikeplastic.study.groups` — the report's groups of models and the comparisons between them
* :mod:`~sb3_spikeplastic.study.report` — tables, intervals, verdicts and figures
* :mod:`~sb3_spikeplastic.study.step_info` — step-info values by step position, and energy per episode
* :mod:`~sb3_spikeplastic.study.storage` — Optuna storages with heartbeats (also used by ``optimize``)
* :mod:`~sb3_spikeplastic.study.robustness` — one model's return under noise (``sb3-spikeplastic robustness``)
* :mod:`~sb3_spikeplastic.study.intervals` — two-stage bootstrap intervals over seeds and episodes
* :mod:`~sb3_spikeplastic.study.optimize` — hyperparameter search (``sb3-spikeplastic optimize``)
"""

from .declaration import Study, load_study_file, study_from_dict
from .protocol import FIG4, Protocol

__all__ = ["FIG4", "Protocol", "Study", "load_study_file", "study_from_dict"]
