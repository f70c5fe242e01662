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
    n = len(steps)
    best, ratio = -1, 0.0
    if n < 3:
        return best, ratio
    for i in np.argsort(steps)[::-1][:8]:  # a jump is among the largest steps
        around = np.concatenate([steps[max(0, i - window):i], steps[i + 1:i + 1 + window]])
        usual = float(np.median(around)) if around.size else 0.0
        if usual > 0 and steps[i] / usual > ratio:
            best, ratio = int(i), float(steps[i] / usual)
    return best, ratio
