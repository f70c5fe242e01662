"""A rope's first self-collision (the flying knot's "critical point") seen through markers, with a confidence.

The event is physics, not marker spacing: the first time two points of the rope whose separation ALONG the
rope is more than pi times its diameter (a tight U-turn) have centre lines within one diameter (the
surfaces touch). Arc-length positions s_a < s_b are fractions of the length in [0, 1]; times are seconds on
the file's own time axis; frame indices are integers, and the time inside a frame comes from linear
interpolation of the signed gap (never from comparing float clocks).

Method (README, "Events in motion capture", has the measurements behind every threshold):

1. Reconstruction between markers (`reconstruct`), exact in arc length. Per interval the circular arc through
   its two markers with exactly the interval's known arc length (turning angle from sin(t/2)/(t/2) =
   chord/arc), bent to the side where the natural cubic spline through all markers bulges (kept from the
   previous frame when the spline barely bends there); one tangent per marker (the bisector of the two arcs'
   tangents); each interval the cubic Hermite curve with those tangents whose length is the known arc length.
   A free end that curls into a loop smaller than one marker spacing (chord much shorter than arc) bulges as
   far as its length requires, where a polyline would cut the corner.
2. Contact test on the reconstruction: sub-segments <= 1.5 radius long, distance minimised under the exact
   along-rope constraint (the two closest points >= pi * diameter apart; `segment_distances_excluded`). A
   rigorous broad phase (`interval_bounds`: every rope of the known length through two markers lies in the
   spheroid with them as foci) skips interval pairs that cannot touch.
3. Time: the first frame whose reconstructed surface gap is within the contact level (CONTACT_LEVEL, 0.5 mm: the
   fine simulators' first impacts last 1.5-3 ms and the pieces then rest within +-0.2 mm, so a frame grid sees
   the resting gap, not the impact), interpolated inside the frame.
4. Confidence (`Detection.reasons` says why in sentences): an earlier near-contact within the gap's
   uncertainty (the only way to report a contact late), a slow approach, an unresolved curl at the contact
   (chord/arc < 2/pi: more than a half turn between two markers), a one-frame touch whose pieces then pass
   each other instead of staying together, bridged (occluded) markers bounding the contact, near it, or
   stretching the rope before it, or a marker missing for longer than 20 ms before it where the rope hidden there
   could have touched itself (the contact may lie in the gap; with no contact seen, such a gap leaves no usable
   answer, as does a recording that ends while the rope closes in), an event long after the rope's fastest
   motion. Marker noise widens the uncertainty; it never moves the contact level.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from wrenorm.jumps import largest_doublet, largest_jump, repeated_runs, true_runs
from wrenorm.tasks.rope.observable import marker_velocity, velocity_intervals

VERSION = 18  # bump when the detector's answer can change (keys the event cache)
TIME_TOLERANCE = 0.02  # s: the accuracy the event is wanted to; flags mean "cannot promise this"
CURL_CHORD_RATIO = 2.0 / np.pi  # chord/arc of a half turn between two markers: its shape is a guess
GAP_ERROR = 0.001  # m: reconstructed-gap error at a resolved contact (newton dev set, 12 markers: median 2 mm
#                    shape error on intervals with chord/arc > 0.95; the gap of two such pieces errs less)
SHAPE_ERROR_FRACTION = 0.25  # typical shape error of a bent interval / its spheroid half-width (newton dev)
MAX_BRIDGE_TIME = 0.02  # s: occlusions longer than this are not trusted near the event
MAX_MISSING_FRACTION = 0.5  # a marker missing in more of the frames makes the file unusable
STRETCH_SLACK = 0.02  # chord/arc above 1 that bridged samples may show before they count as stretching the rope
#                      (observed samples of the MuJoCo dev files reach 1.01; noise is added on top)
SUBSEGMENT_PER_RADIUS = 1.5  # sub-segment length <= 1.5 radius: sagitta error < ~1 mm on tight curls
NEAR_GAP = 0.02  # m: interval pairs whose rigorous bound is below this get the exact reconstructed gap
CONTACT_LEVEL = 5e-4  # m: surfaces this close touch. Fine simulators' first impacts last 1.5-3 ms, after which the
#                      pieces rest with gaps within +-0.2 mm (MuJoCo dev set): a 200 Hz frame grid lands on those gaps,
#                      not on the impact; 2.5x that band. Real ropes are fuzzier than that.
PAIR_END_HORIZON = 0.05  # s: the same for one pair's own gap where it is not the least (_pair_closing_at_the_end):
# built-in throws cut 3-12 ms before their contact, at 12 and 17 markers, that had read "no contact" (138 of 368) touch
# within 8.5 ms at their pair's last speed in median, 34 at most; a whole throw's flailing end closes pairs 0.15-0.4 m
# apart at 1.6-4.6 m/s (50-96 ms), which a horizon as long as END_HORIZON would have said
END_HORIZON = 0.1  # s: a recording whose last frames close the rope's gap fast enough to touch within this ends too
# early to say "no contact" (built-in throws cut 2-30 ms before their contact: 1-150 ms to touch at the last speed)
HOLD_TIME = 0.01  # s after the touch in which touching pieces stay within the gap's uncertainty (dev data)
# Confidence rules applied by default. "fold" (the contact closes a loop within two neighbouring marker intervals) is
# kept for measurements only: on the dev sets it never caught a wrong event that no other rule caught, and it
# flagged 8 (12 markers) and 11 (8 markers) right newton events.
# "start" (the gap within its uncertainty from the first frame) and "loop" (both contact points inside one marker
# interval) since stop 59: on the dev sets (42 MuJoCo and 40 newton throws at 8, 12 and 24 markers, 0.5-1 mm of noise)
# neither changed one answer; a probe's folded and figure-eight throws had read contacts 77-182 ms early there
RULES = ("earlier", "slow", "parted", "graze", "curl", "occlusion", "jump", "tip", "repeat", "start", "loop")
MAX_MARKER_JUMP = 10.0  # x the markers' largest frame-to-frame step around it (wrenorm.jumps): the built-in and test
# references reach 2.1-3.9, 50 frames cut out of a flick with its clock made uniform again 33
MAX_HAND_DOUBLET = 10.0  # x the hand's second difference around it (wrenorm.jumps.largest_doublet): newton's and
# MuJoCo's built-in-path throws 0 (with 0.5 mm noise at most 2.5); one frame cut while the hand moves 5.8-38 (README)


# ------------------------------------------------------------------------------------------------ results

@dataclass(frozen=True)
class CollisionEvent:
    """The critical moment used by the fit: detected in the markers or annotated by the user."""

    index: int  # first frame at or after the event (>= 1 for a usable event)
    time: float  # s, inside (time[index-1], time[index]]
    s_a: float  # arc-length fraction of the contact point nearer the held end
    s_b: float  # arc-length fraction of the contact point nearer the free end
    gap_before: float  # m, reconstructed signed gap at frame index-1 (nan when unknown)
    gap_at: float  # m, reconstructed signed gap at frame index
    source: str = "detected"  # "detected" or "annotated"
    confidence: str = "high"  # "high" or "low" (used, but flagged)
    reasons: tuple = ()

    @property
    def flagged(self) -> bool:
        return self.confidence != "high"


@dataclass
class Detection:
    status: str  # "contact", "no_contact" (none even within its uncertainty, and no long gap that could hide one)
    # or "unusable" (cannot tell)
    event: CollisionEvent | None  # set when status == "contact"
    confidence: str  # "high", "low" (contact reported but flagged) or "none" (status != "contact")
    reasons: list = field(default_factory=list)  # sentences; empty when nothing is doubtful
    diagnostics: dict = field(default_factory=dict)

    @property
    def flagged(self) -> bool:
        return self.confidence != "high"

    @property
    def time(self) -> float | None:
        return None if self.event is None else self.event.time

    def summary(self) -> str:
        if self.status == "contact":
            e = self.event
            head = (f"contact t={e.time:.4f} s (frame {e.index}) s={e.s_a:.3f}/{e.s_b:.3f} "
                    f"confidence={self.confidence}")
        else:
            head = f"{self.status} (confidence={self.confidence})"
        return head + "".join(f"\n  - {r}" for r in self.reasons)


# ----------------------------------------------------------------------------------------------- geometry

def _dot(a, b):
    return np.einsum("...k,...k->...", a, b)


def segment_distances(p0, p1, q0, q1):
    """Closest distance between segments p0-p1 and q0-q1 (broadcast over leading dims).

    Returns (distance, u, v) with u, v in [0,1] the parameters of the closest points.
    """
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a, e, f, c, b = _dot(d1, d1), _dot(d2, d2), _dot(d2, r), _dot(d1, r), _dot(d1, d2)
    tiny = 1e-18
    denom = a * e - b * b
    # Parallel segments: any u works, take 0 and clamp v (Ericson, Real-Time Collision Detection 5.1.9).
    u = np.where(denom > 1e-12 * np.maximum(a * e, tiny), (b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0)
    u = np.clip(u, 0.0, 1.0)
    v = (b * u + f) / np.maximum(e, tiny)
    v_clamped = np.clip(v, 0.0, 1.0)
    u = np.where(v != v_clamped, np.clip((b * v_clamped - c) / np.maximum(a, tiny), 0.0, 1.0), u)
    v = v_clamped
    diff = (p0 + d1 * u[..., None]) - (q0 + d2 * v[..., None])
    return np.sqrt(_dot(diff, diff)), u, v


def segment_distances_excluded(p0, p1, q0, q1, sa0, la, sb0, lb, excl):
    """Closest distance between segments P = p0-p1 and Q = q0-q1 (broadcast over leading dims) subject to
    an along-rope separation of the two closest points >= excl.

    Arc position on P is sa0 + u la, on Q sb0 + v lb (Q further along the rope). The constraint is a half
    plane in (u, v) and the distance is convex, so when the unconstrained closest pair violates it the
    constrained minimum lies on the line (sb0 + v lb) - (sa0 + u la) = excl: a 1-D quadratic, solved in
    closed form. Pairs that can never be far enough apart get +inf. Returns (distance, u, v).
    """
    dist, u, v = segment_distances(p0, p1, q0, q1)
    sa0, la, sb0, lb = (np.broadcast_to(np.asarray(x, dtype=np.float64), u.shape) for x in (sa0, la, sb0, lb))
    bad = (sb0 + v * lb) - (sa0 + u * la) < excl
    if not np.any(bad):
        return dist, u, v
    tiny = 1e-18
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    lbs = np.maximum(lb, tiny)
    alpha = (excl + sa0 - sb0) / lbs
    beta = la / lbs
    lo = np.maximum(0.0, np.where(beta > 0, -alpha / np.maximum(beta, tiny), 0.0))
    hi = np.minimum(1.0, np.where(beta > 0, (1.0 - alpha) / np.maximum(beta, tiny), 1.0))
    w = r - alpha[..., None] * d2
    ee = d1 - beta[..., None] * d2
    ul = np.clip(-_dot(w, ee) / np.maximum(_dot(ee, ee), tiny), lo, np.maximum(lo, hi))
    vl = alpha + beta * ul
    u = np.where(bad, ul, u)
    v = np.where(bad, vl, v)
    infeasible = bad & ((lo > hi + 1e-12) | (sb0 + lb - sa0 < excl))
    diff = (p0 + d1 * u[..., None]) - (q0 + d2 * v[..., None])
    return np.where(infeasible, np.inf, np.sqrt(_dot(diff, diff))), u, v


def polyline_gap(nodes: np.ndarray, arclength: np.ndarray, length: float, radius: float, chunk: int = 64):
    """Signed gap (T,) of a dense centre line given as a polyline (T, N, 3) at arc fractions (N,), with the
    exact pi * diameter along-rope exclusion, and the arc fractions (T, 2) of its closest admissible pair.

    For a rod made of capsules along the polyline's segments (newton's rod, MuJoCo's flex) this is the
    simulator's own capsule surface gap: the dense ground truth of the event."""
    nodes = np.asarray(nodes, dtype=np.float64)
    if nodes.ndim == 2:
        g, s = polyline_gap(nodes[None], arclength, length, radius)
        return g[0], s[0]
    T = nodes.shape[0]
    s = np.asarray(arclength, dtype=np.float64) * length
    excl = 2.0 * np.pi * radius
    i, j = np.triu_indices(len(s) - 1, k=1)
    keep = (s[j + 1] - s[i]) > excl
    i, j = i[keep], j[keep]
    gap = np.full(T, np.inf)
    sab = np.full((T, 2), np.nan)
    if len(i) == 0:
        return gap, sab
    li, lj = s[i + 1] - s[i], s[j + 1] - s[j]
    for a in range(0, T, chunk):
        x = nodes[a:a + chunk]
        d, u, v = segment_distances_excluded(x[:, i], x[:, i + 1], x[:, j], x[:, j + 1], s[i], li, s[j], lj, excl)
        k = np.argmin(d, axis=1)
        r = np.arange(len(x))
        gap[a:a + chunk] = d[r, k] - 2.0 * radius
        sab[a:a + chunk, 0] = (s[i[k]] + u[r, k] * li[k]) / length
        sab[a:a + chunk, 1] = (s[j[k]] + v[r, k] * lj[k]) / length
    return gap, sab


