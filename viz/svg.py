"""Small, dependency-free SVG charts for run folders and the report page: a fit writes its plots without
importing matplotlib (a second of start-up), and the report embeds them inline, so it opens offline."""
from __future__ import annotations

import html
import math

import numpy as np

PALETTE = ["#2891e6", "#e6782a", "#50c850", "#b455d2", "#d23c3c", "#8c8c8c", "#1eb4b4", "#c8a014"]
ROLE_COLORS = {"reference": "#5a5a5a", "measured": "#e6782a", "fitted": "#2891e6", "analytic": "#50c850"}


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step) * step
    return [start + i * step for i in range(int((hi - start) / step + 1e-9) + 1)]


def _fmt(v: float) -> str:
    return f"{v:.3g}" if v != 0 else "0"


def line_chart(series: list[dict], title: str = "", x_label: str = "", y_label: str = "", log_y: bool = False,
               width: int = 520, height: int = 300, hline: float | None = None, hline_label: str = "",
               equal_scale: bool = False) -> str:
    """series: [{"x": ..., "y": ..., "label": str, "color": optional, "dash": optional, "markers": bool}] ->
    an <svg> element. Non-finite (and, on a log axis, non-positive) points are left out. equal_scale: one unit
    spans as many pixels along x as along y (a shape seen from the side keeps its proportions)."""
    left, right, top, bottom = 62, 14, 26, 44
    pw, ph = width - left - right, height - top - bottom
    clean = []
    for s in series:
        x, y = np.asarray(s["x"], float), np.asarray(s["y"], float)
        ok = np.isfinite(x) & np.isfinite(y) & ((y > 0) if log_y else True)
        clean.append((s, x[ok], y[ok]))
    xs = np.concatenate([c[1] for c in clean]) if clean else np.zeros(0)
    ys = np.concatenate([c[2] for c in clean]) if clean else np.zeros(0)
    if hline is not None and (hline > 0 or not log_y):
        ys = np.append(ys, hline)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="11" role="img" '
             f'aria-label="{html.escape(title)}">', f'<rect width="{width}" height="{height}" fill="white"/>']
    if title:
        parts.append(f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="12">{html.escape(title)}</text>')
    if xs.size == 0:
        parts.append(f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle">no finite data</text></svg>')
        return "".join(parts)
    fy = np.log10 if log_y else (lambda v: v)
    x0, x1 = float(xs.min()), float(xs.max())
    y0, y1 = float(fy(ys).min()), float(fy(ys).max())
    if x1 <= x0:
        x0, x1 = x0 - 0.5, x1 + 0.5
    if y1 <= y0:
        y0, y1 = y0 - 0.5, y1 + 0.5
    pad = 0.05 * (y1 - y0)
    y0, y1 = y0 - pad, y1 + pad
    if equal_scale and not log_y:  # widen the shorter span about its centre until both give the same units/pixel
        per_px = max((x1 - x0) / pw, (y1 - y0) / ph)
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        x0, x1 = cx - per_px * pw / 2, cx + per_px * pw / 2
        y0, y1 = cy - per_px * ph / 2, cy + per_px * ph / 2
    px = lambda v: left + (v - x0) / (x1 - x0) * pw  # noqa: E731
    py = lambda v: top + ph - (fy(v) - y0) / (y1 - y0) * ph  # noqa: E731
    parts.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>')
    for t in _nice_ticks(x0, x1):
        parts.append(f'<line x1="{px(t):.1f}" y1="{top + ph}" x2="{px(t):.1f}" y2="{top + ph + 4}" stroke="#999"/>'
                     f'<text x="{px(t):.1f}" y="{top + ph + 16}" text-anchor="middle">{_fmt(t)}</text>')
    yt = [10.0 ** k for k in range(math.ceil(y0), math.floor(y1) + 1)] if log_y else _nice_ticks(y0, y1)
    for t in yt:
        parts.append(f'<line x1="{left - 4}" y1="{py(t):.1f}" x2="{left}" y2="{py(t):.1f}" stroke="#999"/>'
                     f'<text x="{left - 6}" y="{py(t) + 4:.1f}" text-anchor="end">{_fmt(t)}</text>')
    if x_label:
        parts.append(f'<text x="{left + pw / 2}" y="{height - 6}" text-anchor="middle">{html.escape(x_label)}</text>')
    if y_label:
        parts.append(f'<text transform="translate(13,{top + ph / 2}) rotate(-90)" text-anchor="middle">'
                     f'{html.escape(y_label)}</text>')
    if hline is not None and (hline > 0 or not log_y):
        parts.append(f'<line x1="{left}" y1="{py(hline):.1f}" x2="{left + pw}" y2="{py(hline):.1f}" stroke="#444" '
                     f'stroke-dasharray="5,4"/><text x="{left + pw - 4}" y="{py(hline) - 4:.1f}" text-anchor="end">'
                     f'{html.escape(hline_label)}</text>')
    legend_y = top + 12
    for i, (s, x, y) in enumerate(clean):
        color = s.get("color") or PALETTE[i % len(PALETTE)]
        if x.size:
            pts = " ".join(f"{px(a):.1f},{py(b):.1f}" for a, b in zip(x, y))
            dash = f' stroke-dasharray="{s["dash"]}"' if s.get("dash") else ""
            parts.append(f'<polyline points="{pts}" fill="none" stroke="{color}" stroke-width="1.6"{dash}/>')
            if s.get("markers"):
                parts += [f'<circle cx="{px(a):.1f}" cy="{py(b):.1f}" r="2.6" fill="{color}"/>' for a, b in zip(x, y)]
        if s.get("label"):
            parts.append(f'<line x1="{left + 8}" y1="{legend_y - 4}" x2="{left + 24}" y2="{legend_y - 4}" '
                         f'stroke="{color}" stroke-width="2"/><text x="{left + 28}" y="{legend_y}">'
                         f'{html.escape(s["label"])}</text>')
            legend_y += 14
    parts.append("</svg>")
    return "".join(parts)


def bar_chart(categories: list[str], groups: dict[str, list], title: str = "", y_label: str = "",
              width: int = 520, height: int = 280, hline: float | None = None, hline_label: str = "") -> str:
    """Grouped bars: one group of bars per category, one bar per entry of `groups` ({label: values}). A value
    that is not finite is drawn as a hatched stub marked 'n/a' rather than left out silently."""
    left, right, top, bottom = 62, 14, 26, 56
    pw, ph = width - left - right, height - top - bottom
    vals = [v for vs in groups.values() for v in vs if v is not None and math.isfinite(v)]
    hi = max(vals + ([hline] if hline is not None else []) + [1e-12])
    ticks = _nice_ticks(0.0, hi * 1.08)
    y1 = max(ticks[-1], hi * 1.08)
    py = lambda v: top + ph - v / y1 * ph  # noqa: E731
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="11" role="img" '
             f'aria-label="{html.escape(title)}">', f'<rect width="{width}" height="{height}" fill="white"/>',
             '<defs><pattern id="hatch" width="6" height="6" patternUnits="userSpaceOnUse" '
             'patternTransform="rotate(45)"><line x1="0" y1="0" x2="0" y2="6" stroke="#c33" stroke-width="2"/>'
             '</pattern></defs>']
    if title:
        parts.append(f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="12">{html.escape(title)}</text>')
    parts.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>')
    for t in ticks:
        parts.append(f'<line x1="{left - 4}" y1="{py(t):.1f}" x2="{left}" y2="{py(t):.1f}" stroke="#999"/>'
                     f'<text x="{left - 6}" y="{py(t) + 4:.1f}" text-anchor="end">{_fmt(t)}</text>')
    if y_label:
        parts.append(f'<text transform="translate(13,{top + ph / 2}) rotate(-90)" text-anchor="middle">'
                     f'{html.escape(y_label)}</text>')
    n, k = max(len(categories), 1), max(len(groups), 1)
    slot = pw / n
    bar = slot * 0.8 / k
    for i, cat in enumerate(categories):
        x0 = left + i * slot + slot * 0.1
        for j, (label, vs) in enumerate(groups.items()):
            color = ROLE_COLORS.get(label.split()[0], PALETTE[j % len(PALETTE)])
            v = vs[i] if i < len(vs) else None
            x = x0 + j * bar
            if v is None or not math.isfinite(v):
                parts.append(f'<rect x="{x:.1f}" y="{top + ph - 14}" width="{bar - 2:.1f}" height="14" '
                             f'fill="url(#hatch)"/><text x="{x + bar / 2:.1f}" y="{top + ph - 17}" '
                             f'text-anchor="middle">n/a</text>')
                continue
            parts.append(f'<rect x="{x:.1f}" y="{py(v):.1f}" width="{bar - 2:.1f}" height="{top + ph - py(v):.1f}" '
                         f'fill="{color}"><title>{html.escape(f"{cat}, {label}: {v:.4g}")}</title></rect>')
        parts.append(f'<text x="{left + (i + 0.5) * slot:.1f}" y="{top + ph + 15}" text-anchor="middle">'
                     f'{html.escape(str(cat))}</text>')
    if hline is not None:
        parts.append(f'<line x1="{left}" y1="{py(hline):.1f}" x2="{left + pw}" y2="{py(hline):.1f}" stroke="#444" '
                     f'stroke-dasharray="5,4"/><text x="{left + pw - 4}" y="{py(hline) - 4:.1f}" text-anchor="end">'
                     f'{html.escape(hline_label)}</text>')
    lx = left
    for j, label in enumerate(groups):
        color = ROLE_COLORS.get(label.split()[0], PALETTE[j % len(PALETTE)])
        parts.append(f'<rect x="{lx}" y="{height - 16}" width="12" height="10" fill="{color}"/>'
                     f'<text x="{lx + 16}" y="{height - 7}">{html.escape(label)}</text>')
        lx += 24 + 7 * len(label)
    parts.append("</svg>")
    return "".join(parts)
