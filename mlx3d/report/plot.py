"""Small, readable line and scatter plots drawn with Pillow (no plotting library needed).

``plot(series, title=..., xlabel=..., ylabel=...)`` returns a ``PIL.Image``:
a title, a framed plot area with grid lines, ticks and numbers on both axes,
axis labels (put the unit in them, e.g. ``"wall time (s)"``), one line with
markers per :class:`Series` (or markers only), optional horizontal error bars
and point labels, and a legend to the right of the plot area. ``log_x=True``
uses a logarithmic x axis (ticks at 1-2-5 steps per decade). The image is
drawn at twice its size and scaled down, which smooths lines and text.
``barh(categories, {group: values})`` draws horizontal grouped bars.

    from mlx3d.report.plot import Series, plot, save_png
    image = plot([Series("mcmc", [1, 2, 4], [20, 25, 27])], title="Training",
                 xlabel="wall time (s)", ylabel="held-out PSNR (dB)", log_x=True)
    save_png(image, "psnr.png")
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from typing import Sequence

from PIL import Image, ImageChops, ImageDraw, ImageFont

#: Colours of the series, in turn (Tableau 10).
PALETTE = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
)
#: Marker shapes, in turn: circle, square, triangle up, diamond, triangle down, cross, plus.
MARKERS = ("o", "s", "^", "D", "v", "x", "+")
BACKGROUND = (255, 255, 255)
INK = (34, 34, 34)
GRID = (225, 225, 225)
SCALE = 2  # supersampling factor


@dataclass
class Series:
    """One line (or set of points) of a plot.

    x, y: the points, in order; xerr: optional (low, high) x values per point,
    drawn as horizontal error bars; labels: optional text next to each point;
    line: join the points (else markers only); color/marker: None picks the
    next from ``PALETTE``/``MARKERS``.
    """

    label: str
    x: Sequence[float]
    y: Sequence[float]
    color: tuple | None = None
    marker: str | None = None
    line: bool = True
    xerr: Sequence[tuple] | None = None
    labels: Sequence[str] | None = None

    def __post_init__(self):
        if len(self.x) != len(self.y):
            raise ValueError(f"series {self.label!r}: {len(self.x)} x values but {len(self.y)} y values")
        for name in ("xerr", "labels"):
            values = getattr(self, name)
            if values is not None and len(values) != len(self.x):
                raise ValueError(f"series {self.label!r}: {name} needs one entry per point")


def font(size: int):
    """Pillow's built-in scalable font at ``size`` pixels (Pillow >= 10.1)."""
    return ImageFont.load_default(size=size)


