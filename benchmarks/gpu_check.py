"""The GPU check: the test suite, every command and the Python API on ``cuda``, and moving models between devices.

Run on a machine with a CUDA GPU, from the repository root, with the package and its test extras installed::

    MUJOCO_GL=egl python benchmarks/gpu_check.py                 # -> benchmarks/results/gpu_check.md
    MUJOCO_GL=egl python benchmarks/gpu_check.py --pytest-args "-q -rfE -n 8"   # with pytest-xdist
    MUJOCO_GL=egl python benchmarks/gpu_check.py --only benchmark   # learn_throughput.py --device cuda
    MUJOCO_GL=egl python benchmarks/gpu_check.py --only sweep       # env-steps/s against the number of environments

Each check runs as its own subprocess with a time limit; the verdict is one table (check, PASS/FAIL, seconds, what
it measured), printed and written as Markdown with the machine, torch and CUDA versions. Logs of every check go to
``--logs``. The checks:

* ``pytest``: the default suite, every model on the GPU (SB3's ``device="auto"``);
* ``train`` / ``-i`` / ``evaluate`` / ``inspect`` on ``cuda`` for the T-maze (discrete, action masks, ndp-oja) and
  HalfCheetah (Box, VecNormalize, the shipped entry), ``robustness`` and ``enjoy --video`` for HalfCheetah;
* ``every rule``: one update of each built-in rule (and the NDP rules' tanh form) on ``cuda``, finite parameters;
* ``cuda -> cpu`` / ``cpu -> cuda``: a model saved on one device loads on the other and takes the same
  deterministic actions over 60 steps, the recurrent state carried through (float tolerance; the T-maze's actions
  under its action masks, as the environment takes them);
* ``paper network``: ``train --conf paper --device cuda`` for a short run, its env-steps/s;
* ``sweep`` (only when asked): ``learn_throughput.py``'s ``paper-conf`` and ``recurrent`` rows with 8, 16, 32 and
  64 environments, each written to ``benchmarks/results/learn_throughput_cuda_<N>envs.json``, and 2 and 4
  ``paper-conf`` trainings at once (``learn_throughput_cuda_x<K>.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: the groups of checks, in the order they run
GROUPS = ("suite", "tmaze", "cheetah", "rules", "devices", "paper", "benchmark", "sweep")
#: environments of the ``sweep`` group's rows
SWEEP_ENVS = (8, 16, 32, 64)
CLI = [sys.executable, "-m", "sb3_spikeplastic.cli"]

#: the cross-device check, run in a subprocess: ``python -c CROSS_DEVICE <model.zip> <env id> <from> <to>``
CROSS_DEVICE = r"""
import sys, numpy as np, torch
from sb3_spikeplastic import PPO
path, env_id, source, target = sys.argv[1:]
import gymnasium as gym
from stable_baselines3.common.env_util import make_vec_env
actions = {}
for device in (source, target):
    model = PPO.load(path, device=device)
    env = make_vec_env(env_id, n_envs=2, seed=0)
    masked = hasattr(env.envs[0].unwrapped, "action_masks")  # the T-maze: only the decision frame's action counts
    obs, state, starts, taken = env.reset(), None, np.ones(2, bool), []
    for _ in range(60):
        masks = np.stack(env.env_method("action_masks")) if masked else None
        action, state = model.predict(obs, state=state, episode_start=starts, deterministic=True, action_masks=masks)
        taken.append(np.asarray(action, dtype=np.float64))
        obs, _, starts, _ = env.step(action)
    actions[device] = np.stack(taken)
gap = np.abs(actions[source] - actions[target])
print(f"max |action difference| over 60 steps x 2 envs: {gap.max():.2e} ({int((gap > 1e-3).sum())} actions differ)")
sys.exit(0 if gap.max() <= 1e-3 else 1)
"""

#: prefix of CROSS_DEVICE: trains a small model for 128 steps on the source device and saves it at the path
SAVE_SMALL = r"""
import sys
from sb3_spikeplastic import PPO
path, env_id, source = sys.argv[1:4]
PPO("SpikePlasticPolicy", env_id, n_steps=64, batch_size=64, bptt_steps=16, device=source, seed=0,
    policy_kwargs=dict(rule="ndp-oja", hidden_sizes=[32], steps=10 if env_id == "Pendulum-v1" else None,
                       encoder_pop_size=10, action_pop_size=8)).learn(128).save(path)
