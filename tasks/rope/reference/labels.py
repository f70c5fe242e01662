"""Marker samples that break the rope's length: a motion-capture tracker's label swaps and ghost samples.

A rope carries identical markers, and a tracker labels them by continuity: where two come close (the pieces that touch
at a self-contact, a knot forming after it) it can exchange their labels and keep them exchanged, a reflection can
stand in for a marker for a frame, and two labels can sit on one marker. The first two put a marker farther from its
neighbours along the rope than the rope between them is long, the third two centre-line points nearer each other
than touching pieces come; no rope does either. Such a sample anywhere in a recording had the whole file refused as
"wrong units or wrong length?" (a probe of stop 48: one ghost sample 0.1 s after the contact, or two labels exchanged
after it). Here each exchange that a swap of two labels undoes (or two swaps, where a knot exchanges two pairs), in
the frame it shows and in the next, is undone from the frame it began (found by the smoothness of the two paths;
that frame is read as missing where the exchange showed only later); any other such sample is read as missing, and
the loader bridges and the detector flags such gaps as it does any other. A hand sample off its path that breaks the
rope's reach is no marker's fault: it is reported (`hand_frames`) for the loader to refuse."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from wrenorm.tasks.rope.reference.events import estimate_noise

CHORD_SLACK = 1.1  # a chord may exceed its arc by 10 % (stretch) ...
CHORD_SLACK_M = 0.002  # ... plus 2 mm, or NOISE_SIGMAS chord noises where the markers are noisier
NOISE_SIGMAS = 5.0
MAX_BROKEN_FRAMES = 0.1  # more frames than this breaking the length: the file's length or units are wrong
SWAP_LOOKBACK = 0.25  # s searched back for the frame an exchange began in
MAX_SWAP_CANDIDATES = 12  # markers in (or beside) a frame's broken intervals, each tried against every other
CONFIRM_FRAMES = 3  # frames after the one an exchange shows in, searched for one holding both markers


@dataclass(frozen=True)
class RopeLimits:
    """How far apart the hand and the markers may be: the rope between them plus slack."""

    s: np.ndarray  # (M,) marker arc-length fractions
    length: float  # m
    slack: float  # m beyond 10 % of every interval
    hand_slack: float  # m the hand may sit off the held end beyond 10 % of the rope to the first seen marker

    def reach(self, arc: np.ndarray, from_hand: bool = False) -> np.ndarray:
        """Longest chord over these arc fractions of rope, between two markers or (from_hand) from the hand, where
        the loader's own rule for marker 0's reach applies."""
        return CHORD_SLACK * np.asarray(arc) * self.length + (self.hand_slack if from_hand else self.slack)

    def allowed(self, nodes_s: np.ndarray) -> np.ndarray:
        """Longest chord between consecutive nodes at these arc fractions, node 0 the hand (at arc 0)."""
        arc = np.diff(nodes_s)
        return np.concatenate([self.reach(arc[:1], from_hand=True), self.reach(arc[1:])])


@dataclass
class LengthRepair:
    markers: np.ndarray  # (T, M, 3) with exchanges undone and samples breaking the length NaN
    swaps: list = field(default_factory=list)  # (frame exchanged from, i, j)
    broken: np.ndarray | None = None  # (T, M) bool: samples read as missing (ghosts, second labels, each exchange's
    # first frame where it showed only later)
    hand_frames: list = field(default_factory=list)  # frames whose hand sample, off its path, breaks the reach
    refused: bool = False  # more than MAX_BROKEN_FRAMES of the frames break the length: the caller refuses
    broken_frames: int = 0  # frames that broke the length as read (an exchange counted once, where it shows)
    broken_frames_as_read: int = 0  # where refused: frames whose neighbouring markers break the length as read
    worst_chord_over_arc: float = 0.0  # where refused: the largest chord / arc between neighbouring markers
    worst_markers: tuple = ()  # where refused: the markers most often in a broken interval
    noise: float = 0.0  # m, the markers' noise (third differences) that set the slack


def _merged(X: np.ndarray, radius: float, noise: float, arc: np.ndarray) -> list[tuple[int, int, int]]:
    """(frame, i, j) where markers i and j lie nearer each other than a rope's centre line can come to itself (one
    diameter: pieces touch, they do not pass into each other), by more than the noise allows: a tracker put two labels
    on one marker. Within the rope's length such a sample breaks nothing, and at 8 markers a marker seen where
    another was made a contact between the two 31 ms early, with confidence (a held-out MuJoCo throw of stop 48).
    Markers nearer along the rope (arc, m) than twice the limit are not judged: the rope between them may bring them
    that near without folding through itself (clean files with neighbours 5-8 mm apart on a rope of 8-11 mm radius
    had been refused as mostly missing; a probe of stop 59)."""
    limit = min(radius, 2.0 * radius - 4.0 * np.sqrt(2.0) * noise)
    if limit <= 0.0:
        return []
    T, M, _ = X.shape
    apart = np.abs(arc[:, None] - arc[None, :]) > 2.0 * limit
    out = []
    chunk = max(1, 2_000_000 // (M * M))  # frames at a time: every pair of a long 65-marker recording is gigabytes
    for a in range(0, T, chunk):
        Y = X[a:a + chunk]
        sq = np.einsum("tmk,tmk->tm", Y, Y)
        with np.errstate(invalid="ignore"):
            near = sq[:, :, None] + sq[:, None, :] - 2.0 * np.einsum("tmk,tnk->tmn", Y, Y) < limit * limit
        t, i, j = np.nonzero(np.triu(near & apart[None], 1))
        out += zip((a + t).tolist(), i.tolist(), j.tolist())
    return out


def _frame_breaks(X: np.ndarray, hand: np.ndarray, t: int, rope: RopeLimits):
    """(broken (K,), marker index of each node (K + 1,), -1 for the hand) over the consecutive nodes of frame t: the
    hand and the markers seen there."""
    seen = np.flatnonzero(np.isfinite(X[t]).all(axis=1))
    points = np.concatenate([hand[t][None], X[t, seen]])
    chord = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return chord > rope.allowed(np.concatenate([[0.0], rope.s[seen]])), np.concatenate([[-1], seen])


def _neighbour_ratios(X: np.ndarray, hand: np.ndarray, rope: RopeLimits, plain: bool = False) -> np.ndarray:
    """(T, M) chord / allowed from the hand to marker 0 and between neighbouring markers (NaN where one is missing);
    plain: chord / arc."""
    nodes = np.concatenate([hand[:, None], X], axis=1)
    chord = np.linalg.norm(np.diff(nodes, axis=1), axis=2)
    nodes_s = np.concatenate([[0.0], rope.s])
    with np.errstate(divide="ignore", invalid="ignore"):
        return chord / (np.diff(nodes_s) * rope.length if plain else rope.allowed(nodes_s))[None]


def _suspect_frames(X: np.ndarray, hand: np.ndarray, rope: RopeLimits, markers=None) -> np.ndarray:
    """Frames where an interval between neighbouring markers (or the hand and marker 0) breaks the length, or where
    a marker is missing (its neighbours then span the gap, checked frame by frame); `markers`: only the intervals
    beside these."""
    ratio = _neighbour_ratios(X, hand, rope)
    missing = ~np.isfinite(X).all(axis=2)
    if markers is not None:
        cols = sorted({c for m in markers for c in (m, m + 1) if c < X.shape[1]})  # interval c ends at marker c
        ratio, missing = ratio[:, cols], missing[:, sorted(set(markers))]
    with np.errstate(invalid="ignore"):
        return np.flatnonzero(np.any(ratio > 1.0, axis=1) | missing.any(axis=1))


def _off_path(col: np.ndarray, t: int, value: np.ndarray | None = None) -> float:
    """How far sample t of a path (T, 3) (or `value` put there) lies from the straight continuation of the path
    through its two nearest seen samples before t (after t where there are not two before): a ghost leaves its path,
    and so does a marker given another's position; a marker moving fast does not."""
    here = col[t] if value is None else value
    seen = np.isfinite(col).all(axis=1)
    seen[t] = False
    before = np.flatnonzero(seen[:t])[-2:]
    after = t + 1 + np.flatnonzero(seen[t + 1:])[:2]
    ends = before if len(before) == 2 else after if len(after) == 2 else None
    if ends is None:
        near = np.flatnonzero(seen)
        return float(np.linalg.norm(here - col[near[np.argmin(np.abs(near - t))]])) if near.size else 0.0
    a, b = ends
    return float(np.linalg.norm(here - (col[a] + (col[b] - col[a]) * (t - a) / (b - a))))


