"""Deterministic evaluation: episodes with the actor's mean action, success read at the last step."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import gymnasium as gym
import jax
import numpy as np

from mcrl.algo.sac import Agent
from mcrl.config import Config
from mcrl.envs import episode_seed, flatten_obs, make_env, success_of, to_env_action
from mcrl.progress import progress as progress_bar
from mcrl.run.policy import load_policy

TRAIN_STREAM, EVAL_STREAM = 0, 1  # seed streams of training and evaluation resets
FRESH_ROUND = 10_000_019  # round index of `mcrl eval`: episodes no training evaluation used


def run_episode(env: gym.Env, act: Callable[[np.ndarray], np.ndarray], action_scale: float, seed: int,
                on_step: Callable | None = None) -> tuple[float, float | None]:
    """One episode from a seeded reset; returns (return, success at the last step or None).

    `on_step(obs, action, next_obs, reward, info)` sees every step (videos record frames with it).
    """
    obs, _ = env.reset(seed=seed)
    done, ret, info = False, 0.0, {}
    while not done:
        action = act(flatten_obs(obs))
        next_obs, r, term, trunc, info = env.step(to_env_action(action, env, action_scale))
        if on_step is not None:
            on_step(obs, action, next_obs, float(r), info)
        ret += float(r)
        done = term or trunc
        obs = next_obs
    return ret, success_of(info)


def eval_episode_seed(seed: int, round_index: int, i: int) -> int:
    """Reset seed of episode `i` of evaluation round `round_index` of a run seeded `seed` (peer systems that
    evaluate on the same start states and goals use it too)."""
    return episode_seed(seed, EVAL_STREAM, round_index * 100_003 + i)


def summarise(returns: list[float], successes: list[float | None]) -> dict:
    s = [x for x in successes if x is not None]
    return {"success_rate": float(np.mean(s)) if s else None, "mean_return": float(np.mean(returns)),
            "episodes": len(returns)}


class Evaluator:
    """Deterministic (mean-action) episodes on a separate environment, seeded per evaluation round."""

    def __init__(self, cfg: Config, agent: Agent):
        self.cfg, self.agent = cfg, agent
        self.env = make_env(cfg)
        self._act = jax.jit(agent.act_deterministic)

    def policy(self, actor_params) -> Callable[[np.ndarray], np.ndarray]:
        return lambda flat: np.asarray(self._act(actor_params, flat[None]))[0]

    def run(self, actor_params, round_index: int, episodes: int, bar=None) -> dict:
        """`episodes` deterministic episodes of evaluation round `round_index`; `bar` (`mcrl.progress`) counts them."""
        act = self.policy(actor_params)
        results = []
        for i in range(episodes):
            results.append(run_episode(self.env, act, self.cfg.action_scale,
                                       eval_episode_seed(self.cfg.seed, round_index, i)))
            if bar is not None:
                bar.update(1)
        return summarise([r for r, _ in results], [s for _, s in results])

    def close(self):
        self.env.close()


def evaluate_run(run_dir: Path | str, episodes: int | None = None, checkpoint: int | None = None,
                 progress: bool = False) -> dict:
    """Re-evaluate a saved policy: {"success_rate", "mean_return", "episodes"}; `progress`: count the episodes on
    stderr."""
    cfg, agent, state = load_policy(run_dir, checkpoint)
    ev = Evaluator(cfg, agent)
    n = episodes or cfg.eval_episodes
    bar = progress_bar(n, "evaluating", unit="episode", enabled=progress)
    try:
        return ev.run(state.pi.params, FRESH_ROUND, n, bar)
    finally:
        if bar is not None:
            bar.close()
        ev.close()
