"""Episode videos: headless MuJoCo rendering, a per-step timeline panel, mp4/gif writing.

One module per step of making a video:

- ``gl``        pick a headless OpenGL backend (EGL, OSMesa fallback), make render envs, explain failures
- ``episode``   roll out a policy, collecting frames and per-step data (the package's only rollout)
- ``timeline``  the panel drawn beneath each frame: one row per series, success band, cursor at step t
- ``encode``    write frames as mp4 or gif (or GIF bytes for TensorBoard)
- ``render``    videos of a saved run's policy with its intrinsic reward's timeline (`mcrl render`,
  ``--video-every``); the only module that knows about runs, checkpoints and the agent, so it imports
  JAX: import it as ``mcrl.video.render``, it is not re-exported here

Typical use (what ``mcrl render RUN_DIR`` does, see ``render``)::

    from mcrl import video
    video.configure_headless_gl()          # before the first env.render(); best before `import mujoco`
    env = video.make_render_env("FetchReach-v4")
    ep = video.render_episode(env, policy_fn, seed=0)
    # ... compute the per-step raw and normalised intrinsic reward from ep["observations"], ep["actions"] ...
    series = {"raw KL (nats)": kl, "MC reward (normalised)": r_mc, "extrinsic reward": ep["rewards"]}
    frames = video.compose_episode(ep["frames"], series, ep["success"])
    video.write_video(frames, run_dir / "videos" / "episode.mp4", "mp4", fps=25)

Step alignment: ``ep["frames"][i]`` is the scene *after* action ``i`` (see ``episode``), so every per-step
array, and the video, has ``ep["length"]`` entries.

Heavy imports (mujoco, matplotlib, PIL, imageio) happen inside the functions, so importing this package
never touches OpenGL.
"""
from __future__ import annotations

from mcrl.video.encode import encode_gif, write_video
from mcrl.video.episode import render_episode
from mcrl.video.gl import APT_PACKAGES, RenderCheck, check_renderer, configure_headless_gl, make_render_env
from mcrl.video.timeline import Timeline, compose_episode, compose_frame, format_value, timeline_values_at

__all__ = [
    "APT_PACKAGES",
    "RenderCheck",
    "Timeline",
    "check_renderer",
    "compose_episode",
    "compose_frame",
    "configure_headless_gl",
    "encode_gif",
    "format_value",
    "make_render_env",
    "render_episode",
    "timeline_values_at",
    "write_video",
]
