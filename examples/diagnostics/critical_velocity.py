"""Is the critical velocity a sampling artefact? (README, "Seeds the loop never saw" and "The velocity at the contact")

The critical state's velocity was the marker difference over the frame interval that holds the first contact (since
stop 60 it is extrapolated to the contact's time from that interval's and the one before), so it could carry the
impact's response or jump when the contact time crosses a frame. Both modes sample the same motion twice, at the
engine's frame rate (the rule the correction scores with) and at 1000 Hz with the same physics step, where the state
at the contact time is taken from the three frames BEFORE the contact (quadratic in time), free of the impact.

`RUN ARM` simulates the goal throw and every trial of a finished run and prints each trial's error to the goal both
ways (two simulations per trial, about 4 minutes for 11 commands here). `throws [ROPES]` records each built-in throw
of the seven newton ropes (or those named, comma-separated) and prints the relative RMS error to the 1000 Hz velocity
of the velocity at the 250 Hz event's time by the interval's frame difference (the rule before stop 60) and by
observable.event_velocity (the rule since) (about 6 minutes for the 35 throws).

    python -m wrenorm correct rope --variant heavy_end --seed 3 --params fitted --no-record --out runs/he-s3
    python examples/diagnostics/critical_velocity.py runs/he-s3 fitted
    python examples/diagnostics/critical_velocity.py throws [stiff,soft,...]
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
ROPES = ("stiff", "soft", "heavy", "light", "long", "damped", "heavy_end")
THROWS = ("flick", "flick_fast", "flick_wide", "flick_high", "flick_slow")


def _fail(message: str) -> None:
    print(f"critical_velocity: {message}", file=sys.stderr)
    sys.exit(2)


def quadratic_before(ref, k: int, when: float) -> tuple[np.ndarray, np.ndarray]:
    """(markers, 3) positions and velocities at `when` of a quadratic in time through frames k-3 .. k-1."""
    dt = ref.time[k - 3:k] - when
    basis = np.stack([np.ones(3), dt, dt ** 2], 1)
    frames = ref.markers[k - 3:k].astype(np.float64)
    coef = np.linalg.solve(basis, frames.reshape(3, -1)).reshape(3, *frames.shape[1:])
    return coef[0], coef[1]


def before_contact(ref, event) -> crit.CriticalStates:
    """The state at the event time from the three frames before its interval (quadratic in time)."""
    k = event.index
    if k < 3:
        _fail(f"the contact at frame {k} leaves fewer than three frames before it")
    pos, vel = quadratic_before(ref, k, event.time)
    s_k = np.linspace(0.0, 1.0, crit.SAMPLES)
    s = ref.marker_arclength
    return crit.CriticalStates(crit.resample(pos, s, s_k)[None], crit.resample(vel, s, s_k)[None],
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


def _relative(v: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((v - truth) ** 2, -1)) / np.mean(np.sum(truth ** 2, -1))))


def throws(ropes: list[str]) -> int:
    """Each built-in throw: the 250 Hz recording's velocity at its event, by both rules, against the 1000 Hz one."""
    rate = ENGINE_FRAME_RATE["newton"]
    rows = []
    for variant in ropes:
        for name in THROWS:
            coarse, fine = (generate_reference(get_hand_path(name), segments=64, variant=variant, duration=1.5,
                                               frame_rate=r, engine="newton") for r in (rate, FINE_RATE))
            event = crit.reference_event(coarse)
            j = -1 if event is None else int(np.searchsorted(fine.time, event.time, side="left"))
            if j < 3:
                print(f"{variant:10s} {name:11s} no event with three {FINE_RATE:g} Hz frames before it")
                continue
            truth = quadratic_before(fine, j, event.time)[1]
            k = event.index
            frac = (event.time - coarse.time[k - 1]) / (coarse.time[k] - coarse.time[k - 1])
            interval = _relative(crit.marker_velocity(coarse, k - 1, 1), truth)
            at_event = _relative(crit.event_velocity(coarse, k, frac), truth)
            rows.append((interval, at_event))
            print(f"{variant:10s} {name:11s} frac {frac:.2f}  relative RMS velocity error: interval {interval:.3f}  "
                  f"at the event {at_event:.3f}", flush=True)
    if rows:
        r = np.array(rows)
        print(f"{len(r)} throws: median interval {np.median(r[:, 0]):.3f}, at the event {np.median(r[:, 1]):.3f}; "
              f"at the event nearer in {int((r[:, 1] < r[:, 0]).sum())}")
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "throws" and len(argv) <= 2:
        return throws(argv[1].split(",") if len(argv) == 2 else list(ROPES))
    if len(argv) != 2:
        _fail("usage: critical_velocity.py RUN_FOLDER ARM, or critical_velocity.py throws [ROPES]")
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
