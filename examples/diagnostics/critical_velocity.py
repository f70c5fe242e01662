"""Is the velocity floor of a stalled correction a sampling artefact? (README, "Seeds the loop never saw")

The critical state's velocity was the marker difference over the frame interval that holds the first contact (since
stop 60 it is interpolated to the contact's time from that interval's and its neighbour's), so it could carry the
impact's response or jump when the contact time crosses a frame. This simulates the goal throw and
every trial of a finished run twice: at the engine's frame rate (the rule the correction scores with) and at
1000 Hz with the same physics step, where the state at the contact time is taken from the three frames BEFORE the
contact (quadratic in time), free of the impact. It prints each trial's error to the goal both ways.

    python -m wrenorm correct rope --variant heavy_end --seed 3 --params fitted --no-record --out runs/he-s3
    python examples/diagnostics/critical_velocity.py runs/he-s3 fitted

Two simulations per trial (about 4 minutes for 11 commands here).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from wrenorm.tasks.rope import observable as crit
from wrenorm.tasks.rope.control.command import CommandSpace
from wrenorm.tasks.rope.reference.generate import ENGINE_FRAME_RATE, generate_reference
from wrenorm.tasks.rope.reference.paths import get_hand_path

FINE_RATE = 1000.0  # Hz


def _fail(message: str) -> None:
    print(f"critical_velocity: {message}", file=sys.stderr)
    sys.exit(2)


def before_contact(ref, event) -> crit.CriticalStates:
    """The state at the event time from the three frames before its interval (quadratic in time)."""
    k = event.index
    if k < 3:
        _fail(f"the contact at frame {k} leaves fewer than three frames before it")
    dt = ref.time[k - 3:k] - event.time
    basis = np.stack([np.ones(3), dt, dt ** 2], 1)
    frames = ref.markers[k - 3:k].astype(np.float64)
    coef = np.linalg.solve(basis, frames.reshape(3, -1)).reshape(3, *frames.shape[1:])
    s_k = np.linspace(0.0, 1.0, crit.SAMPLES)
    s = ref.marker_arclength
    return crit.CriticalStates(crit.resample(coef[0], s, s_k)[None], crit.resample(coef[1], s, s_k)[None],
                               np.array([event.time - ref.time[0]]), np.array([[event.s_a, event.s_b]]),
                               np.ones(1, bool), np.zeros(1))


def states(path, settings: dict) -> tuple[crit.CriticalStates, crit.CriticalStates]:
    """(the scoring rule's state at the engine's frame rate, the pre-contact state at FINE_RATE)."""
    engine = settings.get("engine", "newton")
    out = []
    for rate in (ENGINE_FRAME_RATE[engine], FINE_RATE):
        # either engine's physics step is its own at every frame rate: the frames only sample the same motion
        ref = generate_reference(path, segments=settings.get("fine_segments", 64), variant=settings["variant"],
                                 duration=1.5, frame_rate=rate, engine=engine)
        event = crit.reference_event(ref)
        if event is None:
            out.append(None)
            continue
        out.append(crit.from_reference(ref, event) if rate != FINE_RATE else before_contact(ref, event))
    return out[0], out[1]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        _fail("usage: critical_velocity.py RUN_FOLDER ARM")
    folder, arm = Path(argv[0]), argv[1]
    try:
        result = json.loads((folder / "correct.json").read_text())
        settings = json.loads((folder / "settings.json").read_text())
    except (OSError, ValueError) as e:
        _fail(f"{folder / 'correct.json'}: not a finished correction run ({type(e).__name__})")
    if arm not in result["runs"]:
        _fail(f"{folder / 'correct.json'}: no run {arm!r} (has {', '.join(result['runs'])})")
    space = CommandSpace(get_hand_path(settings["start"]))
    commands = [("goal", get_hand_path(settings["goal"]))]
    commands += [(f"trial {t['trial']}", space.decode(t["command_u"])) for t in result["runs"][arm]["trials"]]
    coarse_goal, fine_goal = states(commands[0][1], settings)
    if coarse_goal is None or fine_goal is None:
        _fail(f"the {settings['variant']} rope never hits itself under the goal {settings['goal']!r}")
    targets = [crit.Target(g, _length(settings), _speed(g), dict(crit.WEIGHTS))
               for g in (coarse_goal, fine_goal)]
    print(f"{settings['variant']} rope on {settings.get('engine', 'newton')}: error to the goal, the scoring rule "
          f"({ENGINE_FRAME_RATE[settings.get('engine', 'newton')]:g} Hz) | pre-contact at {FINE_RATE:g} Hz")
    print("command     total  velocity | total  velocity")
    for name, path in commands[1:]:
        coarse, fine = states(path, settings)
        if coarse is None or fine is None:
            print(f"{name:10s} no self-collision")
            continue
        a, b = targets[0].terms(coarse), targets[1].terms(fine)
        print(f"{name:10s} {a['total'][0]:6.3f} {a['velocity'][0]:8.3f} | {b['total'][0]:6.3f} {b['velocity'][0]:8.3f}",
              flush=True)
    return 0


def _length(settings: dict) -> float:
    from wrenorm.tasks.rope.reference.materials import get_variant

    return float(get_variant(settings["variant"]).length)


def _speed(state: crit.CriticalStates) -> float:
    return max(float(np.sqrt(np.mean(np.sum(state.vel[0] ** 2, -1)))), crit.MIN_SPEED)


if __name__ == "__main__":
    sys.exit(main())
