"""The HalfCheetah table script on synthetic per-episode returns: absolute returns and ratios as computed by hand,
models that did not learn listed apart and left out, and verdicts only where the interval excludes 0."""

import csv

import numpy as np
import pytest
from helpers import load_experiment

from sb3_spikeplastic.robustness import RobustnessRow, write_episodes_csv

SIGMAS = (0.0, 0.2, 0.4)


@pytest.fixture(scope="module")
def fig4_table():
    return load_experiment("fig4_table")


def write_model(out, name, r0, losses, rng, noise="action"):
    """``name``'s episodes: mean ``r0 * (1 - loss)`` at each sigma, episode noise of 20."""
    rows = []
    for sigma, loss in zip(SIGMAS, losses):
        returns = tuple(r0 * (1 - loss) + rng.normal(0, 20, size=50))
        rows.append(RobustnessRow(name, noise, sigma, float(np.mean(returns)), 0.0, 50, 0.0, returns))
    write_episodes_csv(rows, out / "robustness" / name / f"robustness_HalfCheetah-v5_{noise}_episodes.csv")
    return rows


def test_table_and_verdicts(tmp_path, fig4_table, capsys):
    rng = np.random.default_rng(0)
    written = {}
    for seed, r0 in enumerate((2800, 3000, 3200)):
        written[f"static@300k_s{seed}"] = write_model(tmp_path, f"static@300k_s{seed}", r0, (0, 0.3, 0.6), rng)
        written[f"dp-oja@300k_s{seed}"] = write_model(tmp_path, f"dp-oja@300k_s{seed}", r0 - 400, (0, 0.1, 0.2), rng)
        write_model(tmp_path, f"dp-bcm@300k_s{seed}", r0, (0, 0.3, 0.6), rng)  # as static: nothing to resolve
        write_model(tmp_path, f"mlp@300k_s{seed}", r0 + 1000, (0, 0.3, 0.6), rng)
    write_model(tmp_path, "ndp-oja@300k_s0", -10, (0, 0, 0), rng)  # never learned: ratio 1 means nothing
    assert fig4_table.main(["--out", str(tmp_path), "--resamples", "300"]) == 0

    table = (tmp_path / "table.md").read_text()
    assert "Did not learn (R0 < 1000): ndp-oja@300k_s0." in table
    (line,) = [line for line in table.splitlines() if line.startswith("| ndp-oja@300k |")]
    assert line.startswith("| ndp-oja@300k | 0 of 1 | -") and line.endswith(" (did not learn) | - |")
    with open(tmp_path / "fig4.csv") as f:
        rows = {(r["group"], float(r["sigma"])): r for r in csv.DictReader(f)}
    assert ("ndp-oja@300k", 0.0) not in rows
    static = [written[f"static@300k_s{s}"] for s in range(3)]
    by_hand = np.mean([seed[2].mean_return for seed in static])
    ratio = np.mean([seed[2].mean_return / seed[0].mean_return for seed in static])
    assert float(rows[("static@300k", 0.4)]["return_estimate"]) == pytest.approx(by_hand, abs=0.1)
    assert float(rows[("static@300k", 0.4)]["ratio_estimate"]) == pytest.approx(ratio, abs=1e-4)

    with open(tmp_path / "verdicts.csv") as f:
        verdicts = {r["model"]: r for r in csv.DictReader(f)}
    oja = verdicts["dp-oja@300k"]
    assert oja["reference"] == "static@300k" and oja["auc_verdict"] == "loses less"
    assert float(oja["r0_difference_estimate"]) == pytest.approx(-400, abs=30)
    assert oja["return_verdict"] == "higher"  # 0.8 * 2600 = 2080 against 0.4 * 3000 = 1200
    assert verdicts["dp-bcm@300k"]["auc_verdict"] == "not resolved"
    pooled = next(r for name, r in verdicts.items() if name.startswith("plastic@300k (pooled"))
    assert int(pooled["seeds"]) == 6  # dp-oja and dp-bcm; ndp-oja did not learn
    assert "| dp-oja@300k | static@300k | 3 vs 3 |" in (tmp_path / "verdicts.md").read_text()
    # the baseline against both fixed references, never against the best plastic group picked on these data
    with open(tmp_path / "verdicts.csv") as f:
        mlp = {r["reference"]: r for r in csv.DictReader(f) if r["model"] == "mlp@300k"}
    assert set(mlp) == {"static@300k", "dp-oja@300k"}
    assert mlp["static@300k"]["auc_verdict"] == "not resolved" and mlp["dp-oja@300k"]["auc_verdict"] == "loses more"
    assert (tmp_path / "robustness.png").read_bytes()[:4] == b"\x89PNG"


def test_training_curves_average_only_the_seeds_that_reached_a_step(tmp_path, fig4_table):
    """A 300k-step seed beside a 1M-step seed: past 300k the curve is the long seed alone, not a flat extrapolation
    of the short one."""
    for seed, steps, value in ((0, (100_000, 300_000), 1000.0), (1, (100_000, 300_000, 1_000_000), 3000.0)):
        folder = tmp_path / "runs" / f"static_{seed}" / "ppo" / "HalfCheetah-v5_1"
        folder.mkdir(parents=True)
        np.savez(folder / "evaluations.npz", timesteps=np.array(steps),
                 results=np.full((len(steps), 5), value))
    curves = fig4_table.training_curves(tmp_path, [dict(variant="static", seed=0), dict(variant="static", seed=1)])
    by_step = {row["steps"]: row for row in curves}
    assert by_step[300_000]["seeds"] == 2 and by_step[300_000]["mean"] == 2000.0
    assert by_step[1_000_000]["seeds"] == 1 and by_step[1_000_000]["mean"] == 3000.0
    assert (tmp_path / "training_curves.png").exists()