def repair_length(markers: np.ndarray, hand: np.ndarray, s: np.ndarray, length: float, radius: float, dt: float,
                  hand_slack: float, marker_offset: float = 0.0) -> LengthRepair:
    """Undo label exchanges and read ghost samples as missing (module docstring). markers: (T, M, 3) NaN where not
    seen; s: marker arc-length fractions; hand_slack: how far (m) the hand may sit from the held end beyond 10 % of
    the rope to the first marker (the loader's rule for marker 0's reach); marker_offset: how far (m) markers may sit
    off the centre line (on its surface): a chord may exceed its arc by twice that. `refused`: more than
    MAX_BROKEN_FRAMES of the frames break the length (wrong units or length, a rope that stretches, markers far noisier
    than their spacing, exchanges one swap does not undo); the scan stops there."""
    X = np.array(markers, dtype=np.float64)
    hand = np.asarray(hand, dtype=np.float64)
    T, M, _ = X.shape
    noise = estimate_noise(X)
    # a chord between two noisy markers scatters by sqrt(2) sigma: 1-3 mm of noise on 24 markers (4.6 cm apart) had
    # every tenth frame break a fixed 2 mm slack (a probe of stop 48)
    rope = RopeLimits(np.asarray(s, np.float64), length,
                      max(CHORD_SLACK_M, NOISE_SIGMAS * np.sqrt(2.0) * noise) + 2.0 * marker_offset,
                      hand_slack + marker_offset)
    out = LengthRepair(X, noise=noise)
    broken = np.zeros((T, M), bool)
    # markers on touching pieces' surfaces come as near as twice the rope's radius less two offsets, or, where the
    # offset passes the radius (the marker's own radius on top), two markers' radii: half of that is the limit here
    for t, i, j in _merged(X, abs(radius - marker_offset), noise, np.asarray(s, np.float64) * length):
        if np.isfinite(X[t, [i, j]]).all():
            m = max((i, j), key=lambda c: _off_path(X[:, c], t))
            X[t, m] = np.nan
            broken[t, m] = True
    with np.errstate(invalid="ignore"):
        if np.mean(_neighbour_ratios(X, hand, rope)[:, 0] > 1.0) > MAX_BROKEN_FRAMES:
            # the hand is not at the held end: not a ghost's anchor (the loader says so on `hand`)
            rope = RopeLimits(rope.s, length, rope.slack, np.inf)
    lookback = max(2, int(round(SWAP_LOOKBACK / dt)))
    queue, q = _suspect_frames(X, hand, rope), 0
    while q < len(queue):
        t = int(queue[q])
        q += 1
        b, idx = _frame_breaks(X, hand, t, rope)
        if not b.any():
            continue
        out.broken_frames += 1
        if out.broken_frames > MAX_BROKEN_FRAMES * T:
            out.refused = True
            _describe_refusal(out, np.asarray(markers, np.float64), hand, rope)
            break
        if b[0] and _off_path(hand, t) > _off_path(X[:, idx[1]], t):
            out.hand_frames.append(t)  # the hand left its path here, not the marker
            continue
        involved = sorted({int(m) for k in np.flatnonzero(b) for m in idx[k:k + 2] if m >= 0})
        # a neighbour's exchange breaks only the intervals beside the pair (5 and 6 exchanged: 4-"5" and "6"-7)
        near = sorted({n for m in involved for n in (m - 1, m, m + 1) if 0 <= n < M})
        for i, j in _undoing_swaps(X, hand, t, rope, near):
            k = _exchange_frame(X, t, i, j, lookback)
            X[k:, [i, j]] = X[k:, [j, i]]
            # the frame of the exchange is a guess within the two markers' distance there: read it as missing
            blur = slice(max(k - 1, 0), k + 1) if k < t else slice(t, t)
            broken[blur, [i, j]] |= np.isfinite(X[blur, [i, j]]).all(axis=2)
            X[blur, [i, j]] = np.nan
            out.swaps.append((int(k), i, j))
            # every frame from k on now reads the other way round: those beside i and j are judged again
            queue, q = np.union1d(queue[q:], _suspect_frames(X[k:], hand[k:], rope, (i, j)) + k), 0
        b, idx = _frame_breaks(X, hand, t, rope)
        while b.any():  # what no exchange explains: drop the marker in most broken intervals, the one off its path
            hits = np.zeros(len(idx), np.int64)
            for k in np.flatnonzero(b):
                hits[k:k + 2] += 1
            hits[0] = 0  # the hand is never dropped
            most = [int(idx[n]) for n in np.flatnonzero(hits == hits.max())]
            m = max(most, key=lambda c: _off_path(X[:, c], t))
            X[t, m] = np.nan
            broken[t, m] = True
            b, idx = _frame_breaks(X, hand, t, rope)
    out.markers, out.broken = X, broken
    return out