# ----------------------------------------------------------------------------------------- reconstruction

def _spline_second_derivatives(X: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots of the natural cubic spline x(s) through X (T, M, 3)."""
    M = len(S)
    out = np.zeros_like(X)
    if M <= 2:
        return out
    h = np.diff(S)
    A = np.zeros((M - 2, M - 2))
    for k in range(M - 2):
        A[k, k] = (h[k] + h[k + 1]) / 3.0
        if k > 0:
            A[k, k - 1] = h[k] / 6.0
        if k < M - 3:
            A[k, k + 1] = h[k + 1] / 6.0
    slope = np.diff(X, axis=1) / h[None, :, None]
    out[:, 1:-1] = np.einsum("ij,tjk->tik", np.linalg.inv(A), slope[:, 1:] - slope[:, :-1])
    return out


def _sinc_inverse(rho):
    """x in [0, pi] with sin(x)/x = rho, for rho in [0, 1] (Newton from a safe start)."""
    rho = np.clip(rho, 0.0, 1.0)
    x = np.where(rho > 0.5, np.sqrt(np.maximum(6.0 * (1.0 - rho), 0.0)), np.pi * (1.0 - rho) / (1.0 + 0.25 * rho))
    x = np.clip(x, 1e-9, np.pi)
    for _ in range(30):
        f = np.sin(x) / x - rho
        df = (x * np.cos(x) - np.sin(x)) / (x * x)
        x = np.clip(x - f / np.where(np.abs(df) > 1e-12, df, -1e-12), 1e-9, np.pi)
    return x


BULGE_HOLD = 0.2  # the previous frame's bend side is kept while the spline's bulge is < this x the arc's


def arc_frames(X: np.ndarray, S: np.ndarray, continuity: bool = False):
    """Per interval and frame: the circular arc of the interval's exact arc length through its two markers.

    Returns half turning angle (T, M-1), unit chord e and unit bend side n (T, M-1, 3). The side is where the
    natural cubic spline through all markers bulges; with `continuity` a frame whose spline barely bulges
    (less than BULGE_HOLD of the arc's own sagitta) keeps the previous frame's side (projected normal to the
    chord): the rope's bend cannot flip between frames while the interval stays bent, the spline's can."""
    T, _M, _ = X.shape
    a = np.diff(S)
    d = X[:, 1:] - X[:, :-1]
    c = np.linalg.norm(d, axis=-1)
    e = d / np.maximum(c, 1e-15)[..., None]
    mpp = _spline_second_derivatives(X, S)
    off = -(a[None, :, None] ** 2 / 16.0) * 0.5 * (mpp[:, :-1] + mpp[:, 1:])  # spline midpoint - chord midpoint
    off = off - _dot(off, e)[..., None] * e
    size = np.linalg.norm(off, axis=-1)
    half = _sinc_inverse(c / a[None, :])
    sagitta = 0.5 * a[None, :] / np.maximum(2 * half, 1e-12) * (1.0 - np.cos(half))
    ref = np.where(np.abs(e[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    alt = ref - _dot(ref, e)[..., None] * e
    alt /= np.maximum(np.linalg.norm(alt, axis=-1), 1e-15)[..., None]
    n = np.where((size > 1e-9)[..., None], off / np.maximum(size, 1e-15)[..., None], alt)
    if continuity and T > 1:
        weak = size < BULGE_HOLD * sagitta
        for t in range(1, T):
            w = weak[t]
            if not w.any():
                continue
            prev = n[t - 1, w] - _dot(n[t - 1, w], e[t, w])[..., None] * e[t, w]
            pn = np.linalg.norm(prev, axis=-1)
            ok = pn > 1e-6
            idx = np.flatnonzero(w)[ok]
            n[t, idx] = prev[ok] / pn[ok, None]
    return half, e, n


_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)
_GL_U = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W
_DH = np.stack([6 * _GL_U**2 - 6 * _GL_U, 3 * _GL_U**2 - 4 * _GL_U + 1, -6 * _GL_U**2 + 6 * _GL_U,
                3 * _GL_U**2 - 2 * _GL_U], 1)  # (q, 4) Hermite basis derivatives at the Gauss points


def _hermite_length(P0, P1, t0, t1, scale):
    """Length of the Hermite curves with end tangents scale * t0, scale * t1 (12-point Gauss)."""
    sc = scale[..., None, None]
    d = (_DH[:, 0, None] * P0[..., None, :] + _DH[:, 2, None] * P1[..., None, :]
         + sc * (_DH[:, 1, None] * t0[..., None, :] + _DH[:, 3, None] * t1[..., None, :]))
    return np.einsum("...q,q->...", np.linalg.norm(d, axis=-1), _GL_W)


def reconstruct(markers: np.ndarray, S: np.ndarray, n_sub: int, continuity: bool = False):
    """C1 arc-length-preserving rope through the markers, sampled n_sub sub-segments per interval.

    markers (T, M, 3) m; S (M,) marker positions along the rope in metres. Returns points
    (T, M-1, n_sub+1, 3), their along-rope positions in metres (T, M-1, n_sub+1), and the interval
    chord/arc ratios (T, M-1)."""
    X = np.asarray(markers, dtype=np.float64)
    T, M, _ = X.shape
    a = np.diff(S)
    half, e, n = arc_frames(X, S, continuity)
    ts = np.cos(half)[..., None] * e + np.sin(half)[..., None] * n  # arc tangent at its start
    te = np.cos(half)[..., None] * e - np.sin(half)[..., None] * n  # ... at its end
    tan = np.empty_like(X)
    tan[:, 0] = ts[:, 0]
    tan[:, -1] = te[:, -1]
    bis = te[:, :-1] + ts[:, 1:]
    nb = np.linalg.norm(bis, axis=-1, keepdims=True)
    tan[:, 1:-1] = np.where(nb > 1e-6, bis / np.maximum(nb, 1e-12), te[:, :-1])  # a full fold keeps one side
    P0, P1 = X[:, :-1], X[:, 1:]
    t0, t1 = tan[:, :-1], tan[:, 1:]
    chord = np.linalg.norm(P1 - P0, axis=-1)
    ratio = chord / a[None, :]
    target = np.maximum(a[None, :], chord)
    # L(mu) grows from the chord at mu = 0: bracket, then bisect (relative precision 2^-22 of the arc).
    lo = np.zeros((T, M - 1))
    hi = np.ones((T, M - 1))
    for _ in range(6):
        short = _hermite_length(P0, P1, t0, t1, hi * a[None, :]) < target
        if not np.any(short):
            break
        lo = np.where(short, hi, lo)
        hi = np.where(short, hi * 2.0, hi)
    straight = ratio > 1.0 - 1e-9
    for _ in range(22):
        mid = 0.5 * (lo + hi)
        below = _hermite_length(P0, P1, t0, t1, mid * a[None, :]) < target
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    mu = np.where(straight, 0.0, 0.5 * (lo + hi))
    sc = (mu * a[None, :])[..., None]
    u = np.linspace(0.0, 1.0, n_sub + 1)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    pts = (h00 * P0[..., None, :] + h10 * (sc * t0)[..., None, :] + h01 * P1[..., None, :]
           + h11 * (sc * t1)[..., None, :])
    seg = np.linalg.norm(np.diff(pts, axis=2), axis=-1)
    cum = np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)
    frac = cum / np.maximum(cum[..., -1:], 1e-15)
    sarc = S[None, :-1, None] + frac * a[None, :, None]
    return pts, sarc, ratio


def interval_bounds(X: np.ndarray, S: np.ndarray, radius: float, excl: float, iv: np.ndarray, jv: np.ndarray,
                    chord_margin: float = 0.0):
    """Rigorous lower bound (T, P) of the gap between any rope shapes in intervals iv <= jv, and chord/arc.
    chord_margin: measured chords may be this much too long (marker noise); the capsules are widened to match, since
    a nearly straight interval's bulge grows fast as its chord shrinks.

    (1) Each interval's rope lies in the capsule of radius b = sqrt(arc^2 - chord^2)/2 around its chord, so
        gap >= dist(chord_I, chord_J) - b_I - b_J - 2r.
    (2) A contact between p in iv and q in jv with s_q - s_p >= excl closes a loop: the rope from marker iv to
        marker jv+1 is then at least excl - 2r longer than their distance, so
        gap >= |x_I - x_{jv+1}| - (S_{jv+1} - S_I - excl) - 2r.
    """
    a = np.diff(S)
    chord = np.linalg.norm(np.diff(X, axis=1), axis=-1)
    b = 0.5 * np.sqrt(np.maximum(a[None, :] ** 2 - np.maximum(chord - chord_margin, 0.0) ** 2, 0.0))
    d = segment_distances(X[:, iv], X[:, iv + 1], X[:, jv], X[:, jv + 1])[0]
    g1 = d - b[:, iv] - b[:, jv] - 2.0 * radius
    span = np.linalg.norm(X[:, jv + 1] - X[:, iv], axis=-1)
    g2 = span - (S[jv + 1] - S[iv] - excl) - 2.0 * radius
    return np.maximum(g1, g2), chord / a[None, :]


# ---------------------------------------------------------------------------------------- missing markers

FILL_RATIO = 1e-3  # a sample window this much smoother (4th difference) than the marker's motion around it ..
FILL_WINDOW = 30  # .. within this many frames either side, over 2 or more windows in a row ..
FILL_MOVE = 1e-3  # m .. while the marker moves at least this far: a gap the recording software filled


def software_filled(markers: np.ndarray, skip: tuple[int, ...] = (), resolution: float = 0.0) -> np.ndarray:
    """(T, M) bool: samples a tracker's gap filling wrote, which look observed. Filled samples beside the contact put
    it 45 ms late with high confidence (a probe of stop 47); read as missing they are bridged and flagged like any
    other gap. A line in time has no 2nd differences, which a marker on a rope moving under gravity always has (a
    tip in free flight: g dt^2); a cubic has no 4th differences, which a free-flying tip nearly shares (a parabola),
    so a cubic is told only where the file's numbers resolve it: its 4th differences below 1e-3 of the motion's
    around it and that level 3000 times the file's number `resolution` (m; float32 at 1 m: 1.2e-7; a float32 file
    at 200 Hz is below it, and its cubic fills go unseen). `skip`: markers that follow a polynomial by design
    (marker 0 on the hand, whose path is a Bezier curve)."""
    X = np.asarray(markers, np.float64)
    T, M, _ = X.shape
    out = np.zeros((T, M), bool)
    if T < 2 * FILL_WINDOW:
        return out
    stencils = {2: (np.array([1.0, -2.0, 1.0]), 3, 10.0, 1e3), 4: (np.array([1.0, -4.0, 6.0, -4.0, 1.0]), 2, 0.0, 3e3)}
    for m in range(M):
        if m in skip:
            continue
        for coef, least_windows, slack, above in stencils.values():
            w = len(coef)
            d = np.linalg.norm(sum(c * X[k:T - w + 1 + k, m] for k, c in enumerate(coef)), axis=1)
            finite = np.isfinite(d)
            padded = np.pad(d, FILL_WINDOW, constant_values=np.nan)
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN window: no level, nothing marked
                level = np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, 2 * FILL_WINDOW + 1), axis=1)
                smooth = finite & (level > above * resolution) & (d < FILL_RATIO * level + slack * resolution)
            for a, n in true_runs(smooth):  # windows a .. a+n-1 span samples a .. a+n+w-2, one polynomial
                end = a + n + w - 2
                if n >= least_windows and np.linalg.norm(X[end, m] - X[a, m]) >= FILL_MOVE:
                    out[a + 1:end, m] = True  # its ends are the observed samples the filling joined
    return out


def bridge_missing(markers: np.ndarray, dt: float, hand: np.ndarray | None = None, held_at_hand: bool = False):
    """Fill NaN marker samples by cubic interpolation in time (linear with fewer than 4 samples).

    Marker 0 takes the hand position where missing when `held_at_hand` (marker 0 sits on the hand). Samples
    before a marker's first or after its last observation hold the nearest one (no extrapolation).
    Returns (filled (T, M, 3), missing (T, M) bool: bridged samples, missing_fraction (M,))."""
    X = np.array(markers, dtype=np.float64)
    T, _M, _ = X.shape
    nan = ~np.all(np.isfinite(X), axis=-1)
    if held_at_hand and hand is not None:
        h = np.asarray(hand, dtype=np.float64)
        use = nan[:, 0] & np.all(np.isfinite(h), axis=-1)
        X[use, 0] = h[use]
        nan[use, 0] = False  # the hand IS marker 0 there: nothing was guessed
    frac = nan.mean(axis=0)
    if not nan.any():
        return X, nan, frac
    t = np.arange(T, dtype=np.float64) * dt
    from scipy.interpolate import CubicSpline

    for m in np.flatnonzero(nan.any(axis=0)):
        ok = ~nan[:, m]
        if ok.sum() < 2:
            X[:, m] = X[ok, m][0] if ok.any() else np.nan
            continue
        inside = (t >= t[ok][0]) & (t <= t[ok][-1]) & ~ok
        if ok.sum() >= 4:
            X[inside, m] = CubicSpline(t[ok], X[ok, m], axis=0)(t[inside])
        else:
            for k in range(3):
                X[inside, m, k] = np.interp(t[inside], t[ok], X[ok, m, k])
        first, last = np.flatnonzero(ok)[[0, -1]]
        X[:first, m] = X[first, m]
        X[last + 1:, m] = X[last, m]
    return X, nan, frac


def missing_runs(missing: np.ndarray) -> np.ndarray:
    """(T, M) length in frames of the run of missing samples each sample belongs to (0 where observed)."""
    T, M = missing.shape
    out = np.zeros((T, M), dtype=np.int64)
    for m in np.flatnonzero(missing.any(axis=0)):
        for s0, n in true_runs(missing[:, m]):
            out[s0:s0 + n, m] = n
    return out


def estimate_noise(X: np.ndarray, missing: np.ndarray | None = None) -> float:
    """Marker noise (m, 1-sigma per coordinate) from the third time difference: smooth motion contributes
    little to it at 100-250 Hz, white noise sqrt(20) sigma. Robust median; an upper estimate on clean data
    (it also measures jerk)."""
    X = np.array(X, dtype=np.float64)
    if missing is not None:
        X[missing] = np.nan
    d3 = np.diff(X, n=3, axis=0)
    d3 = d3[np.isfinite(d3)]
    if d3.size == 0:
        return 0.0
    return float(np.median(np.abs(d3)) / (0.6745 * np.sqrt(20.0)))


def _missing_spans(column: np.ndarray, w0: int, w1: int) -> list:
    """(first, last) frames of each run of missing samples in `column` (T,) that overlaps frames [w0, w1)."""
    return [(a, a + n - 1) for a, n in true_runs(column) if a < w1 and a + n > w0]


def _bridged_gap_reasons(time, X, S, missing, ratio, arc, radius, margin, k, s_contact, ends, w0, w1) -> list:
    """Sentences for bridged samples that may hide the first contact (empty when none do).

    The markers bounding the contact intervals are judged by the caller; a marker one interval further was
    missed there (markers 9-11 bridged for 195 ms over a contact at s=0.88, and the reconstruction, straight
    through the guessed markers, found a contact 41 ms later at s=0.73 with nothing flagged). Two signs:
    (1) near: a bridged sample within the event's window (frames w0..w1) whose marker sat within reach of the
    contact point: the rope on either side of the marker, one interval long, plus the two radii; (2) stretch:
    bridged samples before the end of that window whose interval chord exceeds its arc (beyond the slack observed
    samples get, and the noise): a rope cannot stretch, so the interpolated positions are wrong there."""
    sfrac = S / S[-1]
    contact = np.stack([np.array([np.interp(s_c * S[-1], S, X[k, :, c]) for c in range(3)]) for s_c in s_contact])
    reach = np.maximum(np.concatenate([[0.0], arc]), np.concatenate([arc, [0.0]])) + 2.0 * radius  # (M,)
    out = []
    near = []
    for m in np.flatnonzero(missing[w0:w1].any(axis=0)):
        if m in ends:
            continue
        f = w0 + np.flatnonzero(missing[w0:w1, m])
        dist = np.linalg.norm(X[f, m][:, None, :] - contact[None], axis=-1).min()
        if dist <= reach[m]:
            near.append((int(m), float(dist)))
    if near:
        ms = [m for m, _ in near]
        spans = [sp for m in ms for sp in _missing_spans(missing[:, m], w0, w1)]
        t0, t1 = time[min(a for a, _ in spans)], time[max(b for _, b in spans)]
        where = ", ".join(f"{sfrac[m]:.2f}" for m in ms)
        out.append(f"bridged markers near the contact: markers {ms} (s={where}) were "
                   f"missing from t={t0:.3f} to {t1:.3f} s, around the event, and were interpolated in time within "
                   f"{1000 * min(d for _, d in near):.0f} mm of the contact point: the contact may lie in the gap, "
                   "where the rope's shape is a guess")
    bridged = (missing[:, :-1] | missing[:, 1:])[:w1]  # (frames, M-1) intervals with an interpolated end
    slack = 1.0 + STRETCH_SLACK + margin / arc  # (M-1,)
    stretched = bridged & (ratio[:w1] > slack[None, :])
    if stretched.any():
        f, i = np.unravel_index(np.argmax(np.where(stretched, ratio[:w1], 0.0)), stretched.shape)
        spans = _missing_spans(missing[:, i] | missing[:, i + 1], f, f + 1)
        a, b = spans[0] if spans else (f, f)
        out.append(f"bridged markers stretch the rope: between markers {i} and {i + 1} (s={sfrac[i]:.2f}-"
                   f"{sfrac[i + 1]:.2f}) the interpolated markers lie {ratio[f, i]:.2f}x as far apart as the rope "
                   f"between them is long at t={time[f]:.3f} s (missing from t={time[a]:.3f} to {time[b]:.3f} s): "
                   "the interpolation is wrong there, and the contact may lie in the gap")
    return out


def _gaps_that_may_hide_a_contact(time, X, S, radius, excl, margin, level, missing: np.ndarray,
                                   untrusted: np.ndarray, k_end: int) -> str:
    """A phrase naming each marker gap longer than MAX_BRIDGE_TIME before frame k_end (the event, or the end) over
    which the hidden rope could have touched itself; empty when there are none. Shorter occlusions are bridged well
    enough (dev sets, 1-4 frames at 200 Hz).

    Whether a hidden stretch could touch is decided without bridged positions: over each long gap (and the frame on
    either side, up to k_end: a contact the gap hides begins by then) every marker bridged at any of those frames is
    dropped, and the stretch between the seen markers on either side lies in their spheroid (interval_bounds,
    rigorous for any rope of the known length, its capsules widened for the marker noise); the gap is harmless only
    if that bound keeps the merged interval clear of the rest of the rope (and of itself) by more than the contact
    level at every one of those frames. A hidden free end has nothing seen beyond it and always counts. A bound
    drawn through the bridged markers instead kept a hidden tip clear of a real contact (held-out MuJoCo gaps,
    README)."""
    if k_end <= 0 or not untrusted[:k_end].any():
        return ""
    M = X.shape[1]
    hiding = []
    for m in np.flatnonzero(untrusted[:k_end].any(axis=0)):
        for a, b in _missing_spans(untrusted[:, m], 0, k_end):
            f0, f1 = max(a - 1, 0), min(b + 2, k_end + 1, X.shape[0])
            dropped = missing[f0:f1].any(axis=0)
            if not (dropped[M - 1] or dropped[0]):
                keep = np.flatnonzero(~dropped)
                Sr = S[keep]
                merged = np.flatnonzero(np.diff(keep) > 1)  # reduced intervals that span a hidden marker
                iv, jv = np.triu_indices(len(keep) - 1, k=0)
                sel = ((Sr[jv + 1] - Sr[iv]) > excl) & (np.isin(iv, merged) | np.isin(jv, merged))
                if not sel.any():
                    continue
                glow, _ = interval_bounds(X[f0:f1][:, keep], Sr, radius, excl, iv[sel], jv[sel], margin)
                if (glow - margin).min() > level:
                    continue
            hiding.append(f"marker {int(m)} from t={time[a]:.3f} to {time[b]:.3f} s")
    if not hiding:
        return ""
    return (f"markers were missing for longer than {1000 * MAX_BRIDGE_TIME:.0f} ms while the rope hidden there could "
            f"have touched itself ({'; '.join(hiding)}) and were bridged in time")


# ---------------------------------------------------------------------------------------------- detection

def _crossing(gap: np.ndarray, start: int = 0):
    """(frame, fraction) of the first gap <= 0 at or after start: the crossing lies at frame - 1 + fraction."""
    hits = np.flatnonzero(gap[start:] <= 0.0)
    if len(hits) == 0:
        return None, None
    k = int(hits[0]) + start
    if k == 0:
        return 0, 1.0
    g0, g1 = float(gap[k - 1]), float(gap[k])
    frac = g0 / (g0 - g1) if g0 > g1 and np.isfinite(g0) else 1.0
    return k, float(np.clip(frac, 0.0, 1.0))


def _closing_at_the_end(gap: np.ndarray, dt: float, frames: int, level: float) -> tuple[float, float] | None:
    """(speed m/s, gap at the last frame) where the rope's least gap (measured from the contact level) closes over its
    last `frames` frames fast enough to touch within END_HORIZON after the recording's end; else None. Only a
    reconstructed gap (below NEAR_GAP) counts: above it the series is a lower bound."""
    n = min(int(frames), len(gap) - 1)
    if n < 1 or not gap[-1] + level < NEAR_GAP:
        return None
    speed = float(gap[-1 - n] - gap[-1]) / (n * dt)
    return (speed, float(gap[-1])) if speed > 0.0 and gap[-1] <= speed * END_HORIZON else None


def _pair_gaps(pts, sarc, frames, Ii, Jj, n_sub: int, radius: float, excl: float):
    """(gap m, s_a m, s_b m) per item: the least surface gap between interval Ii and interval Jj of the reconstructed
    rope (pts, sarc from reconstruct) at `frames`, farther than excl apart along it, and where it lies. In blocks of
    about 200 000 segment pairs: every pair of a long, thin rope at once had needed GiBs."""
    ia = np.repeat(np.arange(n_sub), n_sub)
    jb = np.tile(np.arange(n_sub), n_sub)
    gap, sa, sb = np.empty(len(frames)), np.empty(len(frames)), np.empty(len(frames))
    chunk = max(1, 200000 // (n_sub * n_sub))
    for c0 in range(0, len(frames), chunk):
        sl = slice(c0, c0 + chunk)
        f, I, J = frames[sl], Ii[sl], Jj[sl]
        A, B = pts[f, I], pts[f, J]
        sA, sB = sarc[f, I], sarc[f, J]
        d, u, v = segment_distances_excluded(
            A[:, ia], A[:, ia + 1], B[:, jb], B[:, jb + 1],
            sA[:, ia], sA[:, ia + 1] - sA[:, ia], sB[:, jb], sB[:, jb + 1] - sB[:, jb], excl)
        d = np.where((I == J)[:, None] & (jb <= ia)[None, :], np.inf, d)
        k = np.argmin(d, axis=1)
        r = np.arange(len(f))
        gap[sl] = d[r, k] - 2.0 * radius
        sa[sl] = sA[r, ia[k]] + u[r, k] * (sA[r, ia[k] + 1] - sA[r, ia[k]])
        sb[sl] = sB[r, jb[k]] + v[r, k] * (sB[r, jb[k] + 1] - sB[r, jb[k]])
    return gap, sa, sb


def _pair_closing_at_the_end(X, S, iv, jv, n_sub: int, radius: float, excl: float, level: float, dt: float,
                             frames: int, noise: float) -> tuple[float, float] | None:
    """(speed m/s, gap at the last frame, from the contact level) of an interval pair whose own reconstructed gap
    closes over the last `frames` frames by more than twice the noise margin, fast enough to touch within
    PAIR_END_HORIZON after the recording's end; else None. The least gap per frame (_closing_at_the_end) can belong to
    another pair: two points pi diameters apart along a straight stretch are 17 mm apart at 4 mm radius, and throws
    cut 5 ms before their contact read as "no self-contact, 16.9 mm clear" while the pair about to touch closed in (a
    third simulator's throw, 12 markers at 240 Hz; 138 of 368 cuts of the built-in throws 3-12 ms before their
    contact, at 12 and 17 markers; review of stop 55). Every pair is reconstructed at the two frames: the rigorous
    bounds of pairs far apart swing by 5-10 mm from frame to frame with 1 mm of marker noise."""
    T = len(X)
    n = min(int(frames), T - 1)
    if n < 1:
        return None
    pts, sarc, _ = reconstruct(X[[T - 1 - n, T - 1]], S, n_sub)
    P = len(iv)
    g = _pair_gaps(pts, sarc, np.repeat([0, 1], P), np.tile(iv, 2), np.tile(jv, 2), n_sub, radius, excl)[0] - level
    g0, g1 = g[:P], g[P:]
    speed = (g0 - g1) / (n * dt)
    closing = np.flatnonzero((g0 - g1 > 2.0 * noise) & (g1 <= speed * PAIR_END_HORIZON))
    if not len(closing):
        return None
    p = closing[np.argmin((g1 / speed)[closing])]
    return float(speed[p]), float(g1[p])


def _first_per_frame(tt: np.ndarray, value: np.ndarray, T: int):
    """Index into tt/value of each frame's smallest value, and the frames that have one."""
    order = np.lexsort((value, tt))
    first = np.ones(len(order), bool)
    first[1:] = tt[order][1:] != tt[order][:-1]
    return order[first]


TIP_SHAPE_FRACTION = 0.25  # of the unmarked tail's length: how far its straight continuation may miss its bent end


def _unmarked_tip_gap(X: np.ndarray, S: np.ndarray, length: float, radius: float, excl: float, n_sub: int,
                      frames: int) -> tuple[np.ndarray, float]:
    """(gap per frame, tail): the free end beyond the last marker (tail metres that no marker sees) continued
    straight along the reconstructed rope's end tangent, and its least surface gap to the rope farther than pi
    diameters along it, in the first `frames` frames (sampled points: the caller adds half a sub-segment of
    slack). A guess of where the end is, not a bound: the caller widens it by TIP_SHAPE_FRACTION of the tail."""
    tail = float(length - S[-1])
    step = SUBSEGMENT_PER_RADIUS * radius
    u = np.linspace(0.0, tail, int(np.ceil(tail / step)) + 1)[1:]
    gap = np.empty(frames)
    per_frame = len(u) * (len(S) - 1) * (n_sub + 1)
    chunk = max(1, 200000 // per_frame)  # point pairs per block, as the contact search takes them
    for f0 in range(0, frames, chunk):
        f1 = min(frames, f0 + chunk)
        pts, sarc, _ = reconstruct(X[f0:f1], S, n_sub)
        end = pts[:, -1, -1] - pts[:, -1, -2]
        end /= np.maximum(np.linalg.norm(end, axis=-1, keepdims=True), 1e-12)
        tip = X[f0:f1, -1][:, None, :] + u[None, :, None] * end[:, None, :]
        rope, rope_s = pts.reshape(f1 - f0, -1, 3), sarc.reshape(f1 - f0, -1)
        d = np.linalg.norm(tip[:, :, None, :] - rope[:, None, :, :], axis=-1)
        d = np.where((S[-1] + u)[None, :, None] - rope_s[:, None, :] > excl, d, np.inf)
        gap[f0:f1] = d.min(axis=(1, 2)) - 2.0 * radius
    return gap, tail


def detect(time, markers, marker_arclength, length, radius, missing=None, hand=None,
           time_tolerance: float = TIME_TOLERANCE, noise: float | None = None, continuity: bool = False,
           rules: tuple | None = None, contact_level: float = CONTACT_LEVEL, marker_offset: float = 0.0) -> Detection:
    """First self-contact of a rope from markers, with confidence and reasons.

    time (T,) s uniform; markers (T, M, 3) m, held end first (NaN where occluded: bridged here unless the
    caller bridged them and passes `missing`, the (T, M) mask of bridged samples); marker_arclength (M,) in
    [0, 1] increasing; length, radius m. noise: marker noise sigma (m), default estimated from the data; it
    widens the gap's uncertainty only. rules: which confidence rules apply (default all; for measurements).
    marker_offset: how far (m) the markers' centres may lie from the rope's centre line (markers on its surface);
    each piece's centre line is then that far from its markers, so it widens the gap's uncertainty by twice it.
    """
    time = np.asarray(time, dtype=np.float64)
    X = np.array(markers, dtype=np.float64)
    sfrac = np.asarray(marker_arclength, dtype=np.float64)
    T, M, _ = X.shape
    if time.shape != (T,) or sfrac.shape != (M,) or M < 2 or T < 2:
        raise ValueError(f"need time (T>=2,), markers (T, M>=2, 3), marker_arclength (M,); got {time.shape}, "
                         f"{X.shape}, {sfrac.shape}")
    rules = set(rules if rules is not None else RULES)
    dt = float((time[-1] - time[0]) / (T - 1))
    tol_frames = max(1, int(np.ceil(time_tolerance / dt - 1e-9)))
    S = sfrac * float(length)
    a = np.diff(S)
    excl = 2.0 * np.pi * float(radius)  # pi * diameter
    reasons: list[str] = []
    diag: dict = {"markers": M, "frames": T, "dt": dt, "exclusion_m": excl}

    def result(status, conf, event=None):
        return Detection(status, event, conf, reasons, diag)

    if missing is None:
        X, missing, frac = bridge_missing(X, dt, hand, held_at_hand=sfrac[0] == 0.0)
    else:
        missing = np.asarray(missing, bool)
        frac = missing.mean(axis=0)
    diag["missing_fraction"] = [round(float(f), 3) for f in frac]
    diag["bridged_samples"] = int(missing.sum())
    if np.any(frac > MAX_MISSING_FRACTION):
        bad = np.flatnonzero(frac > MAX_MISSING_FRACTION)
        reasons.append(f"markers {bad.tolist()} missing in more than {MAX_MISSING_FRACTION:.0%} of the frames: "
                       "the rope cannot be reconstructed")
        return result("unusable", "none")
    runs = missing_runs(missing)
    max_bridge = max(1, round(MAX_BRIDGE_TIME / dt))
    untrusted = runs > max_bridge

    sigma = estimate_noise(X, missing) if noise is None else float(noise)
    diag["noise_sigma_m"] = sigma
    # 3-sigma of the distance between two noisy points, one axis; and two pieces' markers each off their centre line
    margin = 3.0 * np.sqrt(2.0) * sigma + 2.0 * float(marker_offset)
    diag["marker_offset_m"] = float(marker_offset)

    # --- interval pairs that may touch at all, and the rigorous lower bound of their gap
    iv, jv = np.triu_indices(M - 1, k=0)
    keep = (S[jv + 1] - S[iv]) > excl
    iv, jv = iv[keep], jv[keep]
    if len(iv) == 0:
        reasons.append("the rope is shorter than pi diameters: it cannot touch itself")
        return result("no_contact", "none")
    glow, ratio = interval_bounds(X, S, radius, excl, iv, jv)
    glow = glow - margin
    glow_min = glow.min(axis=1)
    diag["max_chord_over_arc"] = float(ratio.max())

    # --- reconstruction and exact gap for interval pairs near contact
    n_sub = int(max(2, np.ceil(a.max() / (SUBSEGMENT_PER_RADIUS * radius))))
    near = glow <= NEAR_GAP
    near[:-1] |= glow[1:] <= NEAR_GAP  # the frame before too, for the interpolation
    frames = np.flatnonzero(near.any(axis=1))
    if len(frames):
        # only the frames that need it (continuity of the bend side needs every frame from the first one)
        sub = np.arange(max(0, frames[0] - 1), T) if continuity else frames
        pts_s, sarc_s, _ = reconstruct(X[sub], S, n_sub, continuity)
        pts = np.zeros((T,) + pts_s.shape[1:])
        sarc = np.zeros((T,) + sarc_s.shape[1:])
        pts[sub], sarc[sub] = pts_s, sarc_s
    tt, pp = np.nonzero(near)
    gap = np.full(T, np.inf)
    plaus = np.full(T, np.inf)
    best_s = np.full((T, 2), np.nan)
    best_pair = np.full(T, -1)
    unc_at = np.full(T, np.nan)
    plaus_pair = np.full(T, -1)
    plaus_s = np.full((T, 2), np.nan)
    if len(tt):
        b_half = 0.5 * np.sqrt(np.maximum(1.0 - np.minimum(ratio, 1.0) ** 2, 0.0)) * a[None, :]  # (T, M-1)
        # Uncertainty of the reconstructed gap: resolved-contact error + noise + a fraction of the spheroid
        # half-widths of the two intervals. For pairs inside one interval or two adjacent ones the gap
        # measures how tightly the rope folds there (one shape error, not two), and a fold that tight needs
        # more than a half turn inside one interval, so it counts only for curls.
        rho_min = np.minimum(ratio[tt, iv[pp]], ratio[tt, jv[pp]])
        short_range = (jv[pp] - iv[pp]) <= 1
        shape = SHAPE_ERROR_FRACTION * np.where(short_range, np.maximum(b_half[tt, iv[pp]], b_half[tt, jv[pp]]),
                                                b_half[tt, iv[pp]] + b_half[tt, jv[pp]])
        unc = GAP_ERROR + margin + np.where(short_range & (rho_min >= CURL_CHORD_RATIO), 0.0, shape)
        gmin, sa_best, sb_best = _pair_gaps(pts, sarc, tt, iv[pp], jv[pp], n_sub, float(radius), excl)
        sel = _first_per_frame(tt, gmin, T)
        gap[tt[sel]] = gmin[sel]
        best_s[tt[sel]] = np.stack([sa_best[sel], sb_best[sel]], 1)
        best_pair[tt[sel]] = pp[sel]
        unc_at[tt[sel]] = unc[sel]
        gpl = gmin - unc  # the gap that is still plausible: reconstructed minus its uncertainty
        sel2 = _first_per_frame(tt, gpl, T)
        plaus[tt[sel2]] = gpl[sel2]
        plaus_pair[tt[sel2]] = pp[sel2]
        plaus_s[tt[sel2]] = np.stack([sa_best[sel2], sb_best[sel2]], 1) / length
    # From here on gaps are measured from the contact level (surfaces closer than it touch); reports add it back.
    level = float(contact_level)
    gap, plaus, glow_min = gap - level, plaus - level, glow_min - level
    diag["contact_level_m"] = level
    # frames without near pairs: the reconstructed gap is above the rigorous bound (> NEAR_GAP)
    gap_series = np.where(np.isfinite(gap), gap, glow_min + margin)
    kmin = int(np.argmin(gap_series))
    diag.update(min_gap_m=float(gap_series[kmin] + level), min_gap_frame=kmin, min_gap_time=float(time[kmin]),
                gap_series=gap_series + level, plausible_gap_series=np.where(np.isfinite(plaus), plaus, gap_series),
                lower_bound_series=glow_min, subsegments_per_interval=n_sub, near_pairs_checked=len(tt))
    within_unc = np.isfinite(plaus) & (plaus <= 0.0)
    diag["summary"] = {
        "min_gap_m": float(gap_series[kmin] + level), "min_gap_time": float(time[kmin]),
        "contact_level_m": level,
        "frames_within_uncertainty": int(within_unc.sum()),
        "first_within_uncertainty_time": float(time[np.argmax(within_unc)]) if within_unc.any() else None,
        "frames_in_contact": int(np.sum(gap <= 0.0)),
        "noise_sigma_m": sigma, "max_chord_over_arc": float(ratio.max()), "min_chord_over_arc": float(ratio.min()),
        "bridged_samples": int(missing.sum()),
    }
    kp, fp = _crossing(glow_min)
    diag["earliest_possible_time"] = None if kp is None else float(time[max(kp - 1, 0)] + fp * dt * (kp > 0))

    k, frac = _crossing(gap)
    kq, fq = _crossing(plaus)
    diag["earliest_plausible_time"] = None if kq is None else float(time[max(kq - 1, 0)] + fq * dt * (kq > 0))
    # long gaps before the event: bridging through one can hide the first contact anywhere the hidden stretch could
    # reach (held-out MuJoCo throws: no-contact answers and a contact 30 ms late, all unflagged, with markers near the
    # real contact missing for 60-495 ms; README, "Events in motion capture")
    hidden = (_gaps_that_may_hide_a_contact(time, X, S, radius, excl, margin, level, missing, untrusted,
                                            T if k is None else k) if "occlusion" in rules else "")
    # the free end beyond the last marker is seen by no marker: where its straight continuation comes within its
    # uncertainty of the rope, or where more than a marker interval of it is unseen, a contact may hide
    tip_k, tail = None, float(length) * (1.0 - float(sfrac[-1]))
    upto = T if k is None else k
    if tail > radius and "tip" in rules and upto > 0:
        if tail > a.max():
            tip_k = 0
        else:
            tip_gap, tail = _unmarked_tip_gap(X, S, float(length), float(radius), excl, n_sub, upto)
            spacing = float(a.max()) / n_sub
            unc_tip = GAP_ERROR + margin + 0.5 * spacing + TIP_SHAPE_FRACTION * tail
            hit = np.flatnonzero(tip_gap - unc_tip - level <= 0.0)
            tip_k = int(hit[0]) if len(hit) else None
    diag["unmarked_tail_m"] = tail
    diag["unmarked_tip_reach_time"] = None if tip_k is None else float(time[tip_k])
    tip_reason = ""
    if tip_k is not None:
        tip_reason = f"the last {100 * tail:.1f} cm of the rope (from s={sfrac[-1]:.2f}) carry no marker, and " + (
            "that is more than a marker interval: where the free end is cannot be told" if tail > a.max() else
            f"continued straight they come within their uncertainty of the rope at t={time[tip_k]:.3f} s")
    if k is None:
        if tip_reason:
            reasons.append(f"no contact on the marked rope, but {tip_reason}: a contact of the free end cannot be "
                           "excluded")
            return result("unusable", "none")
        if kq is None and hidden:
            reasons.append(f"no contact on the reconstructed rope, but {hidden}: a contact may lie in the gap")
            return result("unusable", "none")
        closing = None
        if kq is None:
            closing = _closing_at_the_end(gap_series, dt, tol_frames, level)
            if closing is None:
                closing = _pair_closing_at_the_end(X, S, iv, jv, n_sub, float(radius), excl, level, dt, tol_frames,
                                                   margin)
        if closing is not None:
            reasons.append(f"no contact before the recording ends, but it ends while the rope closes in (gap "
                           f"{1000 * (closing[1] + level):.1f} mm at its last frame, t={time[-1]:.3f} s, closing "
                           f"at {closing[0]:.2f} m/s: at that speed it touches {1000 * closing[1] / closing[0]:.0f} "
                           "ms after the end): a contact just after its end cannot be excluded; give the recording "
                           "through the throw")
            return result("unusable", "none")
        if kq is None:
            reasons.append(f"no self-contact: the reconstructed rope stays {1000 * (gap_series[kmin] + level):.1f} mm "
                           f"clear (closest at t={time[kmin]:.3f} s), more than its uncertainty")
            return result("no_contact", "none")
        reasons.append(f"no contact on the reconstructed rope, but it comes within its uncertainty of one (gap "
                       f"{1000 * (gap_series[kq] + level):.1f} mm at t={time[kq]:.3f} s between s={plaus_s[kq, 0]:.2f} "
                       f"and s={plaus_s[kq, 1]:.2f}): a contact cannot be excluded")
        return result("unusable", "none")
    if k == 0:
        reasons.append("the reconstructed rope is in contact from the first frame: no first-contact time")
        return result("unusable", "none")
    t_event = float(time[k - 1] + frac * dt)
    sa, sb = float(best_s[k, 0] / length), float(best_s[k, 1] / length)
    Ie, Je = int(iv[best_pair[k]]), int(jv[best_pair[k]])
    diag.update(event_frame=k, event_intervals=(Ie, Je), gap_before=float(gap_series[k - 1] + level),
                gap_at=float(gap[k] + level),
                gap_uncertainty_m=float(unc_at[k]), closing_speed_mps=float((gap_series[k - 1] - gap[k]) / dt))
    low = []

    # earlier near-contact / slow approach: the plausible-contact episode that leads into the contact
    j = k
    while j > 0 and plaus[j - 1] <= 0.0:
        j -= 1
    if j > 0 and np.isfinite(plaus[j - 1]) and plaus[j - 1] > plaus[j]:
        t_ep = float(time[j - 1] + dt * plaus[j - 1] / (plaus[j - 1] - plaus[j]))
    else:
        t_ep = float(time[j])
    diag["approach_episode_start_time"] = t_ep
    earlier = np.flatnonzero((plaus[:j] <= 0.0) & (time[:j] < t_event - time_tolerance))
    diag["earlier_near_contact_time"] = float(time[earlier[0]]) if len(earlier) else None
    if len(earlier) and "earlier" in rules:
        q = int(earlier[0])
        pq = int(plaus_pair[q])
        reasons.append(
            f"earlier near-contact: at t={time[q]:.3f} s ({1000 * (t_event - time[q]):.0f} ms before the detected "
            f"contact) the reconstructed rope came within its uncertainty of touching (gap "
            f"{1000 * (gap_series[q] + level):.1f} mm, uncertainty {1000 * (gap_series[q] - plaus[q]):.1f} mm) between "
            f"s={plaus_s[q, 0]:.2f} (chord/arc {ratio[q, iv[pq]]:.2f}) and s={plaus_s[q, 1]:.2f} (chord/arc "
            f"{ratio[q, jv[pq]]:.2f}); it may have been the first contact")
        low.append("earlier")
    diag["slow_approach_s"] = t_event - t_ep
    if t_event - t_ep > time_tolerance and "slow" in rules:
        reasons.append(
            f"slow approach: the gap is within its uncertainty of touching from t={t_ep:.3f} s, "
            f"{1000 * (t_event - t_ep):.0f} ms before the detected contact, so the contact time is uncertain by "
            f"more than {1000 * time_tolerance:.0f} ms")
        low.append("slow")
    elif j == 0 and "start" in rules:
        # the near-contact was there before the recording began: the approach, which the rules above judge, is not
        # in it (a rope released folded or coiled read a contact 72-182 ms early with confidence; a probe of stop 59)
        reasons.append(f"the gap is within its uncertainty of touching from the recording's first frame (t="
                       f"{time[0]:.3f} s): the approach began before the recording, so whether the pieces touched "
                       "then or only came near cannot be told")
        low.append("start")

    # after the touch: pieces that touched stay together (rest, slide) for a while in both fine simulators
    # (newton and MuJoCo dev sets: every right event at 8-24 markers is within its uncertainty one frame
    # later); a reconstruction that overlaps them for one frame only, or only within its uncertainty and
    # then parts, is as consistent with a near miss (the "gap that only just closes").
    hold = max(1, round(HOLD_TIME / dt))
    after = gap_series[k + 1:k + 1 + hold]
    unc_after = unc_at[k + 1:k + 1 + hold]
    unc_after = np.where(np.isfinite(unc_after), unc_after, GAP_ERROR + margin)
    within = after <= unc_after
    depth = min([float(gap[k])] + [float(g) for g, w in zip(after, within) if w])
    diag.update(gap_after_m=[float(g + level) for g in after], held=[bool(w) for w in within], depth_m=depth + level)
    if len(after) and not within[0] and "parted" in rules:
        reasons.append(f"parted at once: the reconstructed pieces overlap at frame {k} and are "
                       f"{1000 * (after[0] + level):.1f} mm apart one frame later (uncertainty "
                       f"{1000 * unc_after[0]:.1f} mm): "
                       "touching pieces stay together for a while, a reconstruction error does not")
        low.append("parted")
    elif len(after) and not within.all() and depth > -unc_at[k] and "graze" in rules:
        reasons.append(f"gap only just closes: the reconstructed pieces come {1000 * -depth:.1f} mm inside the "
                       f"contact level, less than the gap's uncertainty {1000 * unc_at[k]:.1f} mm, and part within "
                       f"{1000 * hold * dt:.0f} ms: as consistent with a near miss as with a touch")
        low.append("graze")
    if Je - Ie <= 1 and "fold" in rules:
        reasons.append(f"tight fold: the contact closes a loop within two marker intervals (markers {Ie}-{Je + 1}, "
                       f"s={sfrac[Ie]:.2f}-{sfrac[Je + 1]:.2f}): the markers do not pin the shape of so short a loop")
        low.append("fold")

    if Je == Ie and "loop" in rules:
        reasons.append(f"loop inside one marker interval: both contact points lie between markers {Ie} and {Ie + 1} "
                       f"(s={sfrac[Ie]:.2f}-{sfrac[Ie + 1]:.2f}), so the loop is the reconstruction's guess")
        low.append("loop")
    r_ev = np.minimum(ratio[k, [Ie, Je]], ratio[k - 1, [Ie, Je]])
    diag["event_chord_over_arc"] = [float(x) for x in r_ev]
    curl = [(i, r) for i, r in zip((Ie, Je), r_ev) if r < CURL_CHORD_RATIO]
    if curl and "curl" in rules:
        i, r = curl[0]
        reasons.append(f"unresolved curl: the rope between markers {i} and {i + 1} (s={sfrac[i]:.2f}-"
                       f"{sfrac[i + 1]:.2f}) at the contact has chord/arc {r:.2f} < {CURL_CHORD_RATIO:.2f} (more than "
                       f"a half turn between two markers): its shape is a guess")
        low.append("curl")

    # how long after the rope's fastest motion (a diagnostic: on the dev sets right events came up to 0.75 s
    # after it and late wrong ones 0.2 s after, so it flags nothing)
    speed = np.linalg.norm(np.diff(X, axis=0), axis=-1).max(axis=1) / dt
    k_peak = int(np.argmax(speed))
    diag["fastest_motion_time"] = float(time[k_peak] + 0.5 * dt)
    diag["after_fastest_s"] = t_event - diag["fastest_motion_time"]
    if missing.any() and "occlusion" in rules:
        # the samples that shape the two contact pieces around the event: the markers bounding their intervals,
        # from the tolerance before the contact to the end of the hold window
        w0, w1 = max(0, k - tol_frames), min(T, k + max(1, round(HOLD_TIME / dt)) + 1)
        ends = sorted({Ie, Ie + 1, Je, Je + 1})
        if untrusted[w0:w1][:, ends].any():
            ms = [m for m in ends if untrusted[w0:w1, m].any()]
            reasons.append(f"markers {ms} bounding the contact were missing for longer than "
                           f"{1000 * MAX_BRIDGE_TIME:.0f} ms around the event: its time cannot be trusted")
            diag["event_candidate_time"] = t_event
            return result("unusable", "none")
        if missing[w0:w1][:, ends].any():
            ms = [m for m in ends if missing[w0:w1, m].any()]
            reasons.append(f"markers {ms} bounding the contact were occluded within {1000 * time_tolerance:.0f} ms "
                           "of the event and bridged by interpolation in time")
            low.append("occlusion")
        gap_reasons = _bridged_gap_reasons(time, X, S, missing, ratio, a, radius, margin, k, (sa, sb), ends, w0, w1)
        if hidden:
            gap_reasons.append(f"{hidden} (a gap starting before the event): an earlier first contact may lie in it, "
                               "where the rope's shape is a guess")
        diag["bridged_gap_reasons"] = len(gap_reasons)
        if gap_reasons:
            reasons.extend(gap_reasons)
            if "occlusion" not in low:
                low.append("occlusion")
    # frames cut out with the clock made uniform again leave only a jump of the markers, and every time after it is
    # early by the frames lost
    kj, jump = largest_jump(np.linalg.norm(np.diff(X[:k + 1], axis=0), axis=2).max(axis=1))
    diag["largest_jump_over_neighbourhood"] = jump
    if jump > MAX_MARKER_JUMP and "jump" in rules:
        reasons.append(f"the markers jump {jump:.0f} x their frame-to-frame step around there between "
                       f"t={time[kj]:.3f} and {time[kj + 1]:.3f} s, before the contact: frames missing from the "
                       "recording? then the contact time is early by the frames lost")
        low.append("jump")
    if hand is not None and "jump" in rules:
        hd, ratio_h = largest_doublet(np.asarray(hand, dtype=np.float64)[:k + 2])  # the interval into frame k too
        diag["hand_doublet_over_neighbourhood"] = ratio_h
        if ratio_h > MAX_HAND_DOUBLET:
            reasons.append(f"the hand's path kinks forth and back ({ratio_h:.0f} x its usual second difference) "
                           f"between t={time[hd + 1]:.3f} and {time[hd + 2]:.3f} s, up to the contact: frames "
                           "missing from the recording? then the contact time is early by the frames lost")
            if "jump" not in low:
                low.append("jump")
    if hand is not None and "repeat" in rules:
        repeated = _repeated_moving_frames(X[:k + 1], np.asarray(hand, dtype=np.float64)[:k + 1])
        diag["repeated_frames"] = len(repeated)
        if repeated:
            reasons.append(f"{len(repeated)} frame(s) repeat the one before exactly while the hand moves (first at "
                           f"t={time[repeated[0]]:.3f} s), before the contact: a tracker holding its last value? then "
                           "the contact time is late by the frames repeated")
            low.append("repeat")
    if tip_k is not None and time[tip_k] < t_event - time_tolerance:
        reasons.append(f"{tip_reason} ({1000 * (t_event - time[tip_k]):.0f} ms before the detected contact): the "
                       "free end may have touched first")
        low.append("tip")
    diag["rules_fired"] = low
    conf = "low" if low else "high"
    ev = CollisionEvent(k, t_event, sa, sb, float(gap_series[k - 1] + level), float(gap[k] + level), "detected", conf,
                        tuple(reasons))
    return result("contact", conf, ev)


def _repeated_moving_frames(markers: np.ndarray, hand: np.ndarray, moving: float = 1e-3) -> list[int]:
    """Frames whose markers and hand equal the frame before's exactly, in runs over which the hand moves more than
    `moving` (m): no tracker measures a moving rope twice to the bit, a hold-last-value fill does (and delays every
    later frame); a rope and hand at rest may repeat."""
    both = np.concatenate([markers.reshape(len(markers), -1), hand], axis=1)
    return [j for first, n, moved, _ in repeated_runs(both, hand) if moved > moving for j in range(first, first + n)]


# ------------------------------------------------------------------------------ the event a reference uses

@dataclass
class Critical:
    """The critical moment of one reference: the user's annotation when the file has one (it overrides the
    detection), else the detected first contact; `event` is None when there is no usable one (`problem` says
    why, in one line)."""

    event: CollisionEvent | None
    detection: Detection
    annotated: bool
    warnings: list
    problem: str | None = None
    field: str = "markers"  # the file's field the problem is about

    def as_dict(self) -> dict:
        e, d = self.event, self.detection
        det = None
        if d.event is not None:
            det = {"time": d.event.time, "s_a": d.event.s_a, "s_b": d.event.s_b, "frame": d.event.index}
        return {
            "critical": None if e is None else {"time": e.time, "s_a": e.s_a, "s_b": e.s_b, "frame": e.index,
                                                "source": e.source, "confidence": e.confidence},
            "detected": det, "detection_status": d.status, "confidence": d.confidence,
            "reasons": list(d.reasons), "annotation_overrides": self.annotated,
            "gap_summary": d.diagnostics.get("summary", {}), "warnings": list(self.warnings),
            "usable": e is not None, "problem": self.problem,
        }


def _content_key(ref) -> str:
    import hashlib

    offset = float(getattr(ref, "marker_offset", 0.0))
    h = hashlib.sha1((f"events-v{VERSION} L={ref.length!r} r={ref.radius!r}"
                      + (f" offset={offset!r}" if offset else "")).encode())  # keys without an offset as before
    for a in (ref.time, ref.markers, ref.marker_arclength, getattr(ref, "missing", None), ref.hand):
        if a is not None:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype, a.shape)).encode())
            h.update(a.tobytes())
    return h.hexdigest()