# ------------------------------------------------------------------ ticks
def nice_ticks(lo: float, hi: float, count: int = 6) -> list:
    """About ``count`` round tick values (steps of 1, 2, 2.5 or 5 times a power of ten) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"axis range must be finite, got {lo}, {hi}")
    if hi <= lo:
        lo, hi = lo - 1.0, hi + 1.0
    raw = (hi - lo) / max(count - 1, 1)
    power = 10.0 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw * 0.999)
    first = math.floor(lo / step + 1e-9) * step
    ticks = []
    k = 0
    while True:
        t = first + k * step
        if t > hi + step * 1e-6:
            break
        if t >= lo - step * 1e-6:
            ticks.append(round(t, 12))
        k += 1
    return ticks


def log_ticks(lo: float, hi: float) -> list:
    """Tick values for a log axis over [lo, hi] (lo > 0): 1-2-5 per decade when the range is short, decades otherwise."""
    if lo <= 0 or hi <= 0:
        raise ValueError(f"a log axis needs positive values, got {lo}, {hi}")
    decades = math.log10(hi) - math.log10(lo)
    mantissas = (1, 2, 5) if decades <= 3 else (1,)
    if decades < 0.7:
        mantissas = (1, 1.5, 2, 3, 5, 7)
    ticks = []
    for e in range(math.floor(math.log10(lo)) - 1, math.ceil(math.log10(hi)) + 1):
        for m in mantissas:
            t = m * 10.0**e
            if lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9):
                ticks.append(t)
    return ticks


def format_tick(value: float, step: float | None = None) -> str:
    """A tick label: as many decimals as the step between ticks needs; thousands separated."""
    if step is None or step <= 0:
        text = f"{value:.3g}"
        return text if "e" not in text else f"{value:g}"
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if step * 10**decimals % 1 > 1e-6:  # e.g. 2.5 needs one more
        decimals += 1
    if abs(value) >= 1000 and decimals == 0:
        return f"{value:,.0f}"
    return f"{value:.{decimals}f}"


# ------------------------------------------------------------------ drawing helpers
def _marker(draw: ImageDraw.ImageDraw, shape: str, x: float, y: float, r: float, color) -> None:
    w = max(1, int(round(r / 2.5)))
    if shape == "s":
        draw.rectangle([x - r, y - r, x + r, y + r], fill=color)
    elif shape == "^":
        draw.polygon([(x, y - r * 1.2), (x - r * 1.1, y + r * 0.8), (x + r * 1.1, y + r * 0.8)], fill=color)
    elif shape == "v":
        draw.polygon([(x, y + r * 1.2), (x - r * 1.1, y - r * 0.8), (x + r * 1.1, y - r * 0.8)], fill=color)
    elif shape == "D":
        draw.polygon([(x, y - r * 1.3), (x + r * 1.1, y), (x, y + r * 1.3), (x - r * 1.1, y)], fill=color)
    elif shape == "x":
        draw.line([(x - r, y - r), (x + r, y + r)], fill=color, width=w * 2)
        draw.line([(x - r, y + r), (x + r, y - r)], fill=color, width=w * 2)
    elif shape == "+":
        draw.line([(x - r * 1.2, y), (x + r * 1.2, y)], fill=color, width=w * 2)
        draw.line([(x, y - r * 1.2), (x, y + r * 1.2)], fill=color, width=w * 2)
    else:
        draw.ellipse([x - r, y - r, x + r, y + r], fill=color)


def _text_size(draw, text: str, f) -> tuple:
    box = draw.textbbox((0, 0), text, font=f)
    return box[2] - box[0], box[3] - box[1]


def _xlabel(draw, xlabel: str, note: str | None, left, right, bottom, s: int, label_font, tick_font, small) -> tuple:
    """Draw the x-axis label centred under the plot, and the grey ``note`` under it; returns the label's size."""
    w, h = _text_size(draw, xlabel, label_font)
    xlabel_y = bottom + 14 * s + _text_size(draw, "0", tick_font)[1] + 10 * s
    draw.text(((left + right) / 2 - w / 2, xlabel_y), xlabel, font=label_font, fill=INK)
    if note:
        nw, _ = _text_size(draw, note, small)
        draw.text(((left + right) / 2 - nw / 2, xlabel_y + h + 12 * s), note, font=small, fill=(110, 110, 110))
    return w, h


def _range(values: list, log: bool, pad: float = 0.05) -> tuple:
    finite = [v for v in values if math.isfinite(v) and (v > 0 or not log)]
    if not finite:
        return (1.0, 10.0) if log else (0.0, 1.0)
    lo, hi = min(finite), max(finite)
    if log:
        if hi / lo < 1.0001:
            return lo / 2, hi * 2
        span = math.log10(hi) - math.log10(lo)
        return 10 ** (math.log10(lo) - pad * span), 10 ** (math.log10(hi) + pad * span)
    if hi - lo < 1e-12:
        return lo - 1.0, hi + 1.0
    span = hi - lo
    return lo - pad * span, hi + pad * span


