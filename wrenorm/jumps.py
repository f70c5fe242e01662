"""Frames cut out of a recording whose rows carry no clock of their own (or whose clock was made uniform again) leave
one trace: a step between two frames far larger than the steps around it. Compared with its neighbourhood rather
than the whole recording, so that a recording that rests for most of its frames before it moves is no jump."""
from __future__ import annotations

import numpy as np

JUMP_WINDOW = 30  # frames either side whose steps are the neighbourhood (0.5 s at 60 fps, 0.12 s at 250 fps)


def largest_jump(steps: np.ndarray, window: int = JUMP_WINDOW) -> tuple[int, float]:
    """(i, ratio): the step steps[i] (frame i to i + 1) that is the largest multiple of the median of the steps within
    `window` frames either side of it (itself left out), and that multiple; (-1, 0.0) when no step has a moving
    neighbourhood or there are fewer than 3 steps."""
    steps = np.asarray(steps, dtype=np.float64)
    if len(steps) < 3:
        return -1, 0.0
    return _most_unusual(steps, steps, 1, window)


def largest_jump_on_both_sides(steps: np.ndarray, window: int = JUMP_WINDOW) -> tuple[int, float]:
    """As largest_jump, but the step is compared with the larger of the median steps before it and after it: a seam
    between two moving stretches stands out against both, while the first step of a motion out of rest stands out
    only against the rest before it (a fish filmed still, then swimming)."""
    steps = np.asarray(steps, dtype=np.float64)
    if len(steps) < 3:
        return -1, 0.0
    return _most_unusual(steps, steps, 1, window, sides_apart=True)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, length) of each run of True in a boolean series."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b - a)) for a, b in zip(starts, ends)]


def _most_unusual(score: np.ndarray, series: np.ndarray, width: int, window: int,
                  sides_apart: bool = False) -> tuple[int, float]:
    """(i, ratio): among the 8 largest scores, the one that is the largest multiple of the median of `series` within
    `window` entries either side of entries i .. i + width - 1 (left out), and that multiple; (-1, 0.0) if none.
    sides_apart: the larger of the two sides' medians instead of the median of both together."""
    best, ratio = -1, 0.0
    for i in np.argsort(score)[::-1][:8]:  # what stands out is among the largest
        before, after = series[max(0, i - window):i], series[i + width:i + width + window]
        if sides_apart:
            usual = max((float(np.median(side)) for side in (before, after) if side.size), default=0.0)
        else:
            around = np.concatenate([before, after])
            usual = float(np.median(around)) if around.size else 0.0
        if usual > 0 and score[i] / usual > ratio:
            best, ratio = int(i), float(score[i] / usual)
    return best, ratio


def largest_doublet(points: np.ndarray, window: int = JUMP_WINDOW) -> tuple[int, float]:
    """(i, ratio): frames cut out of a smooth path whose clock was made uniform again leave a kink back and forth, two
    neighbouring second differences of opposite direction (a step of k frames' motion, then its return), each as large
    as the motion of the frames lost, between second differences less than half as large (one sample off the path, a
    tracking glitch, kinks three times instead: +e, -2e, +e). ratio is the smaller of the two over the median second
    difference within `window` either side; the cut lies between frames i + 1 and i + 2. A single cut frame already
    stands out where a first-difference jump (largest_jump) needs about ten; (-1, 0.0) when there is none or fewer
    than 4 frames. Used on a driven path (the hand): a free rope's own second differences kink in contact and whip."""
    x = np.asarray(points, dtype=np.float64)
    if len(x) < 4:
        return -1, 0.0
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    size = np.linalg.norm(d2, axis=1)
    both = np.minimum(size[:-1], size[1:])
    cos = np.einsum("ij,ij->i", d2[:-1], d2[1:]) / np.maximum(size[:-1] * size[1:], 1e-300)
    # a cut is a pair with quiet neighbours; one sample off the path (a tracking glitch) kinks three times, +e -2e +e
    before = np.concatenate([[0.0], size[:-2]])
    after = np.concatenate([size[2:], [0.0]])
    quiet = np.maximum(before, after) < 0.5 * both
    return _most_unusual(np.where((cos < -0.5) & (both > 0) & quiet, both, 0.0), size, 2, window)


def repeated_runs(frames: np.ndarray, mover: np.ndarray) -> list[tuple[int, int, float, int]]:
    """Runs of frames equal to the one before to the bit: (first copy, copies, how far `mover` goes from the frame
    before the original to the frame after the last copy, over how many frames). A tracker that holds its last value
    repeats a moving body exactly; a body at rest may repeat too, which the distance the mover covers tells apart."""
    frames = np.asarray(frames)
    same = np.all((frames[1:] == frames[:-1]).reshape(len(frames) - 1, -1), axis=1)
    out = []
    for a, n in true_runs(same):  # same[a:a + n]: frames a+1 .. a + n equal frame a
        before, after = max(a - 1, 0), min(a + n + 1, len(mover) - 1)
        out.append((a + 1, n, float(np.linalg.norm(mover[after] - mover[before])), after - before))
    return out