def _cache_file(key: str):
    import os
    from pathlib import Path

    if os.environ.get("WRENORM_EVENT_CACHE", "1") == "0":
        return None
    root = Path(os.environ.get("WRENORM_CACHE") or Path.home() / ".cache" / "wrenorm")
    return root / "events" / f"{key}.json"


def _to_json(det: Detection) -> dict:
    keep = ("summary", "event_intervals", "gap_before", "gap_at", "gap_uncertainty_m", "closing_speed_mps",
            "earliest_plausible_time", "earliest_possible_time", "approach_episode_start_time", "rules_fired",
            "fastest_motion_time", "after_fastest_s", "event_chord_over_arc", "depth_m", "noise_sigma_m",
            "largest_jump_over_neighbourhood", "hand_doublet_over_neighbourhood", "unmarked_tail_m",
            "unmarked_tip_reach_time", "repeated_frames", "marker_offset_m")
    d = {k: det.diagnostics.get(k) for k in keep if k in det.diagnostics}
    e = det.event
    return {"status": det.status, "confidence": det.confidence, "reasons": list(det.reasons),
            "event": None if e is None else [e.index, e.time, e.s_a, e.s_b, e.gap_before, e.gap_at],
            "diagnostics": d}


def _from_json(d: dict) -> Detection:
    e = d["event"]
    ev = None if e is None else CollisionEvent(int(e[0]), *map(float, e[1:]), "detected", d["confidence"],
                                                tuple(d["reasons"]))
    return Detection(d["status"], ev, d["confidence"], list(d["reasons"]), dict(d["diagnostics"]))


