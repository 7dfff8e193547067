"""The bare line against SB3's: ``PPO("SpikePlasticPolicy", env)`` and ``PPO("MlpPolicy", env)``, both with
every default, the same seeds, one process, the two interleaved seed by seed.

For each run: environment steps per second of ``learn``, the largest and the median gradient norm of the
spiking model's minibatches (before clipping), its action std at the end, the mean deterministic return of
``--eval-episodes`` held-out episodes (``evaluate_policy``) every ``--eval-every`` steps and at the end, and the
last rollout return. Writes ``bare_line.json`` and ``bare_line.md`` into ``--out`` (with the command and the
machine's load from ``uptime`` before and after) and prints the table.

    python benchmarks/bare_line.py --env HalfCheetah-v5 --steps 150000 --seeds 0 1 2 --out results/bare_line

``--checks`` instead trains the bare line briefly (``--steps``, seed 0) with every built-in rule on HalfCheetah-v5
(and ndp-oja's linear modulation), and bare on NoisyHalfCheetah-v5, Pendulum-v1 and TMazeCue-v0: gradient norms,
action std before and after, rollout return (and the T-maze's deterministic success over 100 episodes), written
to ``checks.json`` / ``checks.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

import sb3_spikeplastic  # noqa: F401  (registers the environments)
from sb3_spikeplastic import PPO


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=10).stdout.strip()
    except OSError:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())


class Evaluations(BaseCallback):
    """Mean deterministic return on held-out episodes every ``every`` steps (the time it takes is not
    counted as training time)."""

    def __init__(self, env_id: str, every: int, episodes: int, seed: int):
        super().__init__()
        self.env_id, self.every, self.episodes, self.seed = env_id, every, episodes, seed
        self.results: list[tuple[int, float, float]] = []
        self.eval_seconds, self._next = 0.0, every

    def evaluate(self) -> tuple[float, float]:
        start = time.perf_counter()
        env = make_vec_env(self.env_id, n_envs=1, seed=self.seed)
        mean, std = evaluate_policy(self.model, env, n_eval_episodes=self.episodes, deterministic=True)
        env.close()
        self.eval_seconds += time.perf_counter() - start
        return float(mean), float(std)

    def _on_step(self) -> bool:
        if self.every and self.num_timesteps >= self._next:
            self._next += self.every
            self.results.append((self.num_timesteps, *self.evaluate()))
        return True


def record_gradient_norms(model: PPO) -> list[float]:
    """Every minibatch's global gradient norm before clipping (spiking policies; ``nan`` for a skipped step)."""
    norms: list[float] = []
    clip = model._clip_gradients

    def recording():
        total = clip()
        norms.append(float("nan") if total is None else total)
        return total

    model._clip_gradients = recording
    return norms


def run(policy: str, env_id: str, steps: int, seed: int, eval_every: int, episodes: int) -> dict:
    torch.manual_seed(seed)
    model = PPO(policy, env_id, seed=seed)
    norms = record_gradient_norms(model) if model.recurrent else None
    evaluations = Evaluations(env_id, eval_every, episodes, seed=10_000 + seed)
    start = time.perf_counter()
    model.learn(steps, callback=evaluations)
    train_seconds = time.perf_counter() - start - evaluations.eval_seconds
    final = evaluations.results[-1][1:] if evaluations.results and evaluations.results[-1][0] >= steps else None
    if final is None:
        final = evaluations.evaluate()
        evaluations.results.append((model.num_timesteps, *final))
    episodes_seen = [e["r"] for e in model.ep_info_buffer]
    finite = [n for n in norms or [] if math.isfinite(n)]
    return dict(
        policy=policy,
        seed=seed,
        steps=model.num_timesteps,
        train_seconds=round(train_seconds, 1),
        env_steps_per_s=round(model.num_timesteps / train_seconds, 1),
        final_return=round(final[0], 1),
        final_return_std=round(final[1], 1),
        evaluations=[[s, round(m, 1)] for s, m, _ in evaluations.results],
        rollout_return=round(float(np.mean(episodes_seen)), 1) if episodes_seen else None,
        std=round(float(torch.exp(model.policy.log_std).mean()), 4) if hasattr(model.policy, "log_std") else None,
        grad_norm_max=round(max(finite), 2) if finite else None,
        grad_norm_median=round(float(np.median(finite)), 3) if finite else None,
        skipped_steps=sum(not math.isfinite(n) for n in norms) if norms is not None else None,
    )


CHECKS = [
    ("HalfCheetah-v5", dict(rule=rule)) for rule in ("static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm")
] + [
    ("HalfCheetah-v5", dict(rule="ndp-oja", rule_kwargs=dict(modulation="linear"))),
    ("NoisyHalfCheetah-v5", {}),
    ("Pendulum-v1", {}),
    ("TMazeCue-v0", {}),
]


def tmaze_success(model, episodes: int = 100) -> float:
    """Deterministic success over ``episodes`` episodes of 20 seeded T-mazes (``evaluate``'s own evaluation)."""
    from sb3_spikeplastic.zoo.evaluation import evaluate_model
    from sb3_spikeplastic.zoo.run_folder import make_eval_env

    return evaluate_model(model, make_eval_env("TMazeCue-v0", 20, 123, {}), episodes).success_rate


