"""Episode videos: headless MuJoCo rendering, a per-step timeline panel, mp4/gif writing.

Typical use (what ``mcrl render RUN_DIR`` does)::

    from mcrl import video
    video.configure_headless_gl()          # before the first env.render(); best before `import mujoco`
    env = video.make_render_env("FetchReach-v4")
    ep = video.render_episode(env, policy_fn, seed=0)
    # ... compute per-step KL / MC reward from ep["observations"], ep["actions"] ...
    series = {"KL (raw)": kl, "MC reward (normalised)": r_mc, "extrinsic reward": ep["rewards"]}
    frames = video.compose_episode(ep["frames"], series, ep["success"])
    video.write_video(frames, run_dir / "videos" / "episode.mp4", "mp4", fps=25)

Step alignment: ``ep["frames"][i]`` is the scene *after* action ``i``; it sits beside
``ep["rewards"][i]``, ``ep["success"][i]`` and the transition
``(observations[i], actions[i], observations[i + 1])``, so every per-step array, and the video,
has ``ep["length"]`` entries. The reset frame is kept as ``ep["initial_frame"]``.

Heavy imports (mujoco, gymnasium, matplotlib, PIL, imageio) happen inside the functions, so
importing this module never touches OpenGL.
"""
from __future__ import annotations

import collections
import hashlib
import os
import platform
import re
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from mcrl.envs import register_envs, success_of
from mcrl.errors import MCRLError

__all__ = [
    "APT_PACKAGES",
    "RenderCheck",
    "Timeline",
    "check_renderer",
    "compose_episode",
    "compose_frame",
    "configure_headless_gl",
    "format_value",
    "make_render_env",
    "render_episode",
    "timeline_values_at",
    "write_video",
]

# Debian packages that make each headless backend work (MUJOCO_GL value -> packages).
APT_PACKAGES: dict[str, tuple[str, ...]] = {
    "egl": ("libegl1", "libgl1-mesa-dri"),
    "osmesa": ("libosmesa6",),
}
_HEADLESS_ORDER = ("egl", "osmesa")
_VALID_MUJOCO_GL = ("egl", "osmesa", "glfw", "glx")
_INSTALL_HINT = (
    "install the Debian packages libegl1 libgl1-mesa-dri (MUJOCO_GL=egl) "
    "or libosmesa6 (MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa)"
)

# --------------------------------------------------------------------------------------------
# Headless OpenGL
# --------------------------------------------------------------------------------------------

_PROBE_SCRIPT = """
import mujoco
from mujoco.{backend} import GLContext
ctx = GLContext(16, 16)
ctx.make_current()
model = mujoco.MjModel.from_xml_string("<mujoco/>")
con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
con.free()
ctx.free()
print("MCRL_GL_OK")
"""

_configured: str | None = None  # the backend configure_headless_gl() settled on
_none_works = False  # probed every candidate and none worked
_probe_failures: dict[str, str] = {}


def _probe_backend(backend: str, timeout: float = 60.0) -> str | None:
    """Try `backend` in a fresh interpreter; return None when it works, else a short reason.

    A subprocess, because a failed attempt pins PyOpenGL's platform in this process.
    """
    env = dict(os.environ, MUJOCO_GL=backend)
    env.pop("PYOPENGL_PLATFORM", None)
    if backend in APT_PACKAGES:  # PyOpenGL's platform must match egl/osmesa
        env["PYOPENGL_PLATFORM"] = backend
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_SCRIPT.format(backend=backend)],
            env=env, capture_output=True, text=True, timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout:.0f} s"
    if proc.returncode == 0 and "MCRL_GL_OK" in proc.stdout:
        return None
    return _exception_line(proc.stderr) or f"exit status {proc.returncode}"


_EXC_LINE = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception|Exit)\b:?.*$")


def _exception_line(stderr: str) -> str:
    """The first ``SomeError: message`` line of a traceback (the real failure comes before
    the at-exit noise some GL contexts print from ``__del__``), shortened."""
    for ln in stderr.splitlines():
        ln = ln.strip()
        if _EXC_LINE.match(ln):
            return ln[:120]
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    return lines[-1][:120] if lines else ""