def detect_reference(ref, use_cache: bool = True) -> Detection:
    """detect() for a loaded reference, memoised on the object and cached on disk by content (the detector
    takes 0.1-1 s per file; a fit reads the same files again and again)."""
    import json

    from wrenorm.results import jsonable, stored_digest, write_atomic

    cached = getattr(ref, "_detection", None)
    if cached is not None:
        return cached
    key = _content_key(ref)
    path = _cache_file(key) if use_cache else None
    det = None
    if path is not None and path.exists():
        try:
            saved = json.loads(path.read_text())
            body = saved["detection"]
            # a file renamed, cut or edited since it was written is not this recording's answer: detect again
            if saved["key"] == key and saved["digest"] == stored_digest(body):
                det = _from_json(body)
        except (OSError, ValueError, KeyError, TypeError, IndexError):
            det = None
    if det is None:
        det = detect(ref.time, ref.markers, ref.marker_arclength, ref.length, ref.radius,
                     missing=getattr(ref, "missing", None), hand=ref.hand,
                     marker_offset=float(getattr(ref, "marker_offset", 0.0)))
        if path is not None:
            try:
                body = jsonable(_to_json(det))
                write_atomic(path, json.dumps({"key": key, "digest": stored_digest(body), "detection": body}))
            except OSError:  # a read-only cache only costs time
                pass
    try:
        ref._detection = det
    except AttributeError:
        pass
    return det