def _describe_refusal(out: LengthRepair, X: np.ndarray, hand: np.ndarray, rope: RopeLimits) -> None:
    """By how much and which markers most often the recording as read breaks the length (the refusal's words)."""
    with np.errstate(invalid="ignore"):
        over = _neighbour_ratios(X, hand, rope) > 1.0
    out.broken_frames_as_read = int(over.any(axis=1).sum())
    out.worst_chord_over_arc = float(np.nanmax(_neighbour_ratios(X, hand, rope, plain=True)[:, 1:]))
    per_interval = over.sum(axis=0)  # interval m ends at marker m (interval 0 starts at the hand)
    counts = per_interval.copy()
    counts[:-1] += per_interval[1:]
    out.worst_markers = tuple(int(m) for m in np.argsort(-counts, kind="stable")[:2] if counts[m] > 0)


def _after(X: np.ndarray, hand: np.ndarray, t: int, rope: RopeLimits, swaps) -> tuple[int, bool]:
    """(broken intervals, whether every interval beside the swapped markers is whole) in frame t with these label
    exchanges made."""
    for i, j in swaps:
        X[t, [i, j]] = X[t, [j, i]]
    b, idx = _frame_breaks(X, hand, t, rope)
    for i, j in reversed(swaps):
        X[t, [i, j]] = X[t, [j, i]]
    nodes = np.flatnonzero(np.isin(idx, [m for pair in swaps for m in pair]))
    return int(b.sum()), not b[np.clip(np.concatenate([nodes - 1, nodes]), 0, len(b) - 1)].any()


