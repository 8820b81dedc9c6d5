"""Videos of a saved policy with the intrinsic reward's timeline beneath the scene (`mcrl render`,
`--video-every`).

Each frame shows the scene and, under it, the episode's per-step raw intrinsic reward (MC: the KL in nats),
the normalised intrinsic reward, the extrinsic reward, the mixed reward at the intrinsic weight in force (its row
names the weight: the run's schedule gives it, `mcrl.algo.schedule`) and success, with a cursor at the current
step; the rows are named after the reward the run used (its `About`'s `title` and `raw_label`). The raw values
are computed by the run's own intrinsic models (`IntrinsicReward.reward`) from the recorded (s, a, s') of the very
episode shown, and normalised by `mcrl.algo.normaliser.reward` with the run's own normaliser history, exactly as
the agent's reward would have been. A run without intrinsic models (plain SAC) shows the extrinsic reward alone.

This is the glue between a run (its config and checkpoint, `mcrl.run`) and the video pieces
(`gl`, `episode`, `timeline`, `encode`).
"""
from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mcrl.algo import normaliser
from mcrl.algo.schedule import Schedule
from mcrl.algo.sac import Agent, TrainState
from mcrl.config import Config
from mcrl.envs import episode_seed, flatten_obs, to_env_action
from mcrl.errors import MCRLError
from mcrl.progress import progress as progress_bar
from mcrl.run import checkpoint, rundir
from mcrl.run.policy import load_policy
from mcrl.video.encode import encode_gif, write_video
from mcrl.video.episode import render_episode
from mcrl.video.gl import check_renderer, make_render_env
from mcrl.video.timeline import compose_episode

__all__ = ["intrinsic_timeline", "record_episode", "record_training_video", "render_policy", "render_run"]

_RENDER_STREAM = 2  # seed stream of rendered episodes (training uses 0, evaluation 1)
FPS = 25.0


def intrinsic_timeline(cfg: Config, agent: Agent, state: TrainState, flat_obs: np.ndarray,
                       actions: np.ndarray) -> dict[str, np.ndarray]:
    """The timeline rows of the run's intrinsic reward along a trajectory, flat_obs (T+1, obs_dim) and actions
    (T, act_dim): {its raw label: (T,) raw values, "<title> reward (normalised)": (T,)}, or {} for a run without
    intrinsic models. The history is not updated: the reward is the one the agent would give these transitions
    now."""
    if state.intrinsic is None:
        return {}
    net, models = agent.intrinsic_net, state.intrinsic
    s = jnp.asarray(flat_obs[:-1, : agent.intrinsic_dim])
    s_next = jnp.asarray(flat_obs[1:, : agent.intrinsic_dim])
    raw = net.reward(models.params, models.untrained, s, jnp.asarray(actions), s_next)
    r_int, _ = normaliser.reward(state.norm, raw, cfg.min_percentile, cfg.max_percentile, cfg.intrinsic_reward_low,
                                 cfg.intrinsic_reward_high)
    return {agent.about.raw_label: np.asarray(raw, np.float64), _normalised(agent): np.asarray(r_int, np.float64)}


def _normalised(agent: Agent) -> str:
    return f"{agent.about.title} reward (normalised)"


def record_episode(cfg: Config, agent: Agent, state: TrainState, env, seed: int, act=None,
                   alpha: float | None = None) -> dict:
    """One deterministic episode, rendered, with its timeline series (`act`: a jitted deterministic policy; `alpha`:
    the intrinsic weight in force, None for the config's intrinsic_alpha).

    Returns :func:`mcrl.video.episode.render_episode`'s dict plus ``series`` (name -> (T,) array),
    ``flat_obs`` (T+1, obs_dim) and ``policy_actions`` (T, act_dim), the actor's actions before scaling.
    """
    act = act or jax.jit(agent.act_deterministic)
    policy_actions: list[np.ndarray] = []

    def policy(obs):
        a = np.asarray(act(state.pi.params, flatten_obs(obs)[None]))[0]
        policy_actions.append(a)
        return to_env_action(a, env, cfg.action_scale)

    ep = render_episode(env, policy, seed)
    obs = ep["observations"]
    n = ep["length"] + 1
    flat = np.stack([flatten_obs({k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i])
                     for i in range(n)])
    series = intrinsic_timeline(cfg, agent, state, flat, np.stack(policy_actions))
    series["extrinsic reward"] = ep["rewards"]
    if state.intrinsic is not None:  # the reward the agent learns from, at the weight in force (the row says which)
        a = cfg.intrinsic_alpha if alpha is None else alpha
        r_int = series[_normalised(agent)]
        series[f"mixed reward, alpha {a:.3g}"] = (1.0 - a) * ep["rewards"] + a * r_int
    ep["series"] = series
    ep["flat_obs"], ep["policy_actions"] = flat, np.stack(policy_actions)
    return ep