def closest_pair_at(ref, t: float):
    """Closest admissible pair (gap m, s_a, s_b) of the reconstructed rope at time t (markers interpolated
    linearly between the two frames around t)."""
    time = ref.time
    k = int(np.clip(np.searchsorted(time, t, side="left"), 1, len(time) - 1))
    w = (t - time[k - 1]) / (time[k] - time[k - 1])
    X = (1 - w) * ref.markers[k - 1] + w * ref.markers[k]
    S = np.asarray(ref.marker_arclength, np.float64) * ref.length
    n_sub = int(max(2, np.ceil(np.diff(S).max() / (SUBSEGMENT_PER_RADIUS * ref.radius))))
    pts, sarc, _ = reconstruct(X[None], S, n_sub)
    P = pts[0].reshape(-1, n_sub + 1, 3)
    nodes = np.concatenate([P[:, :-1].reshape(-1, 3), P[-1, -1:]], 0)
    arc = np.concatenate([sarc[0, :, :-1].reshape(-1), sarc[0, -1, -1:]]) / ref.length
    gap, sab = polyline_gap(nodes, arc, ref.length, ref.radius)
    return float(gap), float(sab[0]), float(sab[1])


REST_SPEED = 0.05  # m/s: every coordinate of the markers' first step below this, the rope starts at rest ..
REST_TILT_DEG = 2.0  # .. and a rope hanging at rest further off -z than this says the frame is tilted
REST_FIT_SPEED = 0.1  # m/s RMS: a rope whose one step is within its noise still moves when its fitted start velocity
REST_FIT_SIGMAS = 3.0  # (start_velocity) exceeds this speed and this many times its noise (3D RMS)
START_NOISE_SHARE = 0.1  # a moving start whose velocity noise is more than this share of its speed is said: 0.19 m/s
# RMS on 0.96 (1000 Hz markers with 0.5 mm of noise, from 0.15 s into a throw) made the measured chain miss its contact
# (error 5.1 against 0.45 from the clean markers; with the clean velocity 0.48; review of stop 54)