def configure_headless_gl(*, candidates: Sequence[str] = _HEADLESS_ORDER) -> str | None:
    """Pick the OpenGL backend MuJoCo renders with; return its name (None: leave the default).

    - ``MUJOCO_GL`` already set: respected (``PYOPENGL_PLATFORM`` is set to match for
      egl/osmesa); an invalid value raises :class:`MCRLError` (``import mujoco`` would crash).
    - unset, on Linux: each of `candidates` (egl, then osmesa) is tried in a short subprocess
      (~0.3 s) and the first that creates a MuJoCo GL context is exported as ``MUJOCO_GL`` and
      ``PYOPENGL_PLATFORM`` (child processes inherit it). None when none works;
      :func:`check_renderer` then raises with the packages to install.
    - unset, on macOS/Windows: None (MuJoCo's default works there).

    Call it before the first ``env.render()``; before ``import mujoco`` if you also use
    ``mujoco.Renderer`` (mujoco reads ``MUJOCO_GL`` at import). Idempotent and cached.
    """
    global _configured, _none_works
    current = os.environ.get("MUJOCO_GL", "").strip().lower()
    if current:
        if current not in _VALID_MUJOCO_GL:
            raise MCRLError(
                f"MUJOCO_GL={current!r} is not a rendering backend: unset it (mcrl then picks one) "
                f"or set MUJOCO_GL=egl or osmesa; {_INSTALL_HINT}"
            )
        if current in APT_PACKAGES:
            os.environ.setdefault("PYOPENGL_PLATFORM", current)
        _configured = current
        return current
    if platform.system() != "Linux":
        return None
    if _configured is not None:  # we chose before and someone unset it: restore
        os.environ["MUJOCO_GL"] = _configured
        return _configured
    if _none_works:
        return None
    pinned = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    order = [b for b in candidates if not pinned or b == pinned]
    for backend in order:
        reason = _probe_backend(backend)
        if reason is None:
            os.environ["MUJOCO_GL"] = backend
            os.environ["PYOPENGL_PLATFORM"] = backend
            _configured = backend
            return backend
        _probe_failures[backend] = reason
    _none_works = True
    return None


class RenderCheck(NamedTuple):
    backend: str
    shape: tuple[int, int, int]


def _backend_hint(backend: str) -> str:
    if backend in APT_PACKAGES:
        pk = " ".join(APT_PACKAGES[backend])
        other = "osmesa" if backend == "egl" else "egl"
        return (f"install the Debian package{'s' if len(APT_PACKAGES[backend]) > 1 else ''} {pk} "
                f"(or unset MUJOCO_GL, or use MUJOCO_GL={other} with "
                f"{' '.join(APT_PACKAGES[other])})")
    return "it needs an X display; on a headless machine unset MUJOCO_GL (mcrl picks egl/osmesa) or " + _INSTALL_HINT


def _render_failure(env_id: str, backend: str, what: str, exc: BaseException) -> MCRLError:
    """Tell a broken GL backend (-> packages to install) from an env that cannot render."""
    if backend in _VALID_MUJOCO_GL and _probe_backend(backend) is None:
        return MCRLError(f"{what} ({_one_line(exc)}), although the GL backend "
                         f"MUJOCO_GL={backend} works: the environment cannot render rgb_array frames")
    return MCRLError(f"{what} with MUJOCO_GL={backend} ({_one_line(exc)}): {_backend_hint(backend)}")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"[:130]


def make_render_env(env_id: str, *, width: int | None = None, height: int | None = None, **kwargs: Any):
    """``gym.make(env_id, render_mode="rgb_array", ...)`` after configuring headless GL.

    `width`/`height` are passed only when given (Fetch and the mujoco envs default to 480x480).
    """
    configure_headless_gl()
    import gymnasium as gym

    register_envs()
    if width is not None:
        kwargs["width"] = int(width)
    if height is not None:
        kwargs["height"] = int(height)
    return gym.make(env_id, render_mode="rgb_array", **kwargs)


