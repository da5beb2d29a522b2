"""A small learning-curve PNG drawn with Pillow (already a dependency; matplotlib would add ~40 MB for two lines)."""

from __future__ import annotations

import os
from collections.abc import Sequence

from PIL import Image, ImageDraw

COLOURS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189))


def moving_average(values: list[float], window: int) -> list[float]:
    """Trailing mean over up to `window` values (shorter at the start)."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


def _panel(draw: ImageDraw.ImageDraw, box: tuple[int, int, int, int], title: str,
           series: Sequence[tuple[str, Sequence[float], Sequence[float]]], y_range: tuple[float, float] | None) -> None:
    x0, y0, x1, y1 = box
    left, bottom = x0 + 60, y1 - 30
    top, right = y0 + 22, x1 - 10
    draw.text((x0 + 60, y0 + 4), title, fill=(0, 0, 0))
    draw.rectangle((left, top, right, bottom), outline=(0, 0, 0))
    xs_all = [x for _, xs, _ in series for x in xs]
    ys_all = [y for _, _, ys in series for y in ys]
    if not xs_all:
        draw.text((left + 10, top + 10), "no data", fill=(0, 0, 0))
        return
    xmin, xmax = min(xs_all), max(xs_all)
    ymin, ymax = y_range if y_range else (min(ys_all), max(ys_all))
    if xmax == xmin:
        xmax = xmin + 1
    if ymax == ymin:
        ymax = ymin + 1
    sx = lambda x: left + (x - xmin) / (xmax - xmin) * (right - left)
    sy = lambda y: bottom - (y - ymin) / (ymax - ymin) * (bottom - top)
    for frac in (0.0, 0.5, 1.0):
        y = ymin + frac * (ymax - ymin)
        draw.text((x0 + 4, sy(y) - 6), f"{y:.2f}", fill=(0, 0, 0))
        draw.line((left, sy(y), right, sy(y)), fill=(220, 220, 220))
        x = xmin + frac * (xmax - xmin)
        draw.text((min(sx(x) - 20, right - 60), bottom + 6), f"{x:,.0f}", fill=(0, 0, 0))
    for i, (label, xs, ys) in enumerate(series):
        colour = COLOURS[i % len(COLOURS)]
        points = [(sx(x), sy(y)) for x, y in zip(xs, ys, strict=True)]
        if len(points) > 1:
            # raw per-update values faintly, a moving average (about 1/25 of the run) on top
            faint = tuple(255 - (255 - c) // 4 for c in colour)
            draw.line(points, fill=faint, width=1)
            smooth = moving_average(list(ys), max(1, len(ys) // 25))
            draw.line([(sx(x), sy(y)) for x, y in zip(xs, smooth, strict=True)], fill=colour, width=2)
        elif points:
            draw.ellipse((points[0][0] - 2, points[0][1] - 2, points[0][0] + 2, points[0][1] + 2), fill=colour)
        draw.text((right - 150, top + 6 + 14 * i), label, fill=colour)


def learning_curve(path: str | os.PathLike, runs: dict[str, list[dict]], width: int = 720,
                   titles: tuple[str, str] = ("mean episode return", "solve rate (finished episodes)")) -> None:
    """Write a PNG with mean episode return and solve rate against env steps, one line per run.

    `runs` maps a label to that run's metrics (dicts with env_steps, mean_return, solve_rate); `titles` names the
    two panels."""
    image = Image.new("RGB", (width, 520), "white")
    draw = ImageDraw.Draw(image)
    def series(key):
        return [(label, [m["env_steps"] for m in ms], [m[key] for m in ms]) for label, ms in runs.items()]

    _panel(draw, (0, 0, width, 260), titles[0], series("mean_return"), None)
    _panel(draw, (0, 260, width, 520), titles[1], series("solve_rate"), (0.0, 1.0))
    tmp = f"{path}.tmp.png"
    image.save(tmp)
    os.replace(tmp, path)
