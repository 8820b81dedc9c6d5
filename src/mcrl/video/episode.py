"""Rolling out one episode for a video: frames and per-step data, aligned step by step.

Step alignment: ``ep["frames"][i]`` is the scene *after* action ``i``; it sits beside
``ep["rewards"][i]``, ``ep["success"][i]`` and the transition
``(observations[i], actions[i], observations[i + 1])``, so every per-step array, and the video,
has ``ep["length"]`` entries. The reset frame is kept as ``ep["initial_frame"]``.

This is the video package's only rollout. It differs from :func:`mcrl.run.evaluation.run_episode` in
what it keeps (frames, every observation and per-step reward and success, for the timeline), and its
policy returns *environment* actions, so any callable can be filmed, not only an mcrl actor.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from mcrl.envs import success_of
from mcrl.errors import MCRLError

__all__ = ["render_episode"]


def _stack_obs(obs_list: list) -> Any:
    first = obs_list[0]
    if isinstance(first, Mapping):
        return {k: np.stack([np.asarray(o[k]) for o in obs_list]) for k in first}
    return np.stack([np.asarray(o) for o in obs_list])


def _as_rgb(frame: Any) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise MCRLError("the environment's render() did not return an RGB frame: "
                        "make it with render_mode='rgb_array' (see mcrl.video.make_render_env)")
    arr = arr[..., :3]
    if arr.dtype != np.uint8:
        arr = np.clip(arr, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(arr)


def render_episode(
    env,
    policy_fn: Callable[[Any], Any],
    seed: int,
    max_steps: int | None = None,
    *,
    render: bool = True,
) -> dict:
    """Run one episode with ``policy_fn(obs) -> action``, recording frames and per-step data.

    The env is reset with `seed` (and its action space seeded with it), so a deterministic
    policy gives the same episode every time. It stops at termination, truncation or after
    `max_steps` steps. Returns a dict:

    - ``frames``: list of T uint8 (H, W, 3) arrays, frame i rendered after action i
      (empty when ``render=False``); ``initial_frame``: the frame after reset (or None)
    - ``observations``: the T + 1 observations, stacked (dict of arrays for goal envs:
      ``{"observation": (T+1, n), "achieved_goal": ..., "desired_goal": ...}``)
    - ``actions`` (T, act_dim) float32, ``rewards`` (T,) float64 (extrinsic),
      ``success`` (T,) float64 (``info["is_success"]`` or ``info["success"]``; 0 if absent)
    - ``has_success`` bool, ``terminated`` bool, ``truncated`` bool, ``length`` T, ``seed``
    """
    if render and getattr(env, "render_mode", None) != "rgb_array":
        raise MCRLError("render_episode needs an env made with render_mode='rgb_array' "
                        "(use mcrl.video.make_render_env)")
    obs, _info = env.reset(seed=int(seed))
    try:
        env.action_space.seed(int(seed))
    except Exception:
        pass
    initial_frame = _as_rgb(env.render()) if render else None
    observations, actions, rewards, success, frames = [obs], [], [], [], []
    has_success = False
    terminated = truncated = False
    limit = None if max_steps is None else int(max_steps)
    while limit is None or len(actions) < limit:
        action = np.asarray(policy_fn(obs))
        obs, reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        actions.append(np.asarray(action, dtype=np.float32).reshape(-1))
        rewards.append(float(reward))
        s = success_of(info)
        has_success = has_success or s is not None
        success.append(0.0 if s is None else s)
        if render:
            frames.append(_as_rgb(env.render()))
        if terminated or truncated:
            break
    T = len(actions)
    return {
        "frames": frames,
        "initial_frame": initial_frame,
        "observations": _stack_obs(observations),
        "actions": np.stack(actions) if T else np.zeros((0,) + env.action_space.shape, np.float32),
        "rewards": np.asarray(rewards, dtype=np.float64),
        "success": np.asarray(success, dtype=np.float64),
        "has_success": has_success,
        "terminated": bool(terminated),
        "truncated": bool(truncated),
        "length": T,
        "seed": int(seed),
    }