def check_renderer(env_id: str, **make_kwargs: Any) -> RenderCheck:
    """Render one frame of `env_id` headlessly; raise :class:`MCRLError` (one line) if impossible.

    Returns the backend used and the frame shape. The message names the Debian package(s) to
    install when no GL backend works, or says that the environment cannot render.
    """
    backend = configure_headless_gl()
    if backend is None:
        if platform.system() == "Linux":
            tried = "; ".join(f"{b}: {r}" for b, r in _probe_failures.items())
            raise MCRLError(
                f"no headless OpenGL backend works for rendering ({tried}): {_INSTALL_HINT}"
            )
        backend = "default"
    try:
        import gymnasium as gym  # noqa: F401

        register_envs()
    except Exception as exc:  # e.g. `import mujoco` failing with MUJOCO_GL=osmesa, no libOSMesa
        raise _render_failure(env_id, backend, "cannot import the environments", exc) from exc
    try:
        env = make_render_env(env_id, **make_kwargs)
    except MCRLError:
        raise
    except Exception as exc:
        raise MCRLError(f"cannot create environment {env_id!r} ({_one_line(exc)}): "
                        "check the environment id and that gymnasium-robotics is installed") from exc
    try:
        env.reset(seed=0)
        try:
            frame = env.render()
        except Exception as exc:
            raise _render_failure(env_id, backend, f"environment {env_id!r} cannot render", exc) from exc
    finally:
        try:
            env.close()
        except Exception:
            pass
    if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[-1] != 3:
        raise MCRLError(f"environment {env_id!r} cannot render rgb_array frames "
                        f"(render() returned {type(frame).__name__}): it has no visual rendering")
    if frame.size == 0 or float(frame.std()) == 0.0:
        raise MCRLError(f"environment {env_id!r} renders blank frames with MUJOCO_GL={backend}: "
                        f"{_backend_hint(backend)}")
    return RenderCheck(backend, tuple(int(s) for s in frame.shape))


# --------------------------------------------------------------------------------------------
# Running an episode
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Timeline panel
# --------------------------------------------------------------------------------------------


def format_value(value: float) -> str:
    """How a value is written in the timeline's value column."""
    if not np.isfinite(value):
        return "nan" if np.isnan(value) else ("inf" if value > 0 else "-inf")
    return f"{value:.4g}"


def timeline_values_at(
    series: Mapping[str, Any], t: int, success: Any | None = None
) -> dict[str, float]:
    """The numbers annotated in the timeline at step `t`: ``{name: series[name][t]}``
    (in the series' order) plus ``"success"`` when `success` is given."""
    out = {str(name): float(np.asarray(values, dtype=np.float64)[t]) for name, values in series.items()}
    if success is not None:
        out["success"] = float(np.asarray(success, dtype=np.float64)[t])
    return out