def check(env_id: str, policy_kwargs: dict, steps: int) -> dict:
    torch.manual_seed(0)
    model = PPO("SpikePlasticPolicy", env_id, seed=0, policy_kwargs=policy_kwargs or None)
    norms = record_gradient_norms(model)
    std = (lambda: float(torch.exp(model.policy.log_std.detach()).mean())) if hasattr(model.policy, "log_std") else None
    std_start = std() if std else None
    start = time.perf_counter()
    model.learn(steps)
    seconds = time.perf_counter() - start
    finite = [n for n in norms if math.isfinite(n)]
    episodes = [e["r"] for e in model.ep_info_buffer]
    return dict(
        env=env_id,
        policy_kwargs=policy_kwargs,
        steps=model.num_timesteps,
        env_steps_per_s=round(model.num_timesteps / seconds, 1),
        updates=model._n_updates // model.n_epochs,
        grad_norm_max=round(max(finite), 2),
        grad_norm_median=round(float(np.median(finite)), 2),
        nonfinite=len(norms) - len(finite),
        std_start=std_start and round(std_start, 4),
        std_end=round(std(), 4) if std else None,
        rollout_return=round(float(np.mean(episodes)), 1) if episodes else None,
        success=tmaze_success(model) if env_id.startswith("TMazeCue") else None,
    )


def checks_markdown(report: dict) -> str:
    lines = [
        '# Bare line, brief checks: `PPO("SpikePlasticPolicy", env, policy_kwargs=...)`, seed 0',
        "",
        f"Command: `{report['command']}`",
        "",
        f"Machine: {report['machine']}; torch threads {report['torch_threads']}; commit {report['commit']}",
        "",
        f"Load before: `{report['uptime_before']}`",
        "",
        f"Load after: `{report['uptime_after']}`",
        "",
        "| env | policy_kwargs | steps (updates) | env-steps/s | grad norm max / median (non-finite) | std start "
        "→ end | rollout return | deterministic success (100 ep.) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in report["checks"]:
        std = "-" if r["std_start"] is None else f"{r['std_start']} → {r['std_end']}"
        lines.append(
            f"| {r['env']} | `{json.dumps(r['policy_kwargs'])}` | {r['steps']} ({r['updates']}) | "
            f"{r['env_steps_per_s']:g} | {r['grad_norm_max']:.3g} / {r['grad_norm_median']:.3g} "
            f"({r['nonfinite']}) | {std} | {r['rollout_return']} | "
            f"{'-' if r['success'] is None else r['success']} |"
        )
    return "\n".join(lines) + "\n"


def markdown(report: dict) -> str:
    lines = [
        f'# Bare line: `PPO(policy, "{report["env"]}")` with every default',
        "",
        f"Command: `{report['command']}`",
        "",
        f"Machine: {report['machine']}; torch threads {report['torch_threads']}; commit {report['commit']}",
        "",
        f"Load before: `{report['uptime_before']}`",
        "",
        f"Load after: `{report['uptime_after']}`",
        "",
        "| policy | seed | steps | env-steps/s | grad norm max / median | final std | deterministic return "
        f"({report['eval_episodes']} ep.) | rollout return | return during training |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        norms = "-" if r["grad_norm_max"] is None else f"{r['grad_norm_max']:g} / {r['grad_norm_median']:g}"
        curve = ", ".join(f"{s // 1000}k: {m:g}" for s, m in r["evaluations"])
        lines.append(
            f"| {r['policy']} | {r['seed']} | {r['steps']} | {r['env_steps_per_s']:g} | {norms} | "
            f"{r['std'] if r['std'] is not None else '-'} | {r['final_return']:g} ± {r['final_return_std']:g}"
            f" | {r['rollout_return']} | {curve} |"
        )
    lines += ["", "| policy | mean final return over seeds | mean env-steps/s |", "|---|---|---|"]
    for policy in report["policies"]:
        runs = [r for r in report["runs"] if r["policy"] == policy]
        lines.append(
            f"| {policy} | {np.mean([r['final_return'] for r in runs]):.1f} | "
            f"{np.mean([r['env_steps_per_s'] for r in runs]):.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--steps", type=int, default=150_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--policies", nargs="+", default=["SpikePlasticPolicy", "MlpPolicy"])
    parser.add_argument("--eval-every", type=int, default=50_000, help="0: only at the end")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--out", default="results/bare_line")
    parser.add_argument("--checks", action="store_true", help="brief checks of every rule and env (see above)")
    parser.add_argument("--only", nargs="+", help="with --checks: only the checks of these env ids")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.torch_threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    report = dict(
        env=args.env,
        command=shlex.join([Path(sys.executable).name, *sys.argv]),
        commit=commit or None,
        machine=f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        torch_threads=args.torch_threads,
        eval_episodes=args.eval_episodes,
        policies=args.policies,
        uptime_before=uptime(),
        runs=[],
    )
    if args.checks:
        report["checks"] = []
        for env_id, policy_kwargs in [c for c in CHECKS if not args.only or c[0] in args.only]:
            report["checks"].append(check(env_id, policy_kwargs, args.steps))
            print(json.dumps(report["checks"][-1]), flush=True)
            report["uptime_after"] = uptime()
            (out / "checks.json").write_text(json.dumps(report, indent=1) + "\n")
            (out / "checks.md").write_text(checks_markdown(report))
        print(checks_markdown(report))
        return
    for seed in args.seeds:
        for policy in args.policies:
            result = run(policy, args.env, args.steps, seed, args.eval_every, args.eval_episodes)
            report["runs"].append(result)
            print(json.dumps(result), flush=True)
            report["uptime_after"] = uptime()
            (out / "bare_line.json").write_text(json.dumps(report, indent=1) + "\n")
            (out / "bare_line.md").write_text(markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