def _mends(X: np.ndarray, hand: np.ndarray, t: int, rope: RopeLimits, swaps) -> bool:
    """Whether these exchanges in frame t leave every interval beside them whole, and fewer broken ones."""
    broken, beside_whole = _after(X, hand, t, rope, swaps)
    return beside_whole and broken < int(_frame_breaks(X, hand, t, rope)[0].sum())


def _confirmed(X: np.ndarray, hand: np.ndarray, t: int, rope: RopeLimits, swaps) -> bool:
    """Whether the exchanges mend the next frame holding their markers too: a tracker keeps exchanged labels, so
    that frame breaks beside them as read; swapping a ghost with some marker can mend its one frame but not the next
    (a lone ghost at 8 markers had been read as an exchange that moved 0.25 s of the contact, a held-out MuJoCo
    throw of stop 48)."""
    markers = [m for pair in swaps for m in pair]
    later = [n for n in range(t + 1, min(len(X), t + 1 + CONFIRM_FRAMES)) if np.isfinite(X[n, markers]).all()]
    return bool(later) and _mends(X, hand, later[0], rope, swaps)


def _fits_at(X: np.ndarray, hand: np.ndarray, t: int, rope: RopeLimits, a: int) -> np.ndarray:
    """(M,) whether each marker's sample in frame t would sit within the rope's reach of marker a's seen neighbour
    on one side or the other: the partners worth trying for an exchange with a (a 65-marker rope had tried all 64)."""
    seen = np.flatnonzero(np.isfinite(X[t]).all(axis=1))
    seen = seen[seen != a]
    before, after = seen[seen < a], seen[seen > a]
    ok = np.zeros(X.shape[1], bool)
    for n in ([before[-1]] if before.size else [-1]) + ([after[0]] if after.size else []):
        point, arc = (hand[t], rope.s[a]) if n < 0 else (X[t, n], abs(rope.s[a] - rope.s[n]))
        with np.errstate(invalid="ignore"):
            ok |= np.linalg.norm(X[t] - point, axis=1) <= rope.reach(arc, from_hand=n < 0)
    return ok