_ROW_COLOURS = ("#1f77b4", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


class Timeline:
    """A static per-episode timeline (drawn once, with matplotlib Agg) plus a cheap per-frame
    overlay: a red cursor at step t, a red dot on each curve and the values at t.

    One row per series, each on its own y axis scaled to its own range (min/max as ticks),
    then a success band, then the step axis. ``frame(scene, t)`` stacks the scene over it.
    """

    def __init__(
        self,
        series: Mapping[str, Any],
        success: Any | None,
        width: int,
        *,
        row_height: int = 46,
        success_height: int = 20,
        axis_height: int = 24,
        left: int = 46,
        value_width: int = 84,
        dpi: int = 100,
    ):
        if not series:
            raise ValueError("series must hold at least one per-step array")
        self.names = [str(k) for k in series]
        self.values = [np.asarray(v, dtype=np.float64).reshape(-1) for v in series.values()]
        T = len(self.values[0])
        if T == 0 or any(len(v) != T for v in self.values):
            raise ValueError(f"all series need the same non-zero length; got "
                             f"{ {n: len(v) for n, v in zip(self.names, self.values)} }")
        self.success = None if success is None else np.asarray(success, dtype=np.float64).reshape(-1)
        if self.success is not None and len(self.success) != T:
            raise ValueError(f"success has {len(self.success)} steps, the series {T}")
        self.T = T
        self.width = int(width)
        top = 7
        rows_h = row_height * len(self.names) + (success_height if self.success is not None else 0)
        height = top + rows_h + axis_height
        height += height % 2  # even, for yuv420p video
        self.height = height
        self._draw_static(top, row_height, success_height, left, value_width, dpi)

    # -- static part ------------------------------------------------------------------------
    def _draw_static(self, top, row_height, success_height, left, value_width, dpi):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        W, H, T = self.width, self.height, self.T
        plot_w = max(W - left - value_width, 40)
        fig = Figure(figsize=(W / dpi, H / dpi), dpi=dpi, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        steps = np.arange(T)
        axes = []
        y = top
        heights = [row_height] * len(self.names) + ([success_height] if self.success is not None else [])
        for i, h in enumerate(heights):
            rect = (left / W, 1 - (y + h - 3) / H, plot_w / W, (h - 3) / H)
            ax = fig.add_axes(rect)
            ax.set_xlim(-0.5, T - 0.5)
            ax.tick_params(labelsize=6, length=2, pad=1)
            for side in ("top", "right"):
                ax.spines[side].set_visible(False)
            last = i == len(heights) - 1
            if not last:
                ax.set_xticks([])
            else:
                ax.tick_params(axis="x", labelsize=6)
            if i < len(self.names):
                v = self.values[i]
                lo, hi = _finite_range(v)
                pad = 0.08 * (hi - lo)
                ax.set_ylim(lo - pad, hi + pad)
                ax.set_yticks([lo, hi])
                ax.set_yticklabels([f"{lo:.3g}", f"{hi:.3g}"])
                ax.plot(steps, v, color=_ROW_COLOURS[i % len(_ROW_COLOURS)], lw=1.0,
                        drawstyle="steps-mid" if T > 1 else "default",
                        marker="o" if T == 1 else None, ms=2)
                ax.text(0.005, 0.97, self.names[i], transform=ax.transAxes, va="top", ha="left",
                        fontsize=6.5, bbox=dict(facecolor="white", edgecolor="none", alpha=0.75, pad=0.5))
            else:
                s = self.success > 0.5
                ax.set_ylim(0, 1)
                ax.set_yticks([])
                ax.fill_between(steps, 0, 1, where=s, step="mid", color="#2ca02c", alpha=0.85, lw=0)
                ax.set_ylabel("success", fontsize=6, rotation=0, ha="right", va="center", labelpad=2)
            axes.append(ax)
            y += h
        axes[-1].set_xlabel("step", fontsize=6, labelpad=0)
        canvas.draw()
        panel = np.asarray(canvas.buffer_rgba())[..., :3]
        if panel.shape[:2] != (H, W):  # figure size rounding: crop/pad to exact size
            fixed = np.full((H, W, 3), 255, np.uint8)
            h, w = min(H, panel.shape[0]), min(W, panel.shape[1])
            fixed[:h, :w] = panel[:h, :w]
            panel = fixed
        self.panel = np.ascontiguousarray(panel, dtype=np.uint8)

        # pixel geometry for the overlay (display coords have y upwards)
        x_disp = axes[0].transData.transform(np.column_stack([steps, np.zeros(T)]))[:, 0]
        self._cursor_x = np.clip(np.round(x_disp).astype(int), 0, W - 1)
        bb_top = axes[0].get_window_extent()
        bb_bot = axes[-1].get_window_extent()
        self._cursor_y0 = int(np.clip(H - bb_top.y1, 0, H - 1))
        self._cursor_y1 = int(np.clip(H - bb_bot.y0, 1, H))
        self._dot_y = []
        self._value_pos = []
        for i, ax in enumerate(axes):
            bb = ax.get_window_extent()
            yc = int(round(H - (bb.y0 + bb.y1) / 2))
            self._value_pos.append((int(left + plot_w + 6), yc))
            if i < len(self.names):
                pts = ax.transData.transform(np.column_stack([steps, self.values[i]]))[:, 1]
                yy = np.where(np.isfinite(pts), H - pts, -1)
                self._dot_y.append(np.round(yy).astype(int))
        from PIL import ImageFont

        try:
            self._font = ImageFont.load_default(size=11)
        except TypeError:  # very old Pillow
            self._font = ImageFont.load_default()

    # -- per-frame part ---------------------------------------------------------------------
    def cursor_x(self, t: int) -> int:
        """Pixel column of the cursor for step `t` (in panel coordinates)."""
        return int(self._cursor_x[self._check_t(t)])

    def _check_t(self, t: int) -> int:
        t = int(t)
        if not 0 <= t < self.T:
            raise ValueError(f"step {t} outside the timeline's 0..{self.T - 1}")
        return t

    def annotations(self, t: int) -> list[tuple[str, float, str]]:
        """``(name, value, text)`` for each value drawn at step `t` (series rows, then success)."""
        t = self._check_t(t)
        vals = timeline_values_at(dict(zip(self.names, self.values)), t)
        out = [(n, v, format_value(v)) for n, v in vals.items()]
        if self.success is not None:
            s = float(self.success[t])
            out.append(("success", s, "yes" if s > 0.5 else "no"))
        return out

    def panel_at(self, t: int) -> np.ndarray:
        """The panel for step `t`: static timeline + cursor + dots + values."""
        from PIL import Image, ImageDraw

        t = self._check_t(t)
        panel = self.panel.copy()
        x = int(self._cursor_x[t])
        panel[self._cursor_y0:self._cursor_y1, max(x - 1, 0):x + 1] = (220, 30, 30)
        H, W = panel.shape[:2]
        for dy in self._dot_y:
            yv = int(dy[t])
            if 0 <= yv < H:
                panel[max(yv - 2, 0):yv + 3, max(x - 2, 0):x + 3] = (220, 30, 30)
        img = Image.fromarray(panel)
        draw = ImageDraw.Draw(img)
        for (_name, _v, text), (vx, vy) in zip(self.annotations(t), self._value_pos):
            draw.text((vx, vy), text, fill=(0, 0, 0), font=self._font, anchor="lm")
        step_text = f"t={t}/{self.T - 1}"
        draw.text((self._value_pos[-1][0], H - 3), step_text, fill=(90, 90, 90), font=self._font,
                  anchor="ld")
        return np.asarray(img)

    def frame(self, scene: np.ndarray, t: int) -> np.ndarray:
        """`scene` (H, W, 3) uint8 with the panel for step `t` beneath it."""
        scene = np.asarray(scene)
        if scene.ndim != 3 or scene.shape[1] != self.width:
            raise ValueError(f"scene must be (H, {self.width}, 3); got {scene.shape}")
        panel = self.panel_at(t)
        out = np.empty((scene.shape[0] + panel.shape[0], self.width, 3), np.uint8)
        out[: scene.shape[0]] = scene[..., :3]
        out[scene.shape[0]:] = panel
        return out


def _finite_range(v: np.ndarray) -> tuple[float, float]:
    f = v[np.isfinite(v)]
    if f.size == 0:
        return -1.0, 1.0
    lo, hi = float(f.min()), float(f.max())
    if hi - lo < 1e-12 * max(1.0, abs(lo), abs(hi)):
        d = max(abs(lo) * 0.1, 0.5)
        return lo - d, hi + d
    return lo, hi


_TIMELINES: "collections.OrderedDict[bytes, Timeline]" = collections.OrderedDict()


def _timeline_key(series: Mapping[str, Any], success: Any | None, width: int) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    h.update(str(width).encode())
    for name, values in series.items():
        h.update(b"\0" + str(name).encode() + b"\0")
        h.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    if success is not None:
        h.update(b"\0success\0" + np.ascontiguousarray(success, dtype=np.float64).tobytes())
    return h.digest()


def _get_timeline(series, success, width) -> Timeline:
    key = _timeline_key(series, success, width)
    tl = _TIMELINES.get(key)
    if tl is None:
        tl = Timeline(series, success, width)
        _TIMELINES[key] = tl
        while len(_TIMELINES) > 4:
            _TIMELINES.popitem(last=False)
    else:
        _TIMELINES.move_to_end(key)
    return tl


def compose_frame(
    scene: np.ndarray,
    series: Mapping[str, Any],
    t: int,
    success: Any | None = None,
    *,
    timeline: Timeline | None = None,
) -> np.ndarray:
    """`scene` (H, W, 3) uint8 with a timeline of `series` (name -> (T,) array, one row each)
    and `success` (T,) beneath it, cursor and values at step `t`. Returns (H + h, W, 3) uint8.

    The static timeline is drawn once per (series, success, width) and cached (the last 4), so
    calling this for every frame of an episode costs only the overlay; pass `timeline` to skip
    even the cache lookup.
    """
    scene = np.asarray(scene)
    if timeline is None:
        timeline = _get_timeline(series, success, scene.shape[1])
    return timeline.frame(scene, t)


def compose_episode(
    frames: Sequence[np.ndarray], series: Mapping[str, Any], success: Any | None = None
) -> list[np.ndarray]:
    """:func:`compose_frame` for every frame; frame i shows step i (len(frames) == T)."""
    if not frames:
        return []
    timeline = Timeline(series, success, np.asarray(frames[0]).shape[1])
    if len(frames) != timeline.T:
        raise ValueError(f"{len(frames)} frames but the series have {timeline.T} steps")
    return [timeline.frame(f, i) for i, f in enumerate(frames)]


# --------------------------------------------------------------------------------------------
# Writing videos
# --------------------------------------------------------------------------------------------


def _pad_even(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _write_mp4(frames, path: Path, fps: float) -> None:
    try:
        import imageio.v2 as iio2
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        raise MCRLError(
            f"writing mp4 needs ffmpeg ({_one_line(exc)}): pip install 'mcrl[video]' "
            "(imageio-ffmpeg ships one) or apt-get install ffmpeg, or write a gif instead"
        ) from exc
    writer = iio2.get_writer(
        str(path), format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
        pixelformat="yuv420p", quality=7, macro_block_size=1, ffmpeg_log_level="error",
    )
    try:
        for f in frames:
            writer.append_data(_pad_even(np.ascontiguousarray(np.asarray(f)[..., :3], np.uint8)))
    finally:
        writer.close()


def _write_gif(frames, path: Path, fps: float, max_width: int | None, colors: int) -> None:
    from PIL import Image

    imgs = []
    for f in frames:
        im = Image.fromarray(np.ascontiguousarray(np.asarray(f)[..., :3], np.uint8))
        if max_width and im.width > max_width:
            h = max(1, round(im.height * max_width / im.width))
            im = im.resize((int(max_width), int(h)), Image.Resampling.BILINEAR)
        imgs.append(im)
    # one global palette from a few frames: small file, and every frame shares it
    picks = sorted({round(i) for i in np.linspace(0, len(imgs) - 1, min(8, len(imgs)))})
    mosaic = Image.new("RGB", (imgs[0].width, imgs[0].height * len(picks)))
    for k, i in enumerate(picks):
        mosaic.paste(imgs[i].resize(imgs[0].size) if imgs[i].size != imgs[0].size else imgs[i],
                     (0, k * imgs[0].height))
    palette = mosaic.quantize(colors=int(np.clip(colors, 2, 255)), method=Image.Quantize.MEDIANCUT)
    n_colors = max(2, len(palette.getpalette() or []) // 3)
    out, prev = [], None
    for im in imgs:
        q = im.quantize(palette=palette, dither=Image.Dither.NONE)
        idx = np.asarray(q)
        if prev is not None and idx.shape == prev.shape and np.array_equal(idx, prev):
            # Pillow merges identical consecutive frames; nudge one corner pixel so the GIF
            # keeps one frame per step.
            idx = idx.copy()
            idx[-1, -1] = (int(idx[-1, -1]) + 1) % n_colors
            q = Image.fromarray(idx, mode="P")
            q.putpalette(palette.getpalette())
        prev = idx
        out.append(q)
    duration = max(int(round(1000.0 / float(fps))), 10)
    # optimize=True: unchanged pixels become the (free) transparent index -> ~5x smaller files
    out[0].save(path, format="GIF", save_all=True, append_images=out[1:], duration=duration,
                loop=0, optimize=True, disposal=1)


def write_video(
    frames: Sequence[np.ndarray],
    path: str | os.PathLike,
    fmt: str | None = None,
    fps: float = 25.0,
    *,
    gif_max_width: int | None = 320,
    gif_colors: int = 128,
) -> Path:
    """Write uint8 RGB `frames` as ``"mp4"`` (H.264 via imageio-ffmpeg) or ``"gif"`` (Pillow).

    `fmt` defaults to the path's suffix. One video frame per input frame. GIFs are downscaled
    to at most `gif_max_width` px wide (None: full size) with one shared palette of at most
    `gif_colors` (<= 255) colours, and store only what changed between frames. Odd mp4 sizes are padded by one pixel (yuv420p). Returns the path.
    """
    path = Path(path)
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt not in ("mp4", "gif"):
        raise MCRLError(f"unknown video format {fmt!r}: use mp4 or gif")
    if not frames:
        raise MCRLError(f"no frames to write to {path}: the episode rendered nothing")
    if not fps or fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "mp4":
        _write_mp4(frames, path, fps)
    else:
        _write_gif(frames, path, fps, gif_max_width, gif_colors)
    return path
