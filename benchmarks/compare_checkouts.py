"""``learn()`` throughput of two checkouts of the package in interleaved rounds: does a change cost speed?

Each round runs ``benchmarks/learn_throughput.py --only ROWS`` once per checkout, in the order A, B (the next round
B, A), each checkout's own script with its own package first on ``PYTHONPATH``, so that both see the same machine
state as nearly as possible. Prints every run and the median per row and checkout, and writes them as JSON.

Usage (documented in benchmarks/README.md)::

    git worktree add /tmp/before <commit>
    python benchmarks/compare_checkouts.py /tmp/before . --rows entry bare --rounds 3 \\
        --output benchmarks/results/compare_checkouts.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def run_rows(checkout: Path, rows: list[str], threads: int) -> list[dict]:
    """One run of ``learn_throughput.py`` of ``checkout``: its rows as it records them."""
    with tempfile.TemporaryDirectory() as folder:
        output = Path(folder) / "rows.json"
        env = {**os.environ, "PYTHONPATH": str(checkout)}
        subprocess.run(
            [
                sys.executable,
                str(checkout / "benchmarks" / "learn_throughput.py"),
                "--only",
                *rows,
                "--threads",
                str(threads),
                "--output",
                str(output),
            ],
            check=True,
            env=env,
            cwd=checkout,
        )
        return json.loads(output.read_text())["rows"]


def commit_of(checkout: Path) -> str:
    """The checkout's commit (with ``+`` where its tracked files differ from it), or ``?`` outside git."""

    def git(*command: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(checkout), *command], capture_output=True, text=True)

    head = git("rev-parse", "--short", "HEAD")
    if head.returncode:
        return "?"
    return head.stdout.strip() + ("+" if git("diff", "--quiet", "HEAD").returncode else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkouts", type=Path, nargs=2, help="the two checkouts (A, B)")
    parser.add_argument("--rows", nargs="+", default=["entry", "bare"], help="rows of learn_throughput.py")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "compare_checkouts.json")
    args = parser.parse_args()
    checkouts = [c.resolve() for c in args.checkouts]
    commits = [commit_of(c) for c in checkouts]
    runs = []
    for round_ in range(args.rounds):
        for checkout in checkouts if round_ % 2 == 0 else checkouts[::-1]:
            load = os.getloadavg()[0] / (os.cpu_count() or 1)
            for row in run_rows(checkout, args.rows, args.threads):
                runs.append(
                    dict(
                        round=round_,
                        checkout=str(checkout),
                        row=row["name"],
                        load_per_core=round(load, 2),
                        env_steps_per_s=row["env_steps_per_s"],
                        peak_rss_mb=row["peak_rss_mb"],
                    )
                )
                print(
                    f"round {round_}  {checkout.name:>12}  {row['name'][:60]:60}  "
                    f"{row['env_steps_per_s']:7.1f} env-steps/s  load/core {load:.2f}",
                    flush=True,
                )
    summary = {}
    for row in dict.fromkeys(r["row"] for r in runs):
        for checkout in checkouts:
            speeds = [r["env_steps_per_s"] for r in runs if r["row"] == row and r["checkout"] == str(checkout)]
            summary.setdefault(row, {})[str(checkout)] = dict(median=statistics.median(speeds), runs=speeds)
        a, b = (summary[row][str(c)]["median"] for c in checkouts)
        summary[row]["b_over_a"] = b / a
        print(f"{row[:60]:60}  A {a:7.1f}  B {b:7.1f}  B/A {b / a:.3f}")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(
        json.dumps(
            dict(
                checkouts=[str(c) for c in checkouts],
                commits=commits,
                threads=args.threads,
                runs=runs,
                summary=summary,
            ),
            indent=1,
        )
    )
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
