"""A line chart drawn with Pillow (matplotlib is not among nefii's dependencies).

One row of panels, each with its own axes, ticks at round numbers, a legend, and series that
are polylines (``dashed`` for reference levels).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont


@dataclass(frozen=True)
class Series:
    label: str
    x: np.ndarray
    y: np.ndarray
    colour: tuple[int, int, int]
    dashed: bool = False


@dataclass
class Panel:
    title: str
    series: list[Series] = field(default_factory=list)


def nice_ticks(lo: float, hi: float, count: int = 5) -> np.ndarray:
    """Round tick values covering [lo, hi] (1, 2, 5 times a power of ten apart)."""
    if not hi > lo:
        hi = lo + 1.0
    raw = (hi - lo) / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    return np.arange(math.floor(lo / step) * step, hi + 0.5 * step, step)


def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: one bitmap size
        return ImageFont.load_default()


def _dashed(draw: ImageDraw.ImageDraw, pts: list[tuple[float, float]], colour, width: int, dash: float = 8.0):
    for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:]):
        n = max(1, int(math.hypot(x1 - x0, y1 - y0) / dash))
        for k in range(0, n, 2):
            a, b = k / n, min(k + 1, n) / n
            draw.line([(x0 + a * (x1 - x0), y0 + a * (y1 - y0)), (x0 + b * (x1 - x0), y0 + b * (y1 - y0))],
                      fill=colour, width=width)


def draw_chart(path: Path, panels: list[Panel], xlabel: str, ylabel: str, panel_size=(520, 400)) -> None:
    W, H = panel_size
    img = Image.new("RGB", (W * len(panels), H), "white")
    d = ImageDraw.Draw(img)
    small, big = _font(13), _font(16)
    left, right, top, bottom = 62, 14, 30, 48
    for p_idx, panel in enumerate(panels):
        ox = p_idx * W
        xs = np.concatenate([s.x for s in panel.series]) if panel.series else np.array([0.0, 1.0])
        ys = np.concatenate([s.y for s in panel.series]) if panel.series else np.array([0.0, 1.0])
        xt = nice_ticks(0.0, float(np.nanmax(xs)) if len(xs) else 1.0)
        yt = nice_ticks(float(np.nanmin(ys)) - 0.5, float(np.nanmax(ys)) + 0.5)
        x0, x1, y0, y1 = xt[0], xt[-1], yt[0], yt[-1]
        px0, px1, py0, py1 = ox + left, ox + W - right, H - bottom, top

        def to_px(x, y):
            return (px0 + (x - x0) / (x1 - x0) * (px1 - px0), py0 + (y - y0) / (y1 - y0) * (py1 - py0))

        for t in xt:
            X = to_px(t, y0)[0]
            d.line([(X, py0), (X, py1)], fill=(230, 230, 230))
            d.text((X, py0 + 4), f"{t:g}", fill="black", font=small, anchor="ma")
        for t in yt:
            Y = to_px(x0, t)[1]
            d.line([(px0, Y), (px1, Y)], fill=(230, 230, 230))
            d.text((px0 - 5, Y), f"{t:g}", fill="black", font=small, anchor="rm")
        d.rectangle([px0, py1, px1, py0], outline="black")
        d.text(((px0 + px1) / 2, 6), panel.title, fill="black", font=big, anchor="ma")
        d.text(((px0 + px1) / 2, H - 18), xlabel, fill="black", font=small, anchor="ma")
        label = Image.new("RGB", (H - top - bottom, 18), "white")
        ImageDraw.Draw(label).text(((H - top - bottom) / 2, 0), ylabel, fill="black", font=small, anchor="ma")
        img.paste(label.rotate(90, expand=True), (ox + 4, top))
        for s in panel.series:
            ok = ~(np.isnan(s.x) | np.isnan(s.y))
            pts = [to_px(x, y) for x, y in zip(s.x[ok], s.y[ok])]
            if len(pts) == 1:
                X, Y = pts[0]
                d.ellipse([X - 3, Y - 3, X + 3, Y + 3], fill=s.colour)
            elif s.dashed:
                _dashed(d, pts, s.colour, 2)
            elif pts:
                d.line(pts, fill=s.colour, width=2, joint="curve")
        ly = py0 - 8 - 18 * len(panel.series)
        for k, s in enumerate(panel.series):
            Y = ly + 18 * k + 9
            seg = [(px1 - 190, Y), (px1 - 165, Y)]
            (_dashed(d, seg, s.colour, 2, 5.0) if s.dashed else d.line(seg, fill=s.colour, width=2))
            d.text((px1 - 160, Y), s.label, fill="black", font=small, anchor="lm")
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
