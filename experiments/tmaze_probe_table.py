"""Collect the ``probe.txt`` of several runs (written by ``tmaze_probe.py``) into one ``probes.md`` table.

Usage::

    for run in results/tmaze_alpha_lr30/runs/*; do
        python experiments/tmaze_probe.py $run/ppo/TMazeCueNoisy-v0_1 --episodes 4000 > $run/probe.txt
    done
    python experiments/tmaze_probe_table.py results/tmaze_alpha_lr30 "Stage by stage: ..." \\
        TMazeCueNoisy-v0_dp-oja_0 TMazeCueNoisy-v0_dp-oja_1 ...
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

#: (pattern of the line in probe.txt, column title), from the decision back to the input.
COLUMNS = [
    ("policy's decision", "policy's decision"),
    ("hidden rates", "probe: hidden rates in the decision frame"),
    ("noise-free plastic input per hidden neuron", "probe: noise-free plastic input per hidden neuron"),
    ("left-minus-right trace sums per hidden neuron", "probe: left-minus-right trace sums per hidden neuron"),
    ("trace E", "probe: layer-0 trace E entering the decision frame"),
    (r"whole episode\)", "spike counter"),
    (r"1-cue margins \(\d+% of episodes\)", "policy on 4:3 splits (53 % of episodes)"),
    (r"3-cue margins \(\d+% of episodes\)", "policy on 5:2 splits (34 %)"),
]


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(__doc__)
        return 2
    out_dir, title, runs = Path(argv[0]), argv[1], argv[2:]
    lines = [
        f"# {title}", "",
        f"`python experiments/tmaze_probe.py {out_dir}/runs/<run>/ppo/TMazeCueNoisy-v0_1 --episodes 4000` (each run's",
        "`probe.txt`): probes are fitted on 3000 episodes and tested on the other 1000; the policy's accuracy, the spike",
        "counter and the per-margin accuracies are over all 4000. The spike counter is a reference, not a model: it decides",
        "`left-population spikes > right-population spikes` counted over the whole episode. The noise-free plastic input",
        "is `(alpha * E) x` per hidden neuron with the decision frame's input spikes `x` replaced by their mean; the",
        "left-minus-right sums are, per hidden neuron, its left-cue trace columns' sum minus its right-cue ones'.", "",
        "| run | " + " | ".join(title for _, title in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|",
    ]
    values = []
    for run in runs:
        text = (out_dir / "runs" / run / "probe.txt").read_text()
        row = [float(re.search(pattern + r"\s+([0-9.]+)", text).group(1)) for pattern, _ in COLUMNS]
        values.append(row)
        lines.append(f"| {run.replace('TMazeCueNoisy-v0_', '')} | " + " | ".join(f"{v:.3f}" for v in row) + " |")
    lines.append("| **mean** | " + " | ".join(f"{v:.3f}" for v in np.mean(values, 0)) + " |")
    (out_dir / "probes.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
