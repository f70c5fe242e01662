"""First rope-rope self-collision of a marker polyline (the flying knot's "critical point").

The gap is the minimum distance between non-neighbouring polyline segments minus the rope
diameter. The first frame where it is <= 0 is the contact frame; the event time is interpolated
linearly from the signed gap at the frame before and at the contact frame (integer index plus
interpolation, never float clock comparisons).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CollisionEvent:
    index: int  # first frame where contact holds
    time: float  # s, interpolated inside (index-1, index]
    s_a: float  # arc-length fraction of the closest point nearer the held end
    s_b: float  # arc-length fraction of the closest point nearer the free end
    gap_before: float  # m, signed gap at frame index-1 (nan when index == 0)
    gap_at: float  # m, signed gap at frame index


def candidate_pairs(marker_arclength: np.ndarray, length: float, radius: float,
                    exclude_arclength: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Segment pairs (i < j) that may really touch.

    A rope cannot touch itself between points closer in arc length than a loop around its own
    thickness (~2 pi r), and the marker polyline cuts corners by up to about one marker spacing,
    so pairs closer than max(2 pi r, largest marker spacing) along the rope are excluded, and
    adjacent segments always are.
    """
    s = np.asarray(marker_arclength, dtype=np.float64) * length
    seg_len = np.diff(s)
    if exclude_arclength is None:
        exclude_arclength = max(2.0 * np.pi * radius, float(seg_len.max()))
    n = len(seg_len)
    i, j = np.triu_indices(n, k=2)
    gap_arc = s[j] - s[i + 1]  # arc length between the end of segment i and the start of segment j
    keep = gap_arc > exclude_arclength
    return i[keep], j[keep]


def segment_distances(p0, p1, q0, q1):
    """Closest distance between segments p0-p1 and q0-q1 (broadcast over leading dims).

    Returns (distance, u, v) with u, v in [0,1] the parameters of the closest points.
    """
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("...k,...k->...", d1, d1)
    e = np.einsum("...k,...k->...", d2, d2)
    f = np.einsum("...k,...k->...", d2, r)
    c = np.einsum("...k,...k->...", d1, r)
    b = np.einsum("...k,...k->...", d1, d2)
    tiny = 1e-18
    denom = a * e - b * b
    # Parallel segments: any u works, take 0 and clamp v (Ericson, Real-Time Collision Detection 5.1.9).
    u = np.where(denom > tiny * np.maximum(a * e, tiny), (b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0)
    u = np.clip(u, 0.0, 1.0)
    v = (b * u + f) / np.maximum(e, tiny)
    v_clamped = np.clip(v, 0.0, 1.0)
    u = np.where(v != v_clamped, np.clip((b * v_clamped - c) / np.maximum(a, tiny), 0.0, 1.0), u)
    v = v_clamped
    diff = (p0 + d1 * u[..., None]) - (q0 + d2 * v[..., None])
    return np.sqrt(np.einsum("...k,...k->...", diff, diff)), u, v


def gap_series(markers: np.ndarray, marker_arclength: np.ndarray, length: float, radius: float,
               exclude_arclength: float | None = None, chunk: int = 256):
    """Signed gap (T,) and the closest pair per frame: (gap, seg_i, seg_j, u, v)."""
    markers = np.asarray(markers, dtype=np.float64)
    T = markers.shape[0]
    i, j = candidate_pairs(marker_arclength, length, radius, exclude_arclength)
    gap = np.full(T, np.inf)
    best_i = np.zeros(T, dtype=np.int64)
    best_j = np.zeros(T, dtype=np.int64)
    best_u = np.zeros(T)
    best_v = np.zeros(T)
    if len(i) == 0:
        return gap, best_i, best_j, best_u, best_v
    for start in range(0, T, chunk):
        m = markers[start:start + chunk]
        dist, u, v = segment_distances(m[:, i], m[:, i + 1], m[:, j], m[:, j + 1])
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(m))
        sl = slice(start, start + len(m))
        gap[sl] = dist[rows, k] - 2.0 * radius
        best_i[sl], best_j[sl] = i[k], j[k]
        best_u[sl], best_v[sl] = u[rows, k], v[rows, k]
    return gap, best_i, best_j, best_u, best_v


def first_collision(time: np.ndarray, markers: np.ndarray, marker_arclength: np.ndarray, length: float,
                    radius: float, exclude_arclength: float | None = None) -> CollisionEvent | None:
    gap, bi, bj, bu, bv = gap_series(markers, marker_arclength, length, radius, exclude_arclength)
    hits = np.flatnonzero(gap <= 0.0)
    if len(hits) == 0:
        return None
    k = int(hits[0])
    s = np.asarray(marker_arclength, dtype=np.float64)
    s_a = s[bi[k]] + bu[k] * (s[bi[k] + 1] - s[bi[k]])
    s_b = s[bj[k]] + bv[k] * (s[bj[k] + 1] - s[bj[k]])
    if k == 0:
        return CollisionEvent(0, float(time[0]), float(s_a), float(s_b), float("nan"), float(gap[0]))
    g0, g1 = float(gap[k - 1]), float(gap[k])
    frac = g0 / (g0 - g1) if g0 - g1 > 0 else 1.0
    t = float(time[k - 1] + frac * (time[k] - time[k - 1]))
    return CollisionEvent(k, t, float(s_a), float(s_b), g0, g1)
