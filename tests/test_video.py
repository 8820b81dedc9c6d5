"""Episode videos: real headless rendering of FetchReach, timeline composition, mp4/gif files.

Needs a working headless GL (CI: the Debian packages in .ci/apt-packages.txt). Fast: ~15 s.
"""
from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mcrl import video
from mcrl.errors import MCRLError
from mcrl.video import timeline

ENV_ID = "FetchReach-v4"
STEPS = 12
SRC = str(Path(video.__file__).resolve().parents[2])  # src/, above the mcrl package


@pytest.fixture(scope="module")
def episode():
    check = video.check_renderer(ENV_ID)  # raises MCRLError naming the missing package
    assert check.backend in ("egl", "osmesa", "glfw", "glx", "default")
    env = video.make_render_env(ENV_ID)
    try:
        rng = np.random.default_rng(0)
        ep = video.render_episode(
            env, lambda obs: rng.uniform(-1, 1, env.action_space.shape), seed=3, max_steps=STEPS
        )
    finally:
        env.close()
    return ep


def _series(ep):
    T = ep["length"]
    kl = np.linspace(0.05, 3.0, T) ** 1.5 + 0.01 * np.arange(T) % 3
    return {
        "KL (raw)": kl,
        "MC reward (normalised)": -1.0 + (kl - kl.min()) / np.ptp(kl),
        "extrinsic reward": ep["rewards"],
    }


def test_render_episode_collects_aligned_steps(episode):
    T = episode["length"]
    assert T == STEPS
    assert len(episode["frames"]) == T
    assert episode["actions"].shape == (T, 4)
    assert episode["rewards"].shape == (T,) and episode["success"].shape == (T,)
    assert episode["has_success"]
    obs = episode["observations"]
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    assert obs["observation"].shape == (T + 1, 10)
    for f in episode["frames"] + [episode["initial_frame"]]:
        assert f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3
        assert f.std() > 10, "rendered frame is blank"
    # a random policy moves the arm: the scene changes over the episode
    assert np.abs(episode["frames"][-1].astype(int) - episode["initial_frame"].astype(int)).max() > 0


def test_render_episode_is_deterministic_for_a_seed():
    env = video.make_render_env(ENV_ID)
    try:
        runs = [video.render_episode(env, lambda o: np.full(4, 0.5), seed=7, max_steps=4, render=False)
                for _ in range(2)]
    finally:
        env.close()
    for key in ("observation", "desired_goal"):
        np.testing.assert_array_equal(runs[0]["observations"][key], runs[1]["observations"][key])
    assert runs[0]["frames"] == [] and runs[0]["length"] == 4


def test_timeline_values_drawn_equal_the_series(episode):
    series = _series(episode)
    success = episode["success"]
    scene = episode["frames"][0]
    tl = video.Timeline(series, success, scene.shape[1])
    for t in (0, 5, episode["length"] - 1):
        drawn = tl.annotations(t)
        assert [d[0] for d in drawn] == list(series) + ["success"]
        for name, value, text in drawn[:-1]:
            assert value == series[name][t]
            assert text == video.format_value(series[name][t])
        assert drawn[-1][1] == success[t]
        values = video.timeline_values_at(series, t, success)
        assert values["KL (raw)"] == series["KL (raw)"][t]
        assert values["success"] == success[t]


def test_compose_frame_keeps_scene_and_moves_cursor(episode):
    series = _series(episode)
    success = episode["success"]
    scene = episode["frames"][2]
    a = video.compose_frame(scene, series, 2, success)
    b = video.compose_frame(scene, series, 9, success)
    H, W = scene.shape[:2]
    assert a.dtype == np.uint8 and a.shape[1] == W and a.shape[0] > H and a.shape[0] % 2 == 0
    np.testing.assert_array_equal(a[:H], scene)  # scene on top, untouched
    assert not np.array_equal(a[H:], b[H:])  # the overlay follows t
    tl = timeline._get_timeline(series, success, W)  # the cached static timeline
    x2, x9 = tl.cursor_x(2), tl.cursor_x(9)
    assert x2 < x9
    col = a[H:, x2].astype(int)
    red = (col[:, 0] > 180) & (col[:, 1] < 80) & (col[:, 2] < 80)
    assert red.sum() > 0.5 * (tl._cursor_y1 - tl._cursor_y0)
    with pytest.raises(ValueError):
        video.compose_frame(scene, series, episode["length"], success)


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_written_video_has_one_nonblank_frame_per_step(episode, tmp_path, fmt):
    import imageio.v2 as iio2

    T = episode["length"]
    frames = video.compose_episode(episode["frames"], _series(episode), episode["success"])
    assert len(frames) == T
    path = video.write_video(frames, tmp_path / f"ep.{fmt}", fmt, fps=10)
    assert path == tmp_path / f"ep.{fmt}" and path.stat().st_size > 1000
    back = np.stack([np.asarray(f)[..., :3] for f in iio2.get_reader(str(path))])
    assert back.shape[0] == T
    scene_h = round(episode["frames"][0].shape[0] * back.shape[2] / frames[0].shape[1])
    for f in back:
        assert f.std() > 10, "blank video frame"
        scene = f[: scene_h - 2].astype(float)
        assert scene.std() > 10 and np.ptp(scene) > 50, "scene region is uniform"
    if fmt == "mp4":  # same size, close to the input (lossy codec)
        assert back.shape[1:] == frames[0].shape
        assert np.abs(back.astype(float) - np.stack(frames)).mean() < 6
    else:  # downscaled to at most 320 px wide
        assert back.shape[2] <= 320


