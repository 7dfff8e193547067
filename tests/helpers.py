"""Shared test helpers (importable from the test modules: pytest puts tests/ on sys.path)."""

import numpy as np


def deterministic_success(model, env, n_episodes):
    """Success rate (``info["is_success"]``) of ``model`` over the first ``n_episodes`` episodes that end in the
    vectorised, already seeded ``env``, with deterministic actions and the recurrent state carried through."""
    obs, state, starts, successes = env.reset(), None, np.ones(env.num_envs, bool), []
    while len(successes) < n_episodes:
        actions, state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
        obs, _, starts, infos = env.step(actions)
        successes += [infos[i]["is_success"] for i in np.flatnonzero(starts)]
    return float(np.mean(successes[:n_episodes]))