"""

#: one update of every built-in rule on the GPU (Python API), as ``python -c EVERY_RULE``
EVERY_RULE = r"""
import torch
from sb3_spikeplastic import PPO, available_rules
rows = []
for rule, kwargs in [(r, {}) for r in available_rules()] + [
        (r, {"modulation": m}) for r in ("ndp-oja", "ndp-bcm") for m in ("linear", "tanh")]:
    model = PPO("SpikePlasticPolicy", "Pendulum-v1", n_steps=64, batch_size=64, bptt_steps=16, n_epochs=2,
                device="cuda", seed=0, policy_kwargs=dict(rule=rule, rule_kwargs=kwargs, hidden_sizes=[32],
                                                          steps=10, encoder_pop_size=10, action_pop_size=8))
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(128)
    after = list(model.policy.parameters())
    finite = all(torch.isfinite(p).all() for p in after)
    moved = any(not torch.equal(a, b) for a, b in zip(after, before))
    norm = model.logger.name_to_value.get("train/grad_norm", float("nan"))
    rows.append(f"{rule}{'+' + kwargs['modulation'] if kwargs else ''}: grad_norm {norm:.3g}")
    graphs_ok = model._graphed_step.error is None and model._graphed_evaluation.error is None
    assert finite and moved and graphs_ok, (rule, kwargs, finite, moved, graphs_ok)
print("; ".join(rows))
"""


def run(name: str, argv: list[str], logs: Path, timeout: float, cwd: Path, env: dict) -> dict:
    """Run one check; its output goes to ``logs/<name>.log``. Returns its verdict row."""
    start = time.perf_counter()
    log = logs / (re.sub(r"[^A-Za-z0-9_.-]+", "_", name) + ".log")
    try:
        result = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
        output, ok = result.stdout + result.stderr, result.returncode == 0
    except subprocess.TimeoutExpired as exc:
        output = (exc.stdout or b"").decode(errors="replace") + (exc.stderr or b"").decode(errors="replace")
        output, ok = output + f"\n[timed out after {timeout:.0f} s]", False
    log.write_text(" ".join(argv) + "\n\n" + output)
    seconds = time.perf_counter() - start
    return {"check": name, "ok": ok, "seconds": round(seconds, 1), "note": summarise(name, output, ok)}


def summarise(name: str, output: str, ok: bool) -> str:
    """The line of a check's output that says what it measured (or why it failed)."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    patterns = [
        r"\d+ (passed|failed)",
        r"max \|action",
        r"grad_norm",
        r"success",
        r"mean return|return",
        r"env-steps/s|fps",
        r"Error|error",
    ]
    for pattern in patterns:
        hits = [line for line in lines if re.search(pattern, line)]
        if hits:
            return hits[-1][:160]
    return (lines[-1][:160] if lines else "") if not ok else ""


def machine() -> str:
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no CUDA device"
    driver = ""
    if shutil.which("nvidia-smi"):
        driver = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True, text=True
        ).stdout.strip()
    versions = []
    for package in ("stable_baselines3", "sb3_contrib", "gymnasium", "mujoco"):
        try:
            versions.append(f"{package} {__import__(package).__version__}")
        except ImportError:
            versions.append(f"{package} missing")
    return (
        f"{gpu} (driver {driver or '?'}), {os.cpu_count()} CPU cores, Python {platform.python_version()}, "
        f"torch {torch.__version__} (CUDA {torch.version.cuda}), " + ", ".join(versions)
    )


def latest_run(folder: Path, env_id: str) -> Path:
    runs = sorted((folder / "ppo").glob(f"{env_id}_*"), key=lambda p: int(p.name.rsplit("_", 1)[1]))
    return runs[-1] if runs else folder / "ppo" / f"{env_id}_missing"