# ------------------------------------------------------------------ the plot
def plot(
    series: Sequence[Series],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    log_x: bool = False,
    size: tuple = (1000, 600),
    xlim: tuple | None = None,
    ylim: tuple | None = None,
    legend: bool = True,
    note: str | None = None,
) -> Image.Image:
    """Draw ``series`` into a new RGB image of ``size`` pixels (see the module docstring).

    xlim/ylim: fixed axis ranges (else the data's, with a 5% margin);
    note: a line of small text under the x-axis label (e.g. the machine).
    """
    s = SCALE
    width, height = size[0] * s, size[1] * s
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    title_font, label_font, tick_font, legend_font = font(20 * s), font(15 * s), font(13 * s), font(13 * s)
    small = font(11 * s)

    styled = []
    for i, ser in enumerate(series):
        styled.append((ser, ser.color or PALETTE[i % len(PALETTE)], ser.marker or MARKERS[i % len(MARKERS)]))

    xs = [v for ser in series for v in ser.x] + [v for ser in series if ser.xerr for pair in ser.xerr for v in pair]
    ys = [v for ser in series for v in ser.y]
    x0, x1 = xlim if xlim is not None else _range(xs, log_x)
    y0, y1 = ylim if ylim is not None else _range(ys, False)
    if log_x:
        xticks = log_ticks(x0, x1)
        xlabels = [format_tick(t) for t in xticks]
    else:
        xticks = nice_ticks(x0, x1)
        step = xticks[1] - xticks[0] if len(xticks) > 1 else None
        xlabels = [format_tick(t, step) for t in xticks]
        if xlim is None:
            x0, x1 = min(x0, xticks[0]), max(x1, xticks[-1])
    yticks = nice_ticks(y0, y1, 7)
    ystep = yticks[1] - yticks[0] if len(yticks) > 1 else None
    ylabels = [format_tick(t, ystep) for t in yticks]
    if ylim is None:
        y0, y1 = min(y0, yticks[0]), max(y1, yticks[-1])

    # Layout: title on top, y tick labels and the rotated y label on the left, legend on the right.
    ytick_w = max((_text_size(draw, t, tick_font)[0] for t in ylabels), default=0)
    left = int(18 * s + _text_size(draw, ylabel, label_font)[1] + 12 * s + ytick_w + 10 * s)
    top = int(22 * s + _text_size(draw, title, title_font)[1] + 16 * s)
    bottom = int(height - (14 * s + _text_size(draw, "0", tick_font)[1] + 12 * s + _text_size(draw, xlabel, label_font)[1] + 16 * s))
    if note:
        bottom -= int(_text_size(draw, note, small)[1] + 10 * s)
    legend_w = 0
    if legend and series:
        legend_w = int(max(_text_size(draw, ser.label, legend_font)[0] for ser in series) + 60 * s)
    right = int(width - 24 * s - legend_w)

    def px(v: float) -> float:
        if log_x:
            v = math.log10(max(v, 1e-300))
            a, b = math.log10(x0), math.log10(x1)
        else:
            a, b = x0, x1
        return left + (v - a) / (b - a) * (right - left)

    def py(v: float) -> float:
        return bottom - (v - y0) / (y1 - y0) * (bottom - top)

    # Title.
    tw, _ = _text_size(draw, title, title_font)
    draw.text(((left + right) / 2 - tw / 2, 18 * s), title, font=title_font, fill=INK)

    # Grid, ticks and tick labels.
    for t, text in zip(xticks, xlabels):
        x = px(t)
        if left - 1 <= x <= right + 1:
            draw.line([(x, top), (x, bottom)], fill=GRID, width=s)
            draw.line([(x, bottom), (x, bottom + 6 * s)], fill=INK, width=s)
            w, _ = _text_size(draw, text, tick_font)
            draw.text((x - w / 2, bottom + 10 * s), text, font=tick_font, fill=INK)
    for t, text in zip(yticks, ylabels):
        y = py(t)
        if top - 1 <= y <= bottom + 1:
            draw.line([(left, y), (right, y)], fill=GRID, width=s)
            draw.line([(left - 6 * s, y), (left, y)], fill=INK, width=s)
            w, h = _text_size(draw, text, tick_font)
            draw.text((left - 10 * s - w, y - h / 2 - 2 * s), text, font=tick_font, fill=INK)
    draw.rectangle([left, top, right, bottom], outline=INK, width=s)

    # Axis labels (the y label rotated).
    w, h = _xlabel(draw, xlabel, note, left, right, bottom, s, label_font, tick_font, small)
    w, h = _text_size(draw, ylabel, label_font)
    label = Image.new("RGB", (w + 8 * s, h + 12 * s), BACKGROUND)
    ImageDraw.Draw(label).text((4 * s, 2 * s), ylabel, font=label_font, fill=INK)
    label = label.rotate(90, expand=True)
    image.paste(label, (int(16 * s), int((top + bottom) / 2 - label.height / 2)))

    # The data, clipped to the plot area.
    area = Image.new("RGB", (width, height), BACKGROUND)
    mask = Image.new("L", (width, height), 0)
    adraw, mdraw = ImageDraw.Draw(area), ImageDraw.Draw(mask)
    for ser, color, marker in styled:
        points = [(px(x), py(y)) for x, y in zip(ser.x, ser.y) if math.isfinite(x) and math.isfinite(y) and (x > 0 or not log_x)]
        if ser.xerr is not None:
            for (lo, hi), y in zip(ser.xerr, ser.y):
                if math.isfinite(lo) and math.isfinite(hi) and (lo > 0 or not log_x):
                    yy = py(y)
                    for d in (adraw, mdraw):
                        fill = color if d is adraw else 255
                        d.line([(px(lo), yy), (px(hi), yy)], fill=fill, width=2 * s)
                        d.line([(px(lo), yy - 5 * s), (px(lo), yy + 5 * s)], fill=fill, width=2 * s)
                        d.line([(px(hi), yy - 5 * s), (px(hi), yy + 5 * s)], fill=fill, width=2 * s)
        if ser.line and len(points) > 1:
            adraw.line(points, fill=color, width=3 * s, joint="curve")
            mdraw.line(points, fill=255, width=3 * s, joint="curve")
        for x, y in points:
            _marker(adraw, marker, x, y, 5 * s, color)
            _marker(mdraw, marker, x, y, 5 * s, 255)
    clip = Image.new("L", (width, height), 0)
    ImageDraw.Draw(clip).rectangle([left + s, top + s, right - s, bottom - s], fill=255)
    mask = ImageChops.darker(mask, clip)
    image.paste(area, (0, 0), mask)

    # Point labels (drawn over the data, inside the plot area).
    for ser, color, marker in styled:
        if ser.labels is None:
            continue
        for x, y, text in zip(ser.x, ser.y, ser.labels):
            if text and math.isfinite(x) and math.isfinite(y) and (x > 0 or not log_x):
                X, Y = px(x), py(y)
                w, h = _text_size(draw, text, small)
                tx = X + 8 * s if X + 8 * s + w < right else X - 8 * s - w
                ty = Y - h - 8 * s if Y - h - 8 * s > top else Y + 6 * s
                draw.text((tx, ty), text, font=small, fill=INK)

    # Legend: a framed box to the right of the plot area.
    if legend and series:
        line_h = _text_size(draw, "Ag", legend_font)[1] + 12 * s
        lx = right + 16 * s
        ly = top
        box_h = line_h * len(series) + 12 * s
        draw.rectangle([lx, ly, width - 8 * s, ly + box_h], outline=(180, 180, 180), width=s)
        for i, (ser, color, marker) in enumerate(styled):
            y = ly + 6 * s + i * line_h + line_h / 2
            if ser.line:
                draw.line([(lx + 8 * s, y), (lx + 38 * s, y)], fill=color, width=3 * s)
            _marker(draw, marker, lx + 23 * s, y, 5 * s, color)
            _, h = _text_size(draw, ser.label, legend_font)
            draw.text((lx + 46 * s, y - h / 2 - 3 * s), ser.label, font=legend_font, fill=INK)

    return image.resize(size, Image.Resampling.LANCZOS)


