"""Marker samples that break the rope's length: a motion-capture tracker's label swaps and ghost samples.

A rope carries identical markers, and a tracker labels them by continuity: where two come close (the pieces that touch
at a self-contact, a knot forming after it) it can exchange their labels and keep them exchanged, and a reflection can
stand in for a marker for a frame. Either puts a marker farther from its neighbours along the rope than the rope
between them is long, which no rope does. Such a sample anywhere in a recording had the whole file refused as "wrong
units or wrong length?" (a probe of stop 48: one ghost sample 0.1 s after the contact, or two labels exchanged after
it). Here an exchange that one swap of two labels undoes is undone from the frame it shows on, the frames since the
two markers last came close are read as missing (the exchange happened somewhere there), and any other sample that
breaks the length is read as missing; the loader bridges and the detector flags such gaps as it does any other."""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

CHORD_SLACK = 1.1  # a chord may exceed its arc by 10 % (stretch, marker noise) ...
CHORD_SLACK_M = 0.002  # ... plus 2 mm
MAX_BROKEN_FRAMES = 0.1  # more frames than this breaking the length: the file's length or units are wrong
SWAP_LOOKBACK = 0.25  # s searched back for where two exchanged labels came close
MAX_SWAP_CANDIDATES = 12  # markers in (or beside) a frame's broken intervals tried pairwise as an exchange


@dataclass
class LengthRepair:
    markers: np.ndarray  # (T, M, 3) with exchanges undone and samples breaking the length NaN
    swaps: list = field(default_factory=list)  # (frame exchanged from, i, j, frame where it showed)
    broken: np.ndarray | None = None  # (T, M) bool: samples read as missing (ghosts, and around each exchange)
    broken_frames: int = 0  # frames that broke the length as read (an exchange counted once, where it shows)
    worst_ratio: float = 0.0  # the largest chord / allowed in those frames
    worst_chord_over_arc: float = 0.0  # where refused: the largest chord / arc between neighbouring markers
    worst_markers: tuple = ()  # the markers most often in a broken interval


def _allowed(nodes_s: np.ndarray, length: float, hand_slack: float) -> np.ndarray:
    arc = np.diff(nodes_s) * length
    allowed = CHORD_SLACK * arc + CHORD_SLACK_M
    allowed[:1] += hand_slack  # node 0 is the hand: a fingertip or gripper beside the held end
    return allowed


def _broken_intervals(points: np.ndarray, nodes_s: np.ndarray, length: float, hand_slack: float):
    """(k, ratio) over consecutive nodes: whether the chord k -> k + 1 is longer than the rope allows, and by what
    multiple of the allowance."""
    chord = np.linalg.norm(np.diff(points, axis=0), axis=1)
    ratio = chord / _allowed(nodes_s, length, hand_slack)
    return ratio > 1.0, ratio


def _frame_nodes(X: np.ndarray, hand: np.ndarray, s: np.ndarray, t: int):
    """The hand (arc 0) and the markers seen in frame t: (points, arc fractions, marker index or -1 for the hand)."""
    seen = np.flatnonzero(np.isfinite(X[t]).all(axis=1))
    points = np.concatenate([hand[t][None], X[t, seen]])
    return points, np.concatenate([[0.0], s[seen]]), np.concatenate([[-1], seen])