GRAVITY = 9.81  # m/s^2
GRAVITY_WINDOW = 0.01  # s: the centre of mass's acceleration is a second difference over this step
GRAVITY_MIN_SPREAD = 0.15  # the held end's link must turn enough over the clip (smallest eigenvalue of the mean
# projector across it) for gravity to be told from the pull along it: the built-in throws 0.23-0.42, 60 frames cut
# from mid-throw 0.07
GRAVITY_MAGNITUDE = (0.5, 1.5)  # x GRAVITY: an estimate outside says the motion does not determine it
GRAVITY_MIN_DURATION = 0.4  # s: shorter clips do not determine it. Over every window of the 64 built-in and test
# throws (newton and MuJoCo, every variant, level frames), the estimate's angle off -z: whole throws at most 2.8 deg;
# 0.6 s windows 99th percentile 8.1, at most 10.8; 0.4 s 11.4 and 27.4; 0.2 s 35.8 and 44.2; 0.15 s up to 54
TILT_WARN_DEG = 15.0  # estimated from the motion, gravity further off -z than this is said (0.4 s windows of level
# frames: 0.5 % of them); a rope that starts at rest is judged by the direction it hangs in instead (REST_TILT_DEG)


@dataclass
class GravityEstimate:
    vector: np.ndarray  # (3,) m/s^2 in the file's frame
    determined: bool  # a clip long enough, the held end's link turned enough, the magnitude a gravity's

    @property
    def degrees_off_down(self) -> float:
        n = float(np.linalg.norm(self.vector))
        return float(np.degrees(np.arccos(np.clip(-self.vector[2] / n, -1.0, 1.0)))) if n > 0 else float("nan")


