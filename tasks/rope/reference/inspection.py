"""`python -m wrenorm inspect rope FILE.npz [--json]`: what the fit would take from a reference file.

Prints the critical moment the fit uses (the annotated `critical_time` when the file has one, else the first
self-contact detected in the markers), the detection itself (time, arc-length positions, confidence and
reasons), a summary of the reconstructed gap series, bridged (occluded) samples and the simulator's own contact
when the file carries one. With --json: one JSON object on stdout, with at least `critical` (`time`, `s_a`,
`s_b`, `source`: "detected" or "annotated"; null when there is none) and `warnings` (list of strings).
Exit 0 when the file could be read (with or without an event), 2 on a bad file (one line: file, field, problem).
"""
from __future__ import annotations

import argparse
import json

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="reference rope trajectory (.npz)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout instead of text")


def inspect_reference(path) -> dict:
    """Everything `inspect` reports about one file, as plain data (raises InputError on a bad file)."""
    from wrenorm.results import jsonable
    from wrenorm.tasks.rope.observable import reference_critical
    from wrenorm.tasks.rope.reference.generate import load_reference

    ref = load_reference(path)
    crit = reference_critical(ref)
    out = crit.as_dict()
    T, M = ref.markers.shape[:2]
    missing = 0 if ref.missing is None else int(np.sum(ref.missing))
    out.update({
        "file": str(path),
        "frames": T, "frame_rate_hz": 1.0 / ref.dt, "duration_s": float(ref.time[-1] - ref.time[0]),
        "time_range_s": [float(ref.time[0]), float(ref.time[-1])], "markers": M,
        "length_m": ref.length, "radius_m": ref.radius, "mass_kg": ref.mass, "marker_offset_m": ref.marker_offset,
        "critical_time_annotation": ref.critical_time,
        "bridged_samples": missing,
        "simulator_contact": None if ref.sim_contact_time is None else {
            "time": ref.sim_contact_time if np.isfinite(ref.sim_contact_time) else None,
            "s": None if ref.sim_contact_s is None else [float(x) for x in ref.sim_contact_s]},
    })
    return jsonable(out)


def _ms(x) -> str:
    return "-" if x is None else f"{1000 * x:.1f} mm"


def run(args) -> int:
    info = inspect_reference(args.file)
    if args.json:
        print(json.dumps(info))
        return 0
    print(f"{info['file']}: {info['frames']} frames at {info['frame_rate_hz']:.4g} Hz ({info['duration_s']:.3f} s), "
          f"{info['markers']} markers; rope {info['length_m']:g} m, radius {1000 * info['radius_m']:g} mm"
          + (f"; markers up to {1000 * info['marker_offset_m']:g} mm off the centre line (marker_offset)"
             if info["marker_offset_m"] else ""))
    c = info["critical"]
    if c is None:
        print(f"critical moment: none ({info['problem']})")
    else:
        print(f"critical moment: t = {c['time']:.4f} s (frame {c['frame']}), s_a = {c['s_a']:.3f}, s_b = {c['s_b']:.3f}"
              f"; source {c['source']}, confidence {c['confidence']}")
    d = info["detected"]
    det = "none" if d is None else f"t = {d['time']:.4f} s, s_a = {d['s_a']:.3f}, s_b = {d['s_b']:.3f}"
    print(f"detected in the markers: {info['detection_status']} {det} (confidence {info['confidence']})")
    ann = info["critical_time_annotation"]
    print("annotation: " + ("none" if ann is None else f"critical_time = {ann:.4f} s overrides the detection"))
    g = info["gap_summary"]
    if g:
        within = g.get("first_within_uncertainty_time")
        print(f"gap series: closest {_ms(g.get('min_gap_m'))} at t = {g.get('min_gap_time', float('nan')):.4f} s; "
              f"{g.get('frames_in_contact', 0)} frames touching, {g.get('frames_within_uncertainty', 0)} within the "
              f"uncertainty" + ("" if within is None else f" (first at t = {within:.4f} s)")
              + f"; marker noise ~{1000 * g.get('noise_sigma_m', 0.0):.2f} mm; chord/arc "
              f"{g.get('min_chord_over_arc', 1.0):.2f}..{g.get('max_chord_over_arc', 1.0):.2f}")
    sim = info["simulator_contact"]
    if sim is not None:
        print("simulator's own first contact: " + ("none" if sim["time"] is None else f"t = {sim['time']:.4f} s"))
    for r in info["reasons"]:
        print(f"  reason: {r}")
    for w in info["warnings"]:
        if w.startswith("uncertain event: ") and w[len("uncertain event: "):] in info["reasons"]:
            continue
        print(f"  warning: {w}")
    return 0
