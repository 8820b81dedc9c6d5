"""The timeline panel drawn beneath each video frame: one row per per-step series, a success band, a cursor.

The static part (curves, axes, labels) is drawn once per episode with matplotlib's Agg backend; each frame
then only costs a cheap overlay with PIL (red cursor at step t, a red dot on each curve, the values at t).
:func:`compose_frame` / :func:`compose_episode` stack a scene over its panel.
"""
from __future__ import annotations

import collections
import hashlib
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["Timeline", "compose_episode", "compose_frame", "format_value", "timeline_values_at"]


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
    No two of its texts overlap (`text_boxes`): the left margin widens to the widest tick label, and each row's
    tick labels stay inside its own band.
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
        fig = Figure(figsize=(W / dpi, H / dpi), dpi=dpi, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        ranges = [_finite_range(v) for v in self.values]
        tick_texts = [f"{x:.3g}" for r in ranges for x in r] + (["success"] if self.success is not None else [])
        # a fixed margin cut long tick labels ("-0.00212") at the panel's edge: make room for the widest
        left = max(left, int(np.ceil(_widest(canvas, tick_texts, dpi))) + 8)
        plot_w = max(W - left - value_width, 40)
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
                lo, hi = ranges[i]
                pad = 0.08 * (hi - lo)
                ax.set_ylim(lo - pad, hi + pad)
                ax.set_yticks([lo, hi])
                # centred on their ticks, a row's bottom label met the next row's top label: keep both inside
                for label, va in zip(ax.set_yticklabels([f"{lo:.3g}", f"{hi:.3g}"]), ("bottom", "top")):
                    label.set_va(va)
                ax.plot(steps, v, color=_ROW_COLOURS[i % len(_ROW_COLOURS)], lw=1.0,
                        drawstyle="steps-mid" if T > 1 else "default",
                        marker="o" if T == 1 else None, ms=2)
                # a few pixels in from the axis: at its edge the name ran into the top tick label beside it
                ax.annotate(self.names[i], (0, 1), xycoords="axes fraction", xytext=(5, -2),
                            textcoords="offset pixels", va="top", ha="left", fontsize=6.5,
                            bbox=dict(facecolor="white", edgecolor="none", alpha=0.75, pad=0.5))
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
        self._text_boxes = _text_boxes(fig, canvas, H)
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

    def text_boxes(self) -> list[tuple[str, tuple[float, float, float, float]]]:
        """Each text of the static panel and its box (x0, y0, x1, y1) in panel pixels, y downwards."""
        return list(self._text_boxes)

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


def _widest(canvas, texts: list[str], dpi: int, size: float = 6) -> float:
    """The width in pixels of the widest of `texts` at font size `size` (the tick labels')."""
    from matplotlib.font_manager import FontProperties

    renderer, font = canvas.get_renderer(), FontProperties(size=size)
    return max((renderer.get_text_width_height_descent(t, font, ismath=False)[0] for t in texts), default=0.0)


def _text_boxes(fig, canvas, H: int) -> list[tuple[str, tuple[float, float, float, float]]]:
    """Every visible text of the drawn figure (tick labels, axis labels, row names) and its box (x0, y0, x1, y1)
    in panel pixels, y downwards."""
    renderer, out = canvas.get_renderer(), []
    for ax in fig.axes:
        ticks = [t.label1 for axis in (ax.xaxis, ax.yaxis) for t in axis.get_major_ticks()
                 if min(axis.get_view_interval()) <= t.get_loc() <= max(axis.get_view_interval())]  # those drawn
        for t in [*ticks, ax.xaxis.label, ax.yaxis.label, *ax.texts]:
            if t.get_visible() and t.get_text():
                b = t.get_window_extent(renderer)
                if t.get_bbox_patch() is not None:  # a row name's white box covers more than its letters
                    b = type(b).union([b, t.get_bbox_patch().get_window_extent(renderer)])
                out.append((t.get_text(), (b.x0, H - b.y1, b.x1, H - b.y0)))
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