def gravity_from_motion(time, markers, hand, arclength) -> GravityEstimate:
    """Gravity in the file's frame, from the rope's own motion: its centre of mass accelerates as g plus the hand's
    pull over its mass, and a rope pulls along its held end's link, so across the frames the part of the acceleration
    across that link is g's part across it (least squares over the frames, where the link turns enough). Unlike the
    direction the rope hangs in, this holds for a clip cut from mid-throw: 100-250 frames of a throw in a Y-up frame
    had been fitted with gravity along the rope's side, and 60 frames in the right frame refused (review of stop 54).
    Air drag and the bending moment at the hand are left out (the built-in throws: at most 2.8 deg, |g| 8.1-9.5)."""
    time = np.asarray(time, np.float64)
    X = np.asarray(markers, np.float64)
    hand = np.asarray(hand, np.float64)
    s = np.asarray(arclength, np.float64)
    weight = np.gradient(s) if len(s) > 2 else np.full(len(s), 0.5)
    seen = np.isfinite(X).all(-1)
    w = np.where(seen, weight, 0.0)
    com = np.einsum("tmk,tm->tk", np.nan_to_num(X), w) / np.maximum(w.sum(1), 1e-12)[:, None]
    com[w.sum(1) < 0.9 * weight.sum()] = np.nan  # a frame missing a tenth of the rope is no centre of mass
    h = max(1, int(round(GRAVITY_WINDOW / float(time[1] - time[0])))) if len(time) > 1 else 1
    if len(time) <= 2 * h or time[-1] - time[0] < GRAVITY_MIN_DURATION:
        return GravityEstimate(np.full(3, np.nan), False)
    step = time[2 * h:] - time[:-2 * h]
    accel = (com[2 * h:] - 2.0 * com[h:-h] + com[:-2 * h]) / (0.5 * step[:, None]) ** 2
    link = X[h:-h, 1 if s[0] == 0.0 and X.shape[1] > 1 else 0] - hand[h:-h]
    link /= np.linalg.norm(link, axis=1, keepdims=True)
    ok = np.isfinite(accel).all(1) & np.isfinite(link).all(1)
    if ok.sum() < 3:
        return GravityEstimate(np.full(3, np.nan), False)
    across = np.eye(3)[None] - link[ok, :, None] * link[ok, None, :]
    A = across.sum(0)
    g = np.linalg.solve(A, np.einsum("tij,tj->i", across, accel[ok]))
    spread = float(np.linalg.eigvalsh(A / ok.sum()).min())
    lo, hi = GRAVITY_MAGNITUDE
    return GravityEstimate(g, spread >= GRAVITY_MIN_SPREAD and lo * GRAVITY <= np.linalg.norm(g) <= hi * GRAVITY)


START_WINDOW_MAX = 0.1  # s: the longest window the chain's start velocity is fitted over
START_WINDOW_GROWTH = 1.25  # each window candidate this much longer than the last
START_ICI = 2.5  # a longer window is kept while every marker's start velocity stays within this many noise sigmas
# (3D, of the shorter window's estimate) of every shorter window's. Noise alone stops the growth early now and then
# (uniform motion, 0.5 mm of noise, 17 markers: 18 % of draws at 1000 Hz, 8 % at 250 Hz; review of stop 55): a shorter
# window than the motion allows, so more noise, never more bias
START_MIN_SAMPLES = 4  # seen samples a marker needs in a window for its quadratic (3 coefficients and one more)
HAND_STILL_M = 0.002  # m: the hand within this of where it started, or HAND_STILL_SIGMAS of its noise if more, is still
HAND_STILL_SIGMAS = 5.0
HAND_STILL_MIN_S = 0.02  # .. for at least this long: a hand drifting 0.3 m/s stays within 2.5 mm for 8 ms


def _start_slopes(time, X, seen, m: int, terms: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(markers, 3) velocity at time[0] of each marker's least-squares polynomial (`terms` coefficients: 3 a
    quadratic, 2 a line) through its seen samples in frames 0..m, and (markers,) its noise per unit marker sigma (one
    coordinate); NaN for a marker seen in fewer than START_MIN_SAMPLES of them."""
    T = np.asarray(time[:m + 1], np.float64) - float(time[0])
    scale = T[-1]
    A = np.vander(T / scale, terms, increasing=True)  # (F, terms)
    w = np.asarray(seen[:m + 1], np.float64)  # (F, M)
    N = np.einsum("fm,fa,fb->mab", w, A, A)
    ok = w.sum(0) >= START_MIN_SAMPLES
    N[~ok] = np.eye(terms)
    inv = np.linalg.inv(N)
    coef = np.einsum("mab,fm,fb,fmk->mak", inv, w, A, np.nan_to_num(np.asarray(X[:m + 1], np.float64)))
    slope = np.where(ok[:, None], coef[:, 1] / scale, np.nan)
    return slope, np.where(ok, np.sqrt(np.maximum(inv[:, 1, 1], 0.0)) / scale, np.nan)


def start_velocity(ref) -> tuple[np.ndarray, float]:
    """(markers, 3) the markers' velocity at the first frame, where the chain starts, and its noise (m/s RMS, 3D).

    A quadratic in time over the first frames, whose window is chosen from the data (intersection of confidence
    intervals): it grows while the estimate stays within the noise of every shorter window's, so a smooth start gets
    a long window (little noise) and a sharply accelerating one a short window (little bias). A velocity at the first
    frame, not a slope about a window's middle: one frame difference at 250 Hz sat 2 ms late. Samples bridged over a
    marker's gap are left out of its fit and of the window's test (one marker held 8 frames at its first sighting had
    kept every marker at the shortest window). Where too few frames allow a quadratic, the frame difference
    (observable.marker_velocity) as before, also for a marker seen too rarely. It matters where the rope moves in the
    first frame: from 0.1-0.2 s into a throw at 250 Hz with 0.5 mm of noise, every one of 63 clips of seven ropes had
    started the chain from a velocity 0.3 m/s RMS off and missed its contact (review of stop 54)."""
    n = velocity_intervals(ref)
    time = np.asarray(ref.time, np.float64)
    dt = float(time[1] - time[0])
    m_max = min(int(np.floor(START_WINDOW_MAX / dt + 1e-6)), len(time) - 1)  # 25 Hz: 2.5 frame steps, not 2 or 3
    m = max(3, n)
    step = marker_velocity(ref, 0, n)
    if m > m_max:
        return step, float(np.sqrt(3.0) * first_velocity_noise(ref))
    missing = getattr(ref, "missing", None)
    seen = np.ones(np.shape(ref.markers)[:2], bool) if missing is None else ~np.asarray(missing, bool)
    sigma = estimate_noise(ref.markers[:20], None if missing is None else missing[:20])
    chosen = _start_slopes(time, ref.markers, seen, m)
    shorter = [chosen]
    while True:
        m_next = max(m + 1, int(round(m * START_WINDOW_GROWTH)))
        if m_next > m_max:
            break
        v, k = _start_slopes(time, ref.markers, seen, m_next)
        with np.errstate(invalid="ignore"):
            if any(np.any(np.linalg.norm(v - vs, axis=-1) > START_ICI * np.sqrt(3.0) * sigma * ks)
                   for vs, ks in shorter):
                break
        m, chosen = m_next, (v, k)
        shorter.append(chosen)
    velocity, k = chosen
    lost = ~np.isfinite(velocity).all(-1)
    velocity = np.where(lost[:, None], step, velocity)
    k = np.where(lost, first_velocity_noise(ref) / max(sigma, 1e-300), k)
    return velocity, float(np.sqrt(3.0) * sigma * np.sqrt(np.mean(k ** 2)))


def hand_still_frames(ref) -> int:
    """Frames from the first in which the hand stays where it started (the mean of its first three samples) within
    HAND_STILL_M, or HAND_STILL_SIGMAS of its noise where that is more."""
    hand = np.asarray(ref.hand, np.float64)
    if len(hand) < 4:
        return len(hand)
    off = np.linalg.norm(hand - hand[:3].mean(axis=0), axis=1)
    moved = np.flatnonzero(off > max(HAND_STILL_M, HAND_STILL_SIGMAS * estimate_noise(hand[:20, None])))
    return int(moved[0]) if moved.size else len(hand)


def first_velocity_noise(ref) -> float:
    """The noise (m/s, one coordinate) of the markers' first velocity (observable.marker_velocity over n + 1 frames,
    as the chain's start takes it): sqrt(2) sigma / dt for a frame difference."""
    missing = None if getattr(ref, "missing", None) is None else ref.missing[:20]
    n = velocity_intervals(ref)
    frames = np.arange(n + 1) - 0.5 * n
    return float(estimate_noise(ref.markers[:20], missing) / (ref.dt * np.sqrt(np.sum(frames ** 2))))


