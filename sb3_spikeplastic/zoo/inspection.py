"""``sb3-spikeplastic inspect``: the activity figures of a trained model on the episodes
:func:`sb3_spikeplastic.zoo.recording.inspection_episodes` chooses.

Matplotlib is imported only when a figure is drawn, and only through ``matplotlib.figure.Figure`` (the Agg
renderer, no GUI backend).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

import torch


def inspect_command(
    run: Optional[str] = None,
    model: Optional[str] = None,
    env: Optional[str] = None,
    vecnormalize: Optional[str] = None,
    best: bool = False,
    env_kwargs: Optional[Sequence[str]] = None,
    output: Optional[str] = None,
    seed: int = 0,
    max_steps: Optional[int] = None,
    deterministic: bool = True,
    no_progress: bool = False,
    device: str = "cpu",
    torch_threads: int = 1,
    folder: Optional[str] = None,
    exp_id: int = 0,
    load_checkpoint: Optional[int] = None,
    load_last_checkpoint: bool = False,
) -> Callable[[], int]:
    """``sb3-spikeplastic inspect`` with these options (its long names): the model is found, loaded and checked
    (``ValueError``, nothing written); returns the inspection, which records each of :func:`inspection_episodes`
    (``typical`` from :func:`typical_seed`), draws it into ``<output>/activity_<name>.png`` (default:
    ``<run>/figures``), prints a line per episode and returns 0."""
    from .evaluation import check_fits
    from .inputs import check_output_path, model_source
    from .recording import inspection_episodes, record_episode, typical_seed
    from .run_folder import cpu_settings_of, load_model, make_eval_env

    if output:
        check_output_path(output, "-o/--output", directory=True)
    info, env_id = model_source(
        run, model, env, vecnormalize, best, env_kwargs, folder, exp_id, load_checkpoint, load_last_checkpoint
    )
    torch.set_num_threads(torch_threads)
    loaded = load_model(info, device)
    if not hasattr(loaded.policy, "snn"):
        raise ValueError(f"{str(info.model_path)!r} is not a SpikePlasticPolicy model")
    obs_transform = None
    if info.vecnormalize is not None:
        from stable_baselines3.common.vec_env import VecNormalize

        stats = VecNormalize.load(str(info.vecnormalize), make_eval_env(env_id, 1, 0, info.env_kwargs))
        obs_transform = stats.normalize_obs
    check_fits(loaded, info, env_id, make_error=f"cannot make {env_id}")
    episodes = inspection_episodes(env_id, info.env_kwargs)
    out = Path(output) if output else (info.run_dir / "figures" if info.run_dir else Path("figures"))

    def inspect() -> int:
        with cpu_settings_of(loaded):
            return draw()

    def draw() -> int:
        import matplotlib
        from tqdm.auto import tqdm

        matplotlib.use("Agg")
        from .figures import activity_figure

        out.mkdir(parents=True, exist_ok=True)
        bar = tqdm(
            episodes.items(), total=len(episodes), unit="episode", disable=no_progress, dynamic_ncols=True, leave=False
        )
        for name, make in bar:
            episode_seed, note = seed, None
            if name == "typical":
                episode_seed, note = typical_seed(
                    loaded.policy, make, seed, deterministic=deterministic, obs_transform=obs_transform
                )
            episode_env = make()
            try:
                activity = record_episode(
                    loaded.policy,
                    episode_env,
                    seed=episode_seed,
                    deterministic=deterministic,
                    max_steps=max_steps,
                    obs_transform=obs_transform,
                )
            finally:
                episode_env.close()
            if name == "no_cue":  # the decision is made on the decision cue alone
                activity.info.pop("correct_action", None)
            fig = activity_figure(activity, title=f"{env_id} · {name.replace('_', ' ')}")
            path = out / f"activity_{name}.png"
            fig.savefig(path, dpi=110)
            detail = f" (seed {episode_seed}: {note})" if note else ""
            bar.write(
                f"{name:>9}: return {activity.episode_return:.3g} over {activity.n_steps} steps{detail} -> {path}"
            )
        return 0

    return inspect
