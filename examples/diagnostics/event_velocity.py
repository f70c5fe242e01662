"""Is a recording's critical velocity the velocity at the event? (README, "The velocity at the contact")

Each built-in throw of the seven newton ropes is recorded at 250 Hz (the references' rate) and again at 1000 Hz with
the same physics step; the critical velocity at the 250 Hz event's time is read by the interval's frame difference
(the rule before stop 60) and by observable.event_velocity (the rule since), and both are compared with the velocity
at that time from a quadratic through the three 1000 Hz frames before it (before the contact acts). Prints the
relative RMS error of each per throw.

    python examples/diagnostics/event_velocity.py [stiff,soft,...]

Two fine simulations per throw (about 6 minutes for the 35 here).
"""
from __future__ import annotations

import sys

import numpy as np

from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.reference.generate import generate_reference
from wrenorm.tasks.rope.reference.paths import get_hand_path

ROPES = ("stiff", "soft", "heavy", "light", "long", "damped", "heavy_end")
PATHS = ("flick", "flick_fast", "flick_wide", "flick_high", "flick_slow")


def record(path: str, variant: str, rate: float):
    return generate_reference(get_hand_path(path, "path"), segments=64, variant=variant, duration=1.5,
                              frame_rate=rate, engine="newton")


def before_contact_velocity(fine, when: float) -> np.ndarray | None:
    """(markers, 3) the velocity at `when` of a quadratic through the three frames before it."""
    j = int(np.searchsorted(fine.time, when, side="left"))
    if j < 3:
        return None
    d = fine.time[j - 3:j] - when
    basis = np.stack([np.ones(3), d, d ** 2], 1)
    frames = fine.markers[j - 3:j].astype(np.float64)
    return np.linalg.solve(basis, frames.reshape(3, -1)).reshape(frames.shape)[1]


def relative(v: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((v - truth) ** 2, -1)) / np.mean(np.sum(truth ** 2, -1))))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    variants = argv[0].split(",") if argv else list(ROPES)
    rows = []
    for variant in variants:
        for path in PATHS:
            coarse = record(path, variant, 250.0)
            event = crit.reference_event(coarse)
            truth = None if event is None else before_contact_velocity(record(path, variant, 1000.0), event.time)
            if truth is None:
                print(f"{variant:10s} {path:11s} no event with three fine frames before it")
                continue
            k = event.index
            frac = (event.time - coarse.time[k - 1]) / (coarse.time[k] - coarse.time[k - 1])
            interval = relative(crit.marker_velocity(coarse, k - 1, 1), truth)
            at_event = relative(crit.event_velocity(coarse, k, frac), truth)
            rows.append((interval, at_event))
            print(f"{variant:10s} {path:11s} frac {frac:.2f}  relative RMS velocity error: interval {interval:.3f}  "
                  f"at the event {at_event:.3f}", flush=True)
    if rows:
        r = np.array(rows)
        print(f"{len(r)} throws: median interval {np.median(r[:, 0]):.3f}, at the event {np.median(r[:, 1]):.3f}; "
              f"at the event nearer in {int((r[:, 1] < r[:, 0]).sum())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