def still_within_noise(ref) -> bool:
    """Whether the markers' first velocity is within their noise: RMS below 1.5x the speed pure noise gives (over 3 M
    samples its spread is about a tenth of it); a rope moving faster than about 1.1x that keeps its velocity. 0.5 mm
    of noise read 0.23-0.48 m/s on a rope at rest (a probe of stop 46). Judged by one step, not by start_velocity's
    longer fit: that fit's small noise let a rope just starting to swing read as moving (0.05 m/s RMS, its quadratic's
    bias over the window), and the chain then started from that bias (stop 55)."""
    velocity = marker_velocity(ref, 0, velocity_intervals(ref))
    return bool(np.sqrt(np.mean(velocity ** 2)) < 1.5 * first_velocity_noise(ref))


def first_step_speed(ref) -> float:
    """The fastest coordinate of the markers' first velocity (m/s; observable.marker_velocity)."""
    return float(np.nanmax(np.abs(marker_velocity(ref, 0, velocity_intervals(ref)))))


def starts_at_rest(ref) -> bool:
    """Whether the rope starts at rest: its first step under REST_SPEED (a forward difference of a rope released at
    rest reads g dt, not 0; every built-in path starts so) or within the markers' noise, and then the velocity fitted
    over the first frames (start_velocity) not clearly moving. One step's noise hides a slow rope (0.5 mm at 250 Hz:
    0.18 m/s a coordinate), which the longer fit resolves; a fit just above its noise is the quadratic's bias on a rope
    starting to swing (0.025-0.05 m/s), so both a speed and a multiple of the noise must be exceeded. The chain then
    starts at rest (the rope's prepare_case), and a rope so at rest hangs along gravity (rest_tilt)."""
    if first_step_speed(ref) < REST_SPEED:
        return True
    if not still_within_noise(ref):
        return False
    still = still_span_speed(ref)
    if still is not None and still[0] <= max(REST_FIT_SPEED, REST_FIT_SIGMAS * still[1]):
        return True
    velocity, noise = start_velocity(ref)
    return float(np.sqrt(np.mean(np.sum(velocity ** 2, axis=-1)))) <= max(REST_FIT_SPEED, REST_FIT_SIGMAS * noise)


def still_span_speed(ref) -> tuple[float, float] | None:
    """(the markers' mean velocity, RMS 3D, over the frames in which the hand holds its start, up to START_WINDOW_MAX,
    and its noise), or None where the hand moves within HAND_STILL_MIN_S. Recordings start with the hand still before
    the throw: there the rope rests or swings, and a straight-line slope over that span says the rope rests with little
    noise, where start_velocity's quadratic runs into the throw (a rope hanging still read as moving 0.2-0.6 m/s, 4 of
    its sigmas: 75 of 210 files from a probe's own rope simulator, stop 59) and a quadratic held to the span is too
    noisy to see a swing under 1 m/s (the review of that change). It only ever says "at rest": a mean velocity over the
    span is not the velocity at its start (a rope released from a held curve), which start_velocity judges."""
    time = np.asarray(ref.time, np.float64)
    still = min(hand_still_frames(ref), int(np.searchsorted(time, time[0] + START_WINDOW_MAX + 1e-9)))
    if still < START_MIN_SAMPLES or time[still - 1] - time[0] < HAND_STILL_MIN_S - 1e-9:
        return None
    missing = getattr(ref, "missing", None)
    seen = np.ones(np.shape(ref.markers)[:2], bool) if missing is None else ~np.asarray(missing, bool)
    slope, k = _start_slopes(time, ref.markers, seen, still - 1, terms=2)  # a line's slope: the span's mean velocity
    ok = np.isfinite(slope).all(-1)
    if not ok.any():
        return None
    sigma = estimate_noise(ref.markers[:20], None if missing is None else missing[:20])
    speed = float(np.sqrt(np.mean(np.sum(slope[ok] ** 2, -1))))
    noise = float(np.sqrt(3.0) * sigma * np.sqrt(np.mean(k[ok] ** 2)))
    return speed, noise


def rest_tilt(ref) -> tuple[float, float] | None:
    """(degrees off -z of the hand-to-rope-centre direction, speed of the markers' first step) when the rope starts
    at rest (its first step under REST_SPEED, or within the markers' noise as the chain's start takes it), else
    None. A rope hanging at rest from the hand hangs along gravity (the built-in, test and generated references:
    0.00 deg); a frame tilted 3 deg kept the measured chain, which falls along -z, from ever hitting itself, and
    nothing said so (a probe of stop 47)."""
    if len(ref.markers) < 2:
        return None
    centre = np.nanmean(np.asarray(ref.markers[0], np.float64), axis=0) - np.asarray(ref.hand[0], np.float64)
    norm = np.linalg.norm(centre)
    if not (norm > 0 and starts_at_rest(ref)):
        return None
    return float(np.degrees(np.arccos(np.clip(-centre[2] / norm, -1.0, 1.0)))), first_step_speed(ref)


def critical(ref, time_tolerance: float = TIME_TOLERANCE) -> Critical:
    """The critical moment a reference contributes: its `critical_time` annotation when present (checked by
    the loader to lie inside the time axis), else the detected first contact."""
    det = detect_reference(ref)
    warnings = []
    tilt = rest_tilt(ref)
    if tilt is not None and tilt[0] > REST_TILT_DEG:
        warnings.append(f"the rope starts at rest (first step {tilt[1]:.3f} m/s, or within its noise) but hangs "
                        f"{tilt[0]:.1f} deg off -z (hand to rope centre): a frame tilted from gravity? the chain falls "
                        "along -z, and a 3 deg tilt kept it from hitting itself; level the frame, unless the rope was "
                        "held so that it did not hang freely")
    if tilt is None:
        g = gravity_from_motion(ref.time, ref.markers, ref.hand, ref.marker_arclength)
        if not g.determined:
            warnings.append("gravity's direction could not be checked: the rope does not start at rest, and its "
                            f"motion over the clip does not determine it (shorter than {GRAVITY_MIN_DURATION:g} s, or "
                            "the held end's link turns too little); the chain falls along -z of the file's frame")
        elif g.degrees_off_down > TILT_WARN_DEG:
            v = g.vector
            warnings.append(f"the rope's motion puts gravity {g.degrees_off_down:.0f} deg off -z (({v[0]:+.1f}, "
                            f"{v[1]:+.1f}, {v[2]:+.1f}) m/s^2: its centre of mass's acceleration across the held "
                            "end's link): a frame tilted from gravity? the chain falls along -z, and a 3 deg tilt "
                            "kept it from hitting itself; level the frame")
    if tilt is None and len(ref.markers) > velocity_intervals(ref):
        velocity, noise = start_velocity(ref)
        speed = float(np.sqrt(np.nanmean(np.sum(velocity ** 2, -1))))
        if noise > START_NOISE_SHARE * speed:
            warnings.append(f"the rope is moving in the first frame ({speed:.2f} m/s RMS), and the chain starts from "
                            f"the markers' velocity there, whose noise is about {noise:.2f} m/s RMS "
                            f"({100 * noise / speed:.0f} %): a start this noisy can make the chain miss a contact it "
                            "hits from clean markers (0.19 m/s on 0.96 did); start the recording with the rope at rest")
    missing = getattr(ref, "missing", None)
    if missing is not None and np.any(missing):
        cols = np.flatnonzero(np.any(missing, axis=0)).tolist()
        filled = int(getattr(ref, "tracker_filled", 0) or 0)
        broken = int(getattr(ref, "length_broken", 0) or 0)
        zeros = int(getattr(ref, "zeros_missing", 0) or 0)
        how = "NaN" + "".join(f", or {n} of them {what}, read as missing" for n, what in (
            (zeros, "exactly (0, 0, 0), a tracker's mark for a lost marker"),
            (filled, "filled by the recording's gap filling"),
            (broken, "farther from their neighbours than the rope between them is long (ghost samples, where two "
                     "markers' labels were exchanged, or a rope that stretches more than 10 %, which the chain "
                     "cannot)")) if n)
        warnings.append(f"{int(np.sum(missing))} marker samples were missing ({how}) and bridged in time (markers "
                        f"{cols}, longest gap {int(missing_runs(np.asarray(missing, bool)).max())} frames)")
    lag = float(getattr(ref, "hand_lag", 0.0) or 0.0)
    if lag:
        frames = int(round(abs(lag) / ref.dt))
        warnings.append(f"the hand's track {'lags' if lag > 0 else 'leads'} the markers' by {1000 * abs(lag):.0f} ms "
                        f"({frames} frame{'s' if frames != 1 else ''}; marker 0, the held end, sits on the hand "
                        "shifted so): the chain is driven that much off the rope's own clock; give the hand on the "
                        "markers' clock")
    unseen = getattr(ref, "start_unseen", ()) or ()
    if unseen:
        frames, seconds, which = unseen
        warnings.append(f"markers {list(which)} were not yet seen in the recording's first {frames} frames "
                        f"({seconds:.3f} s): those frames are left out, and the rope starts where every marker has "
                        "been seen (held back to the first frame, an unseen marker made up the shape the chain starts "
                        "from)")
    replaced = int(getattr(ref, "hand_replaced", 0) or 0)
    if replaced:
        warnings.append(f"{replaced} samples of marker 0 lay farther from the hand than the rope allows (ghost "
                        "samples): read as missing and taken from the hand, where marker 0 sits")
    for t_swap, i, j in getattr(ref, "label_swaps", ()) or ():
        warnings.append(f"markers {i} and {j} exchanged labels at {t_swap:.4f} s (each then sat where the other "
                        "belongs, farther from its neighbours than the rope is long): read back in order from there")
    t_c = getattr(ref, "critical_time", None)
    if t_c is not None:
        time = ref.time
        k = int(np.clip(np.searchsorted(time, t_c, side="left"), 1, len(time) - 1))
        gap, sa, sb = closest_pair_at(ref, float(t_c))
        ev = CollisionEvent(k, float(t_c), sa, sb, float("nan"), gap, "annotated", "high", ())
        if det.event is not None and abs(det.event.time - t_c) > time_tolerance:
            warnings.append(f"the annotated critical_time {t_c:.4f} s differs from the detected contact "
                            f"({det.event.time:.4f} s) by {1000 * (det.event.time - t_c):+.0f} ms; "
                            "the annotation is used")
        elif det.event is None:
            warnings.append(f"no contact detected in the markers ({det.status}); the annotated critical_time "
                            f"{t_c:.4f} s is used")
        if gap > 0.05 * ref.length:
            warnings.append(f"at the annotated critical_time the reconstructed rope is {1000 * gap:.0f} mm from "
                            "touching itself: check the annotation")
        return Critical(ev, det, True, warnings)
    if det.status != "contact" or det.event is None:
        why = det.reasons[-1] if det.reasons else det.status
        return Critical(None, det, False, warnings + [f"no usable first contact: {why}"],
                        problem=f"no usable first self-contact in the markers ({det.status}): {why}")
    if det.flagged:
        warnings += [f"uncertain event: {r}" for r in det.reasons]
    elif det.reasons:
        warnings += list(det.reasons)
    return Critical(det.event, det, False, warnings)