def write_verdict(rows: list[dict], output: Path, argv) -> int:
    """Write the verdict table (Markdown) and its rows (JSON) beside it; returns the number of checks passed."""
    passed = sum(row["ok"] for row in rows)
    command = " ".join(["python", "benchmarks/gpu_check.py", *(argv if argv is not None else sys.argv[1:])])
    lines = [
        "# GPU check",
        "",
        f"`{command}`, {time.strftime('%Y-%m-%d')}, on {machine()}.",
        "",
        f"**{passed} of {len(rows)} checks passed.**",
        "",
        "| check | verdict | seconds | measured |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['check']} | {'PASS' if r['ok'] else 'FAIL'} | {r['seconds']} | {r['note'].replace('|', '/')} |"
        for r in rows
    ]
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text("\n".join(lines) + "\n")
    output.with_suffix(".json").write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1) + "\n")
    return passed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "gpu_check.md")
    parser.add_argument("--logs", type=Path, default=None, help="folder for every check's log (default: a temp dir)")
    parser.add_argument(
        "--pytest-args",
        default="-q -p no:cacheprovider -rfE",
        help="arguments of the suite's pytest (default: %(default)s)",
    )
    parser.add_argument(
        "--only",
        nargs="+",
        choices=GROUPS,
        default=[g for g in GROUPS if g not in ("benchmark", "sweep")],
        help="groups of checks to run (default: all but benchmark and sweep)",
    )
    parser.add_argument(
        "--benchmark-args",
        default="--only ndp-oja recurrent entry entry-recurrent paper-conf",
        help="arguments of learn_throughput.py --device cuda (default: %(default)s)",
    )
    args = parser.parse_args(argv)
    import torch

    if not torch.cuda.is_available():
        parser.error("no CUDA device: the GPU check runs on a machine with a CUDA GPU and a CUDA build of torch")

    logs = args.logs or Path(tempfile.mkdtemp(prefix="gpu_check_logs_"))
    logs.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="gpu_check_"))
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    rows: list[dict] = []

    def check(name, command, timeout=300, cwd=work):
        row = run(name, command, logs, timeout, cwd, env)
        rows.append(row)
        write_verdict(rows, args.output, argv)  # after every check: a run cut short keeps its verdicts
        print(f"{'PASS' if row['ok'] else 'FAIL'}  {name:<34} {row['seconds']:7.1f} s  {row['note']}", flush=True)
        return row

    if "suite" in args.only:
        # From tests/, so that the installed package is imported (an editable install or a wheel alike).
        check(
            "pytest (default suite on cuda)",
            [sys.executable, "-m", "pytest", "-c", "../pyproject.toml", "--rootdir", "..", *args.pytest_args.split()],
            timeout=1800,
            cwd=ROOT / "tests",
        )

    runs = work / "logs"
    common = ["--device", "cuda", "--seed", "0", "-f", str(runs), "--no-progress", "-v", "0"]
    if "tmaze" in args.only:
        check(
            "train TMazeCue-v0 ndp-oja",
            CLI
            + [
                "train",
                "--env",
                "TMazeCue-v0",
                "--rule",
                "ndp-oja",
                "-n",
                "8192",
                "--save-freq",
                "4096",
                "--figure-freq",
                "1",
                "--tensorboard-log",
                str(work / "tb"),
                *common,
            ],
        )
        tmaze = latest_run(runs, "TMazeCue-v0")
        checkpoint = sorted(tmaze.glob("rl_model_*_steps.zip"))
        check(
            "train -i (resume T-maze)",
            CLI
            + [
                "train",
                "--env",
                "TMazeCue-v0",
                "-n",
                "12288",
                "-i",
                str(checkpoint[-1] if checkpoint else tmaze),
                *common,
            ],
        )
        check(
            "evaluate T-maze (energy)",
            CLI + ["evaluate", "--run", str(tmaze), "--episodes", "20", "--device", "cuda", "--no-progress"],
        )
        check("inspect T-maze", CLI + ["inspect", "--run", str(tmaze), "--device", "cuda", "--no-progress"])
    if "cheetah" in args.only:
        check(
            "train HalfCheetah-v5 (entry)",
            CLI
            + [
                "train",
                "--env",
                "HalfCheetah-v5",
                "-n",
                "8192",
                "--save-freq",
                "4096",
                "--eval-freq",
                "4096",
                "--eval-episodes",
                "2",
                *common,
            ],
        )
        cheetah = latest_run(runs, "HalfCheetah-v5")
        check(
            "evaluate HalfCheetah (VecNormalize)",
            CLI + ["evaluate", "--run", str(cheetah), "--episodes", "2", "--device", "cuda", "--no-progress"],
        )
        check(
            "robustness HalfCheetah",
            CLI
            + [
                "robustness",
                "--models",
                f"entry={cheetah}",
                "--noise",
                "action",
                "--sigmas",
                "0",
                "0.2",
                "--episodes",
                "2",
                "--n-envs",
                "2",
                "--device",
                "cuda",
                "-o",
                str(work / "robustness"),
                "--no-progress",
            ],
        )
        check(
            "enjoy --video HalfCheetah",
            CLI
            + [
                "enjoy",
                "--run",
                str(cheetah),
                "--n-episodes",
                "1",
                "--max-steps",
                "100",
                "--video",
                str(work / "cheetah.gif"),
                "--device",
                "cuda",
                "--no-progress",
            ],
        )
    if "rules" in args.only:
        check("every rule, Python API", [sys.executable, "-c", EVERY_RULE])
    if "devices" in args.only:
        for env_id, source, target, what in (
            ("TMazeCue-v0", "cuda", "cpu", "T-maze, masks"),
            ("Pendulum-v1", "cpu", "cuda", "Pendulum, Box"),
        ):
            path = work / f"{env_id}_{source}.zip"
            check(
                f"{source} -> {target} ({what})",
                [sys.executable, "-c", SAVE_SMALL + CROSS_DEVICE, str(path), env_id, source, target],
            )
    if "paper" in args.only:
        check(
            "train --conf paper (20k steps)",
            CLI + ["train", "--env", "HalfCheetah-v5", "--conf", "paper", "-n", "20480", *common[:-2], "-v", "1"],
            timeout=600,
        )
    if "benchmark" in args.only:
        check(
            "learn_throughput --device cuda",
            [sys.executable, "benchmarks/learn_throughput.py", "--device", "cuda", *args.benchmark_args.split()],
            timeout=1800,
            cwd=ROOT,
        )
    if "sweep" in args.only:  # throughput against the number of environments, the same rollout size
        for n_envs in SWEEP_ENVS:
            check(
                f"learn_throughput, {n_envs} environments",
                [
                    sys.executable,
                    "benchmarks/learn_throughput.py",
                    "--device",
                    "cuda",
                    "--only",
                    "paper-conf",
                    "recurrent",
                    "--threads",
                    "1",
                    "--n-envs",
                    str(n_envs),
                    "--output",
                    f"benchmarks/results/learn_throughput_cuda_{n_envs}envs.json",
                ],
                timeout=900,
                cwd=ROOT,
            )
        for concurrent in (2, 4):  # several trainings sharing the GPU, as a grid runs them
            check(
                f"learn_throughput, {concurrent} trainings at once",
                [
                    sys.executable,
                    "benchmarks/learn_throughput.py",
                    "--device",
                    "cuda",
                    "--only",
                    "paper-conf",
                    "--threads",
                    "1",
                    "--concurrent",
                    str(concurrent),
                    "--output",
                    f"benchmarks/results/learn_throughput_cuda_x{concurrent}.json",
                ],
                timeout=900,
                cwd=ROOT,
            )

    passed = write_verdict(rows, args.output, argv)
    print(f"\n{passed} of {len(rows)} checks passed; logs in {logs}; verdict in {args.output}")
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