def _frame_breaks(X, hand, s, t, length, hand_slack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points, ns, idx = _frame_nodes(X, hand, s, t)
    # a marker at arc 0 and the hand are two nodes at one place: the hand's slack allows their offset
    broken, ratio = _broken_intervals(points, ns, length, hand_slack)
    return broken, ratio, idx


def _ghost_order(X: np.ndarray, t: int, candidates: list[int]) -> list[int]:
    """Candidates ordered by how far each jumped from its last seen position (a ghost jumps), largest first."""
    def jump(m):
        prev = X[:t, m]
        ok = np.flatnonzero(np.isfinite(prev).all(axis=1))
        return float(np.linalg.norm(X[t, m] - prev[ok[-1]])) if ok.size else 0.0
    return sorted(candidates, key=jump, reverse=True)


def repair_length(markers: np.ndarray, hand: np.ndarray, s: np.ndarray, length: float, dt: float,
                  hand_slack: float) -> LengthRepair:
    """Undo label exchanges and read ghost samples as missing (module docstring). markers: (T, M, 3) NaN where not
    seen; s: marker arc-length fractions; hand_slack: how far (m) the hand may sit from the held end beyond the rope
    between them. Returns the repaired markers and what was done; `broken_frames` above MAX_BROKEN_FRAMES of the
    frames (the frames that broke the length as read, an exchange counted once where it shows) means the length or
    the units are wrong, which the caller refuses (the scan then stops there)."""
    X = np.array(markers, dtype=np.float64)
    hand = np.asarray(hand, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    T, M, _ = X.shape
    out = LengthRepair(X)
    broken = np.zeros((T, M), bool)
    with np.errstate(invalid="ignore"):
        if np.mean(_neighbour_ratios(X, hand, s, length, hand_slack)[:, 0] > 1.0) > MAX_BROKEN_FRAMES:
            hand_slack = np.inf  # the hand is not at the held end: not a ghost's anchor (the loader says so on `hand`)
    counts = np.zeros(M, np.int64)
    lookback = max(2, int(round(SWAP_LOOKBACK / dt)))
    queue, q = _suspect_frames(X, hand, s, length, hand_slack, 0), 0
    while q < len(queue):
        t = int(queue[q])
        q += 1
        b, r, idx = _frame_breaks(X, hand, s, t, length, hand_slack)
        if not b.any():
            continue
        out.broken_frames += 1
        out.worst_ratio = max(out.worst_ratio, float(r[b].max()))
        involved = sorted({int(m) for k in np.flatnonzero(b) for m in idx[k:k + 2] if m >= 0})
        counts[involved] += 1
        if out.broken_frames > MAX_BROKEN_FRAMES * T:
            # the caller refuses (nothing a tracker does breaks the length in so many frames), saying how many frames
            # and which markers as read (neighbouring markers seen in the same frame)
            ratio = _neighbour_ratios(np.asarray(markers, np.float64), hand, s, length, hand_slack)
            with np.errstate(invalid="ignore"):
                over = ratio > 1.0
            out.broken_frames = int(over.any(axis=1).sum())
            out.worst_ratio = float(np.nanmax(ratio))
            out.worst_chord_over_arc = float(np.nanmax(_neighbour_ratios(np.asarray(markers, np.float64), hand, s,
                                                                         length, 0.0, plain=True)[:, 1:]))
            per_interval = over.sum(axis=0)  # interval m ends at marker m (interval 0 starts at the hand)
            counts = per_interval.copy()
            counts[:-1] += per_interval[1:]
            break
        # a neighbour's exchange breaks only the intervals beside the pair (markers 5 and 6 exchanged: 4-"5" and "6"-7)
        near = sorted({n for m in involved for n in (m - 1, m, m + 1) if 0 <= n < M})
        swap = _undoing_swap(X, hand, s, t, length, hand_slack, near)
        if swap is not None:
            i, j = swap
            k = _exchange_frame(X, t, i, j, lookback)
            X[k:, [i, j]] = X[k:, [j, i]]
            # the frame of the exchange is a guess within the two markers' distance there: read it as missing
            blur = slice(max(k - 1, 0), k + 1) if k < t else slice(t, t)
            broken[blur, [i, j]] |= np.isfinite(X[blur, [i, j]]).all(axis=2)
            X[blur, [i, j]] = np.nan
            out.swaps.append((int(k), i, j, int(t)))
            # every later frame now reads the other way round: judged again (an exchange back shows there)
            queue, q = _suspect_frames(X, hand, s, length, hand_slack, t + 1), 0
            b, r, idx = _frame_breaks(X, hand, s, t, length, hand_slack)
        while b.any():  # what no exchange explains: drop the marker in most broken intervals, the biggest jump first
            hits = np.zeros(len(idx), np.int64)
            for k in np.flatnonzero(b):
                hits[k:k + 2] += 1
            hits[0] = 0  # the hand is never dropped
            most = [int(idx[n]) for n in np.flatnonzero(hits == hits.max())]
            m = _ghost_order(X, t, most)[0]
            X[t, m] = np.nan
            broken[t, m] = True
            b, r, idx = _frame_breaks(X, hand, s, t, length, hand_slack)
    if counts.any():
        out.worst_markers = tuple(int(m) for m in np.argsort(-counts, kind="stable")[:2] if counts[m] > 0)
    out.markers, out.broken = X, broken
    return out


def _neighbour_ratios(X, hand, s, length, hand_slack, plain: bool = False) -> np.ndarray:
    """(T, M) chord / allowed from the hand to marker 0 and between neighbouring markers (NaN where one is missing);
    plain: chord / arc."""
    nodes = np.concatenate([hand[:, None], X], axis=1)
    chord = np.linalg.norm(np.diff(nodes, axis=1), axis=2)
    nodes_s = np.concatenate([[0.0], s])
    with np.errstate(divide="ignore", invalid="ignore"):
        return chord / (np.diff(nodes_s) * length if plain else _allowed(nodes_s, length, hand_slack))[None]


def _suspect_frames(X, hand, s, length, hand_slack, start: int) -> np.ndarray:
    """Frames from `start` on where an interval between neighbouring markers (or the hand and marker 0) breaks the
    length, or where a marker is missing (its neighbours then span the gap, checked frame by frame)."""
    ratio = _neighbour_ratios(X[start:], hand[start:], s, length, hand_slack)
    with np.errstate(invalid="ignore"):
        suspect = np.any(ratio > 1.0, axis=1) | ~np.isfinite(X[start:]).all(axis=(1, 2))
    return start + np.flatnonzero(suspect)


def _undoing_swap(X, hand, s, t, length, hand_slack, involved: list[int]) -> tuple[int, int] | None:
    """The one exchange of two labels among `involved` that leaves frame t whole, the one whose markers moved least
    from their last frame if several do; None if none does (or too many markers are involved to try)."""
    if len(involved) < 2 or len(involved) > MAX_SWAP_CANDIDATES:
        return None
    best, best_move = None, np.inf
    for i, j in combinations(involved, 2):
        Y = X[t].copy()
        Y[[i, j]] = Y[[j, i]]
        frame = np.where(np.isfinite(Y).all(axis=1)[:, None], Y, np.nan)
        saved = X[t].copy()
        X[t] = frame
        b, _, _ = _frame_breaks(X, hand, s, t, length, hand_slack)
        X[t] = saved
        if b.any():
            continue
        move = 0.0
        if t > 0 and np.isfinite(X[t - 1, [i, j]]).all():
            move = float(np.linalg.norm(Y[[i, j]] - X[t - 1, [i, j]]))
        if move < best_move:
            best, best_move = (i, j), move
    return best


def _exchange_frame(X: np.ndarray, t: int, i: int, j: int, lookback: int) -> int:
    """The frame k (in the `lookback` frames up to t) from which labels i and j were exchanged, found as the one that,
    undone from k on, leaves the two markers' paths smoothest (least summed second difference around it): a marker's
    path has no kink, while an exchange kinks both unless the two move alike there (where taking the wrong frame
    costs at most their distance)."""
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