def _undoing_swaps(X, hand, t: int, rope: RopeLimits, involved: list[int]) -> list[tuple[int, int]]:
    """The exchange of two labels seen in frame t, one among `involved` and the other any marker, that makes frame t
    whole and is confirmed in the next; where none alone does, two at once (a knot can exchange two pairs of neighbours,
    4-7 and 5-10, and neither mends the intervals beside it alone). Among several, the one whose samples lie
    nearest their new paths. Empty: none found (or too many markers involved to try). The partner may sit anywhere
    along the rope: at 8 markers, markers 5 and 7 exchanged break only the interval 4-5."""
    if not involved or len(involved) > MAX_SWAP_CANDIDATES:
        return []
    seen = np.isfinite(X[t]).all(axis=1)
    fits = {a: _fits_at(X, hand, t, rope, a) for a in involved if seen[a]}
    pairs = sorted({(min(a, int(c)), max(a, int(c))) for a, ok in fits.items() for c in np.flatnonzero(ok & seen)
                    if c != a})

    def cost(swaps):
        return sum(_off_path(X[:, i], t, X[t, j]) + _off_path(X[:, j], t, X[t, i]) for i, j in swaps)

    # the frame must come out whole: a swap that mends only the intervals beside it can be a wrong one that
    # shortens a longer exchange (markers 2 and 6 exchanged on a rope hanging straight at 8 markers: swapping 3 and 5
    # mends 3's and 5's intervals and then blocks the right swap; a MuJoCo throw of stop 48's probe)
    ones = [[p] for p in pairs if _after(X, hand, t, rope, [p])[0] == 0 and _confirmed(X, hand, t, rope, [p])]
    if ones:
        return min(ones, key=cost)
    before = int(_frame_breaks(X, hand, t, rope)[0].sum())
    partial = [p for p in pairs if _after(X, hand, t, rope, [p])[0] < before]
    twos = [[p, r] for n, p in enumerate(partial) for r in partial[n + 1:] if not set(p) & set(r)]
    twos = [w for w in twos if _after(X, hand, t, rope, w)[0] == 0 and _confirmed(X, hand, t, rope, w)]
    return min(twos, key=cost) if twos else []


def _exchange_frame(X: np.ndarray, t: int, i: int, j: int, lookback: int) -> int:
    """The frame k (in the `lookback` frames up to t) from which labels i and j were exchanged, found as the one that,
    undone from k on, leaves the two markers' paths smoothest (least summed second difference around it): a marker's
    path has no kink, while an exchange kinks both unless the two move alike there (where taking the wrong frame
    costs at most their distance). The exchange of the free end's marker and the one two before it showed four
    frames after it began."""
    a = max(1, t - lookback)
    b = min(len(X) - 1, t + 2)
    best, best_cost = t, np.inf
    for k in range(a, t + 1):
        Y = X[a - 1:b + 1, [i, j]].copy()
        Y[k - a + 1:, :] = Y[k - a + 1:, ::-1]
        d2 = np.linalg.norm(Y[2:] - 2 * Y[1:-1] + Y[:-2], axis=2)
        cost = float(np.nansum(d2))
        if cost < best_cost:
            best, best_cost = k, cost
    return best