def test_gif_keeps_identical_consecutive_frames(tmp_path):
    import imageio.v2 as iio2

    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (40, 60, 3), dtype=np.uint8)
    frames = [base, base, base, base.copy(), 255 - base]
    path = video.write_video(frames, tmp_path / "same.gif", fps=20)
    assert len(list(iio2.get_reader(str(path)))) == len(frames)


def test_write_video_rejects_unknown_format(tmp_path):
    with pytest.raises(MCRLError, match="mp4 or gif"):
        video.write_video([np.zeros((8, 8, 3), np.uint8)], tmp_path / "x.avi")


def _run_check(env_overrides: dict, prelude: str = "") -> subprocess.CompletedProcess:
    """check_renderer in a fresh interpreter, so this process' GL state is untouched."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env.update(env_overrides)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    code = textwrap.dedent(f"""
        import sys
        from mcrl import video
        from mcrl.errors import MCRLError
        {prelude}
        try:
            print("OK", video.check_renderer({ENV_ID!r}))
        except MCRLError as e:
            print("MCRLERROR", e)
            sys.exit(3)
    """)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=120)


def _message(proc) -> str:
    assert proc.returncode == 3, (proc.stdout, proc.stderr[-2000:])
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("MCRLERROR ")]
    assert len(lines) == 1 and "\n" not in lines[0]
    return lines[0][len("MCRLERROR "):]


def test_check_renderer_rejects_an_invalid_backend():
    msg = _message(_run_check({"MUJOCO_GL": "bogus"}))
    assert "MUJOCO_GL='bogus'" in msg and "libegl1" in msg and "libosmesa6" in msg


def test_check_renderer_names_packages_when_egl_is_unavailable():
    # glvnd finds no EGL vendor library: what a machine without libegl-mesa0 looks like
    proc = _run_check({"MUJOCO_GL": "egl", "__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent.json"})
    if proc.returncode == 0:
        pytest.skip("EGL still works without a vendor file here (non-glvnd EGL)")
    msg = _message(proc)
    assert "MUJOCO_GL=egl" in msg and "libegl1 libgl1-mesa-dri" in msg


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is not None, reason="OSMesa is installed")
def test_check_renderer_names_libosmesa6_when_osmesa_is_missing():
    msg = _message(_run_check({"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}))
    assert "MUJOCO_GL=osmesa" in msg and "libosmesa6" in msg


def test_check_renderer_when_no_backend_works():
    # MUJOCO_GL unset: mcrl probes egl then osmesa; make every probe fail
    proc = _run_check({}, prelude="video.gl._probe_backend = lambda b, timeout=60: 'unavailable (test)'")
    msg = _message(proc)
    assert "no headless OpenGL backend" in msg
    assert "libegl1 libgl1-mesa-dri" in msg and "libosmesa6" in msg


def test_configure_headless_gl_probes_a_real_backend():
    # MUJOCO_GL unset, egl pinned by PYOPENGL_PLATFORM but broken: the real probe fails
    proc = _run_check({"PYOPENGL_PLATFORM": "egl", "__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent.json"})
    if proc.returncode == 0:
        pytest.skip("EGL still works without a vendor file here (non-glvnd EGL)")
    msg = _message(proc)
    assert "no headless OpenGL backend" in msg and "egl:" in msg


def test_mp4_without_ffmpeg_is_a_clear_error(tmp_path, monkeypatch):
    import imageio_ffmpeg

    def missing():
        raise RuntimeError("No ffmpeg exe could be found.")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", missing)
    with pytest.raises(MCRLError, match="ffmpeg.*gif"):
        video.write_video([np.zeros((8, 8, 3), np.uint8)], tmp_path / "x.mp4", "mp4")


@pytest.mark.parametrize("width", [480, 320])
@pytest.mark.parametrize("series", [
    # a FetchReach video's rows: before the fix the rows' adjacent tick labels ("9.22" over "-0.136") touched
    {"raw KL (nats)": np.linspace(9.22, 10.1, 50), "MC reward (normalised)": np.linspace(-0.213, -0.136, 50),
     "extrinsic reward": -np.ones(50), "mixed reward, alpha 0.2": np.linspace(-0.84, -0.83, 50)},
    # tick labels wider than the fixed margin ran off the panel's left edge
    {"tiny": np.linspace(-0.00209, -0.000129, 50), "huge": np.linspace(-1190.0, -19.7, 50)},
])
def test_timeline_texts_keep_apart_and_inside_the_panel(series, width):
    """Tick labels, row names and axis labels: no two closer than a pixel, none beyond the panel's edges."""
    tl = video.Timeline(series, (np.arange(50) > 30).astype(float), width)
    boxes = tl.text_boxes()
    assert {"step", "success"} | set(series) <= {text for text, _ in boxes}
    for i, (a, (ax0, ay0, ax1, ay1)) in enumerate(boxes):
        assert 0 <= ax0 and ax1 <= tl.width and 0 <= ay0 and ay1 <= tl.height, (a, boxes[i][1])
        for b, (bx0, by0, bx1, by1) in boxes[i + 1:]:
            assert max(bx0 - ax1, ax0 - bx1, by0 - ay1, ay0 - by1) >= 1, (a, b)