def barh(
    categories: Sequence[str],
    groups: dict,
    *,
    title: str,
    xlabel: str,
    size: tuple = (1000, 600),
    note: str | None = None,
) -> Image.Image:
    """Horizontal grouped bars: one row per category (labelled on the left), one bar per group
    (``{label: values}``, one value per category, drawn in ``PALETTE`` order, legend on the right)."""
    s = SCALE
    width, height = size[0] * s, size[1] * s
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    title_font, label_font, tick_font, small = font(20 * s), font(15 * s), font(13 * s), font(11 * s)
    for label, values in groups.items():
        if len(values) != len(categories):
            raise ValueError(f"group {label!r}: {len(values)} values for {len(categories)} categories")
    values = [v for vs in groups.values() for v in vs if v is not None and math.isfinite(v)]
    hi = max(values + [0.0]) * 1.08 or 1.0
    lo = min(values + [0.0])
    lo = lo * 1.08 if lo < 0 else 0.0
    ticks = nice_ticks(lo, hi)
    step = ticks[1] - ticks[0] if len(ticks) > 1 else None
    x0, x1 = min(lo, ticks[0]), max(hi, ticks[-1])

    cat_w = max((_text_size(draw, c, tick_font)[0] for c in categories), default=0)
    legend_w = int(max((_text_size(draw, g, tick_font)[0] for g in groups), default=0) + 50 * s)
    left, right = int(20 * s + cat_w + 12 * s), int(width - 24 * s - legend_w)
    top = int(22 * s + _text_size(draw, title, title_font)[1] + 16 * s)
    bottom = int(height - (14 * s + _text_size(draw, "0", tick_font)[1] + 12 * s + _text_size(draw, xlabel, label_font)[1] + 16 * s))
    if note:
        bottom -= int(_text_size(draw, note, small)[1] + 10 * s)

    def px(v):
        return left + (v - x0) / (x1 - x0) * (right - left)

    tw, _ = _text_size(draw, title, title_font)
    draw.text(((left + right) / 2 - tw / 2, 18 * s), title, font=title_font, fill=INK)
    for t in ticks:
        x = px(t)
        draw.line([(x, top), (x, bottom)], fill=GRID, width=s)
        draw.line([(x, bottom), (x, bottom + 6 * s)], fill=INK, width=s)
        text = format_tick(t, step)
        w, _ = _text_size(draw, text, tick_font)
        draw.text((x - w / 2, bottom + 10 * s), text, font=tick_font, fill=INK)
    row_h = (bottom - top) / max(len(categories), 1)
    bar_h = row_h * 0.8 / max(len(groups), 1)
    for i, category in enumerate(categories):
        y = top + i * row_h + row_h * 0.1
        w, h = _text_size(draw, category, tick_font)
        draw.text((left - 10 * s - w, top + (i + 0.5) * row_h - h / 2 - 3 * s), category, font=tick_font, fill=INK)
        for k, (label, vals) in enumerate(groups.items()):
            v = vals[i]
            if v is None or not math.isfinite(v):
                continue
            a, b = sorted((px(0.0), px(v)))
            draw.rectangle([a, y + k * bar_h, max(b, a + s), y + (k + 1) * bar_h - s], fill=PALETTE[k % len(PALETTE)])
    draw.line([(px(0.0), top), (px(0.0), bottom)], fill=INK, width=s)
    draw.rectangle([left, top, right, bottom], outline=INK, width=s)
    w, h = _xlabel(draw, xlabel, note, left, right, bottom, s, label_font, tick_font, small)
    line_h = _text_size(draw, "Ag", tick_font)[1] + 12 * s
    lx = right + 16 * s
    draw.rectangle([lx, top, width - 8 * s, top + line_h * len(groups) + 12 * s], outline=(180, 180, 180), width=s)
    for k, label in enumerate(groups):
        y = top + 6 * s + k * line_h + line_h / 2
        draw.rectangle([lx + 10 * s, y - 6 * s, lx + 30 * s, y + 6 * s], fill=PALETTE[k % len(PALETTE)])
        _, h = _text_size(draw, label, tick_font)
        draw.text((lx + 38 * s, y - h / 2 - 3 * s), label, font=tick_font, fill=INK)
    return image.resize(size, Image.Resampling.LANCZOS)


def png_bytes(image: Image.Image) -> bytes:
    """The image encoded as PNG."""
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def save_png(image: Image.Image, path) -> None:
    """Write the image as a PNG file, atomically."""
    from ..io.atomic import atomic_write

    with atomic_write(path) as f:
        f.write(png_bytes(image))
