"""Videos of a saved policy with the MC timeline beneath the scene (`mcrl render`, `--video-every`).

Each frame shows the scene and, under it, the episode's per-step raw KL, normalised MC reward,
extrinsic reward and success, with a cursor at the current step. The KL is computed by the MC module
(`mcrl.mc`) from the recorded (s, a, s') of the very episode shown, with the run's own MC models, and
normalised with the run's own normaliser history, exactly as the agent's reward would have been.
"""
from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mcrl import normaliser
from mcrl.config import Config
from mcrl.envs import episode_seed, flatten_obs, to_env_action
from mcrl.errors import MCRLError
from mcrl.mc import transition_kl
from mcrl.sac import Agent, TrainState

_RENDER_STREAM = 2


def mc_timeline(cfg: Config, agent: Agent, state: TrainState, flat_obs: np.ndarray, actions: np.ndarray):
    """Per-step raw KL and normalised MC reward of a trajectory: flat_obs (T+1, obs_dim), actions (T, act_dim)."""
    if state.mc is None:
        return None, None
    s = jnp.asarray(flat_obs[:-1, : agent.mc_dim])  # the KL needs the predictions only, not the observed s'
    kl = transition_kl(agent.mc_models.forward(state.mc, s, jnp.asarray(actions)))
    lo, hi = normaliser.bounds(state.norm, cfg.min_percentile, cfg.max_percentile)
    r_mc = normaliser.scale(kl, lo, hi, cfg.mc_reward_low, cfg.mc_reward_high)
    return np.asarray(kl, np.float64), np.asarray(r_mc, np.float64)


def record_episode(cfg: Config, agent: Agent, state: TrainState, env, seed: int, act=None) -> dict:
    """One deterministic episode, rendered, with its timeline series (`act`: a jitted deterministic policy)."""
    from mcrl.video import render_episode

    act = act or jax.jit(agent.act_deterministic)
    policy_actions: list[np.ndarray] = []

    def policy(obs):
        a = np.asarray(act(state.actor, flatten_obs(obs)[None]))[0]
        policy_actions.append(a)
        return to_env_action(a, env, cfg.action_scale)

    ep = render_episode(env, policy, seed)
    obs = ep["observations"]
    n = ep["length"] + 1
    flat = np.stack([flatten_obs({k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i])
                     for i in range(n)])
    kl, r_mc = mc_timeline(cfg, agent, state, flat, np.stack(policy_actions))
    series = {}
    if kl is not None:
        series["raw KL (nats)"] = kl
        series["MC reward (normalised)"] = r_mc
    series["extrinsic reward"] = ep["rewards"]
    ep["series"] = series
    ep["flat_obs"], ep["policy_actions"] = flat, np.stack(policy_actions)
    return ep


def render_policy(cfg: Config, agent: Agent, state: TrainState, out_path: Path, episodes: int = 1,
                  fmt: str = "mp4", fps: float = 25.0, seed_offset: int = 0, width: int | None = None,
                  height: int | None = None) -> tuple[Path, list[dict], list[np.ndarray]]:
    """Render `episodes` deterministic episodes into one video; returns its path, the episodes, the frames."""
    from mcrl.video import check_renderer, compose_episode, make_render_env, write_video

    check_renderer(cfg.env_id, **cfg.env_kwargs)
    env = make_render_env(cfg.env_id, width=width, height=height, **cfg.env_kwargs)
    frames, eps = [], []
    act = jax.jit(agent.act_deterministic)  # compiled once for all episodes
    try:
        for i in range(episodes):
            ep = record_episode(cfg, agent, state, env, episode_seed(cfg.seed, _RENDER_STREAM, seed_offset + i), act)
            frames.extend(compose_episode(ep["frames"], ep["series"], ep["success"] if ep["has_success"] else None))
            eps.append(ep)
    finally:
        env.close()
    return write_video(frames, out_path, fmt=fmt, fps=fps), eps, frames


def render_run(run_dir: Path | str, episodes: int = 1, fmt: str = "mp4", checkpoint_step: int | None = None,
               out: Path | str | None = None, fps: float = 25.0) -> Path:
    from mcrl.trainer import load_policy

    if episodes < 1:
        raise MCRLError(f"--episodes {episodes}: render at least one episode")
    if fmt not in ("mp4", "gif"):
        raise MCRLError(f"--format {fmt}: choose mp4 or gif")
    cfg, agent, state = load_policy(run_dir, checkpoint_step)
    step = int(_checkpoint_step(run_dir, checkpoint_step))
    out = Path(out) if out else Path(run_dir) / "videos" / f"policy_step{step}.{fmt}"
    out.parent.mkdir(parents=True, exist_ok=True)
    path, _, _ = render_policy(cfg, agent, state, out, episodes=episodes, fmt=fmt, fps=fps)
    return path


def _checkpoint_step(run_dir, step):
    from mcrl import checkpoint

    return checkpoint.load_meta(checkpoint.find(Path(run_dir), step))["step"]


def record_training_video(cfg: Config, agent: Agent, state: TrainState, run_dir: Path, step: int, log) -> Path:
    """Called at evaluation time with `video_every`: keep the video in the run and send it to TensorBoard."""
    out = Path(run_dir) / "videos" / f"eval_step{step}.mp4"
    out.parent.mkdir(parents=True, exist_ok=True)
    path, _, frames = render_policy(cfg, agent, state, out, episodes=1, fmt="mp4", seed_offset=step)
    log.log_video("eval/video", frames, step)
    return path