def render_policy(cfg: Config, agent: Agent, state: TrainState, out_path: Path, episodes: int = 1,
                  fmt: str = "mp4", fps: float = FPS, seed_offset: int = 0, width: int | None = None,
                  height: int | None = None, bar=None,
                  alpha: float | None = None) -> tuple[Path, list[dict], list[np.ndarray]]:
    """Render `episodes` deterministic episodes into one video; returns its path, the episodes, the frames.
    `bar` (`mcrl.progress`) counts the episodes; `alpha` is the intrinsic weight in force (None: intrinsic_alpha)."""
    check_renderer(cfg.env_id, **cfg.env_kwargs)
    env = make_render_env(cfg.env_id, width=width, height=height, **cfg.env_kwargs)
    frames, eps = [], []
    act = jax.jit(agent.act_deterministic)  # compiled once for all episodes
    try:
        for i in range(episodes):
            ep = record_episode(cfg, agent, state, env, episode_seed(cfg.seed, _RENDER_STREAM, seed_offset + i), act,
                                alpha)
            frames.extend(compose_episode(ep["frames"], ep["series"], ep["success"] if ep["has_success"] else None))
            eps.append(ep)
            if bar is not None:
                bar.update(1)
    finally:
        env.close()
    return write_video(frames, out_path, fmt=fmt, fps=fps), eps, frames


def render_run(run_dir: Path | str, episodes: int = 1, fmt: str = "mp4", checkpoint_step: int | None = None,
               out: Path | str | None = None, fps: float = FPS, progress: bool = False) -> Path:
    """`mcrl render`: video of a saved run's policy (default RUN_DIR/videos/policy_step<STEP>.<fmt>); `progress`:
    count the rendered episodes on stderr."""
    if episodes < 1:
        raise MCRLError(f"--episodes {episodes}: render at least one episode")
    if fmt not in ("mp4", "gif"):
        raise MCRLError(f"--format {fmt}: choose mp4 or gif")
    cfg, agent, state = load_policy(run_dir, checkpoint_step)
    meta = checkpoint.load_meta(checkpoint.find(Path(run_dir), checkpoint_step))
    step = int(meta["step"])
    # the weight the schedule gives at the checkpoint's step, from the success window the checkpoint holds
    alpha = Schedule.of(cfg).value(step, meta.get("success_window", []))
    out = Path(out) if out else rundir.video_path(run_dir, "policy", step, fmt)
    bar = progress_bar(episodes, "rendering", unit="episode", enabled=progress)
    try:
        path, _, _ = render_policy(cfg, agent, state, out, episodes=episodes, fmt=fmt, fps=fps, bar=bar, alpha=alpha)
    finally:
        if bar is not None:
            bar.close()
    return path


def record_training_video(cfg: Config, agent: Agent, state: TrainState, run_dir: Path, step: int, log,
                          alpha: float | None = None) -> Path:
    """The training loop's video step (`mcrl.run.trainer.train(..., video=record_training_video)`), called at an
    evaluation that `video_every` selects: keep the video in the run and send it to TensorBoard.

    `log` is the run's `mcrl.run.logger.RunLogger`; TensorBoard gets the episode as an animated GIF. `alpha` is the
    intrinsic weight of this step's gradient step, which the timeline's mixed-reward row shows.
    """
    out = rundir.video_path(run_dir, "eval", step, "mp4")
    path, _, frames = render_policy(cfg, agent, state, out, episodes=1, fmt="mp4", seed_offset=step, alpha=alpha)
    log.log_gif("eval/video", encode_gif(frames, fps=FPS), step)
    return path
