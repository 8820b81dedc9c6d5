"""Encoding frames as a video file: H.264 mp4 (imageio-ffmpeg) or an animated GIF (Pillow).

:func:`encode_gif` returns the GIF's bytes without a file, for TensorBoard image summaries.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import IO, Sequence

import numpy as np

from mcrl.errors import MCRLError
from mcrl.errors import one_line

__all__ = ["encode_gif", "write_video"]


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
            f"writing mp4 needs ffmpeg ({one_line(exc)}): pip install imageio-ffmpeg "
            "(a dependency of mcrl; it ships one) or apt-get install ffmpeg, or write a gif instead"
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


def _write_gif(frames, path: Path | IO[bytes], fps: float, max_width: int | None, colors: int) -> None:
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
    `gif_colors` (<= 255) colours, and store only what changed between frames. Odd mp4 sizes
    are padded by one pixel (yuv420p). Returns the path.
    """
    path = Path(path)
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt not in ("mp4", "gif"):
        raise MCRLError(f"unknown video format {fmt!r}: use mp4 or gif")
    _check(frames, fps, path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "mp4":
        _write_mp4(frames, path, fps)
    else:
        _write_gif(frames, path, fps, gif_max_width, gif_colors)
    return path


def encode_gif(
    frames: Sequence[np.ndarray], fps: float = 25.0, *, max_width: int | None = 320, colors: int = 128
) -> bytes:
    """The bytes of the GIF :func:`write_video` would write for `frames` (e.g. for a TensorBoard image)."""
    _check(frames, fps, "a GIF")
    buf = io.BytesIO()
    _write_gif(frames, buf, fps, max_width, colors)
    return buf.getvalue()


def _check(frames: Sequence[np.ndarray], fps: float, target: object) -> None:
    if not len(frames):
        raise MCRLError(f"no frames to write to {target}: the episode rendered nothing")
    if not fps or fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
