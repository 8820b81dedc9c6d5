"""Headless OpenGL for MuJoCo: pick a working ``MUJOCO_GL`` backend, make render envs, and say what is missing.

On Linux without a display MuJoCo needs EGL or OSMesa. :func:`configure_headless_gl` probes egl, then
osmesa, each in a short subprocess (a failed attempt would pin PyOpenGL's platform in this process), and
exports the first that works. :func:`check_renderer` renders one frame and turns every failure into one
:class:`~mcrl.errors.MCRLError` line that names the Debian packages to install (:data:`APT_PACKAGES`) or says
that the environment itself cannot render. :func:`make_render_env` is ``gym.make(..., render_mode="rgb_array")``
after that.

Nothing here imports mujoco at module level, so importing this module never touches OpenGL.
"""
from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from typing import Any, NamedTuple, Sequence

import numpy as np

from mcrl.envs import register_envs, remove_maze_xml
from mcrl.errors import MCRLError, one_line

__all__ = ["APT_PACKAGES", "RenderCheck", "check_renderer", "configure_headless_gl", "make_render_env"]

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
        return MCRLError(f"{what} ({one_line(exc)}), although the GL backend "
                         f"MUJOCO_GL={backend} works: the environment cannot render rgb_array frames")
    return MCRLError(f"{what} with MUJOCO_GL={backend} ({one_line(exc)}): {_backend_hint(backend)}")


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
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    remove_maze_xml(env)
    return env


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
        raise MCRLError(f"cannot create environment {env_id!r} ({one_line(exc)}): "
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
