"""Measure the event detector against fine simulations whose contact is known (README, "Events in motion capture").

    python -m wrenorm.tasks.rope.reference.evaluate generate --engine mujoco --out DIR [--variants ...]
        [--paths ...] [--perturb-seeds ...] [--frame-rate 200] [--markers 12]
    python -m wrenorm.tasks.rope.reference.evaluate score DIR [--markers 8 12 24] [--noise 0.001]
        [--occlude 3] [--seed 1] [--json OUT]

`generate` writes one reference per (variant, throw) with every node kept (`dense_nodes`) and the simulator's own
first contact (`sim_contact_time`). `score` resamples each file's dense nodes to M markers at even arc length,
optionally adds Gaussian marker noise (sigma, m) and occlusions (runs of 1-4 NaN frames on random markers), runs
the detector, and counts per file (tolerance 20 ms on the simulator's contact time):

  right          contact reported within 20 ms; "false flag" when it is flagged (low confidence)
  flagged        wrong (late, early, missed) but flagged or declared unusable: never used silently
  silent         wrong and unflagged, or "no contact" while the simulator had one: must never happen
  (kiss)         the silent ones where the dense rope came within 0.5 mm of touching within 20 ms of the detected
                 time: a near-touch no marker set resolves, counted apart so that the table says what it is

Files without a simulator contact count as right when the detector says "no contact" or flags, silent when it
reports an unflagged contact.
"""
from __future__ import annotations

import argparse
import json
import sys
import time as _time
import zipfile
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.options import add_number, add_numbers, number

TOL = 0.02  # s
KISS = 5e-4  # m


def _field(z, path: Path, name: str) -> np.ndarray:
    from wrenorm.tasks.rope.reference.generate import _array

    if name not in z.files:
        raise InputError(str(path), name, "missing")
    return _array(str(path), name, z[name], allow_nan=True)


def _truth_and_nodes(path: Path):
    """The file's frames, dense nodes, hand, length, radius and known first contact, checked as the loader checks
    them: a time axis in milliseconds had been scored as a detector 1450 ms off (review of stop 54)."""
    from wrenorm.tasks.rope.reference.generate import time_axis

    z = np.load(path, allow_pickle=False)
    if "time" not in z.files:
        raise InputError(str(path), "time", "missing")
    time, _ = time_axis(str(path), z["time"])
    if "dense_nodes" in z.files:
        nodes = _field(z, path, "dense_nodes")
    elif "markers" in z.files and z["markers"].ndim == 3 and z["markers"].shape[1] >= 33:
        nodes = _field(z, path, "markers")  # a file that kept every node as its markers
    else:
        raise InputError(str(path), "dense_nodes", "missing: generate with --dense (or keep every node as markers)")
    if nodes.ndim != 3 or nodes.shape[0] != len(time) or nodes.shape[2] != 3:
        raise InputError(str(path), "dense_nodes", f"must have shape ({len(time)}, N, 3), got {nodes.shape}")
    hand = _field(z, path, "hand")
    if hand.shape != (len(time), 3):
        raise InputError(str(path), "hand", f"must have shape ({len(time)}, 3), got {hand.shape}")
    length, radius = float(_field(z, path, "length")), float(_field(z, path, "radius"))
    t_sim = float(_field(z, path, "sim_contact_time")) if "sim_contact_time" in z.files else None
    if t_sim is None:  # the physics definition on the dense centre line
        from wrenorm.tasks.rope.reference.generate import _dense_first_contact

        t_sim = _dense_first_contact(time, nodes, length, radius)[0]
    elif np.isfinite(t_sim) and not time[0] <= t_sim <= time[-1]:
        raise InputError(str(path), "sim_contact_time", f"{t_sim:g} s is outside the file's time axis ({time[0]:g}, "
                         f"{time[-1]:g}) s")
    return time, nodes, hand, length, radius, (t_sim if np.isfinite(t_sim) else None)


def classify(status: str, flagged: bool, t_det, t_true) -> str:
    if t_true is None:
        if status == "no_contact":
            return "right"
        return "silent" if status == "contact" and not flagged else "flagged"
    if status == "contact" and abs(t_det - t_true) <= TOL:
        return "false_flag" if flagged else "right"
    if status == "no_contact" or (status == "contact" and not flagged):
        return "silent"
    return "flagged"


def contact_gaps(time, s: np.ndarray, t_true: float, s_true, count: int, rng, at: str = "contact") -> list:
    """`count` long occlusions, each (markers, first frame, last frame + 1): 1-3 adjacent markers missing for 30-500
    ms (never marker 0, which the hand stands in for). at "contact": one of the markers is the one nearest either
    contact point and the contact lies at a uniformly drawn place inside the gap, the occlusions that can hide a
    contact from the bridged markers (README, "Events in motion capture"); "before": any markers, the gap ending at
    least 50 ms before the contact, the occlusions that should cost nothing."""
    gaps = []
    dt = float(time[1] - time[0])
    k_true = int(np.searchsorted(time, t_true))
    for _ in range(count):  # the draws in this order, so that a seed repeats the README's gaps
        if at == "before":
            k = int(rng.integers(1, 4))
            first = int(rng.integers(1, len(s) - k + 1))
            room = max(1, k_true - int(round(0.050 / dt)))
            n = min(max(1, int(round(rng.uniform(0.030, 0.500) / dt))), room)
            start = int(rng.integers(0, room - n + 1))
        else:
            near = int(np.argmin(np.abs(s - s_true[int(rng.integers(0, 2))])))
            k = int(rng.integers(1, 4))
            first = int(np.clip(near - int(rng.integers(0, k)), 1, len(s) - k))
            n = max(1, int(round(rng.uniform(0.030, 0.500) / dt)))
            start = int(np.clip(k_true - int(rng.integers(0, n)), 0, len(time) - n))
        gaps.append((list(range(first, first + k)), start, start + n))
    return gaps


def score(files, markers: int, noise: float = 0.0, occlude: int = 0, seed: int = 1, verbose: bool = False,
          gaps: int = 0, gaps_at: str = "contact"):
    """One row per file, or with `gaps` one row per long occlusion over each file's known contact (contact_gaps;
    files without a contact are skipped then)."""
    from wrenorm.tasks.rope.reference.generate import resample_nodes

    rng = np.random.default_rng(seed)
    rows = []
    for f in files:
        try:
            time, nodes, hand, length, radius, t_true = _truth_and_nodes(f)
        except (InputError, KeyError, ValueError, OSError, zipfile.BadZipFile) as e:  # one foreign file: that file
            why = f"{e.field}: {e.problem}" if isinstance(e, InputError) else e
            print(f"{f}: left out: {why}", file=sys.stderr, flush=True)
            continue
        mk0, s = resample_nodes(nodes, markers)
        if gaps:
            if t_true is None:
                continue
            z = np.load(f, allow_pickle=False)
            if "sim_contact_s" not in z.files or not np.all(np.isfinite(z["sim_contact_s"])):
                raise SystemExit(f"{f}: sim_contact_s: needed to place the gaps over the contact")
            cases = [(g, f"{Path(f).stem}#gap{i}") for i, g in enumerate(
                contact_gaps(time, s, t_true, z["sim_contact_s"], gaps, rng, gaps_at))]
        else:
            cases = [(None, Path(f).stem)]
        for gap, name in cases:
            rows.append(_score_one(time, nodes, hand, length, radius, t_true, mk0, s, gap, name, markers, noise,
                                   occlude, rng, verbose))
    return rows


def _score_one(time, nodes, hand, length, radius, t_true, mk0, s, gap, name, markers, noise, occlude, rng,
               verbose) -> dict:
    from wrenorm.tasks.rope.reference.events import detect, polyline_gap

    mk = mk0.copy()
    if noise > 0:
        mk = mk + rng.normal(0.0, noise, mk.shape)
    for _ in range(occlude):
        m, n = int(rng.integers(1, markers)), int(rng.integers(1, 5))
        s0 = int(rng.integers(0, len(time) - n))
        mk[s0:s0 + n, m] = np.nan
    if gap is not None:
        ms, a, b = gap
        mk[a:b, ms] = np.nan
    t0 = _time.perf_counter()
    det = detect(time, mk, s, length, radius, hand=hand)
    wall = _time.perf_counter() - t0
    cat = classify(det.status, det.flagged, det.time, t_true)
    kiss = None
    if cat == "silent" and det.time is not None:
        k = int(np.searchsorted(time, det.time))
        w = slice(max(0, k - 4), k + 5)
        kiss = float(polyline_gap(nodes[w], np.linspace(0, 1, nodes.shape[1]), length, radius)[0].min())
    row = {"file": name, "truth": t_true, "status": det.status, "confidence": det.confidence, "time": det.time,
           "category": cat, "rules": det.diagnostics.get("rules_fired", []), "reasons": det.reasons, "wall_s": wall,
           "dense_gap_near_detection_m": kiss}
    if gap is not None:
        row["gap"] = {"markers": gap[0], "from_s": float(time[gap[1]]), "to_s": float(time[gap[2] - 1])}
    if verbose:
        off = "-" if det.time is None or t_true is None else f"{1000 * (det.time - t_true):+.1f} ms"
        print(f"M={markers:2d} {name:36s} {det.status:10s} {det.confidence:5s} {off:>10s} {cat} {row['rules']}",
              flush=True)
    return row


def summarise(rows) -> dict:
    cats = [r["category"] for r in rows]
    with_contact = sum(r["truth"] is not None for r in rows)
    kisses = sum(r["category"] == "silent" and r["dense_gap_near_detection_m"] is not None
                 and r["dense_gap_near_detection_m"] < KISS for r in rows)
    right = cats.count("right") + cats.count("false_flag")
    return {"files": len(rows), "with_contact": with_contact,
            "within_20ms": sum(c in ("right", "false_flag") for c, r in zip(cats, rows) if r["truth"] is not None),
            "right": right, "false_flags": cats.count("false_flag"), "flagged": cats.count("flagged"),
            "silent": cats.count("silent"), "silent_kisses": kisses,
            "wall_median_s": float(np.median([r["wall_s"] for r in rows])) if rows else None}


def generate(args) -> int:
    from wrenorm.tasks.rope.reference.generate import generate_reference

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(v, p, None) for v in args.variants for p in args.paths]
    jobs += [(v, args.perturb_paths[i % len(args.perturb_paths)], int(s)) for v in args.variants
             for i, s in enumerate(args.perturb_seeds)]
    if not jobs:
        print("generate: nothing to make: --paths and --perturb-seeds are both empty", file=sys.stderr)
        return 2
    failed, said = 0, set()
    made_with = json.dumps({k: getattr(args, k) for k in ("frame_rate", "timestep", "markers", "duration", "segments",
                                                          "annotate")}, sort_keys=True)
    for variant, path, seed in jobs:
        name = f"{args.engine}_{variant}_{path}" + ("" if seed is None else f"_p{seed}")
        f = out / f"{name}.npz"
        if f.exists():
            try:
                with np.load(f, allow_pickle=False) as z:
                    before = str(z["generate_settings"]) if "generate_settings" in z.files else None
            except (OSError, ValueError, zipfile.BadZipFile) as e:
                print(f"{f}: exists and cannot be read ({e}): left as it is; use another --out", file=sys.stderr)
                failed += 1
                continue
            if before is not None and before != made_with:
                print(f"{f}: made with other settings ({before}; now {made_with}): left as it is and not made again; "
                      "use another --out", file=sys.stderr, flush=True)
                failed += 1
            else:
                print(f"{name}: kept (already in {out})", flush=True)
            continue
        t0 = _time.perf_counter()
        try:
            ref = generate_reference(path, f, variant=variant, engine=args.engine, frame_rate=args.frame_rate,
                                     timestep=args.timestep, markers=args.markers, perturb=seed, dense=True,
                                     duration=args.duration, annotate=args.annotate, extra={"generate_settings":
                                                                                            np.array(made_with)},
                                     **({} if args.segments is None else {"segments": args.segments}))
        except InputError as e:  # one throw this engine cannot make costs that throw, not the set
            if str(e) not in said:  # an option every throw shares fails every throw: said once
                print(f"{name}: {e} (skipped; so is every later throw with this problem)", file=sys.stderr,
                      flush=True)
                said.add(str(e))
            failed += 1
            continue
        hit = ref.sim_contact_time
        print(f"{name}: simulator contact {'none' if not np.isfinite(hit) else f'{hit:.4f} s'} "
              f"({_time.perf_counter() - t0:.1f} s)", flush=True)
    if failed:
        print(f"{failed} of {len(jobs)} throws could not be made (above)", file=sys.stderr)
    return 2 if failed and failed == len(jobs) else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m wrenorm.tasks.rope.reference.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="simulate a set of references with dense nodes")
    g.add_argument("--engine", choices=["newton", "mujoco"], default="mujoco")
    g.add_argument("--out", required=True)
    g.add_argument("--variants", nargs="+", default=["default"])
    g.add_argument("--paths", nargs="*", default=["flick", "flick_fast", "flick_wide", "flick_high", "flick_slow"],
                   help="built-in paths thrown as they are (none: only the perturbed throws)")
    g.add_argument("--perturb-paths", nargs="+", default=["flick", "flick_fast", "flick_wide", "flick_high",
                                                          "flick_slow"], help="seed i perturbs path i mod their number")
    g.add_argument("--perturb-seeds", nargs="*", type=number(lo=0, integer=True), default=[])
    g.add_argument("--frame-rate", type=float, default=200.0)
    g.add_argument("--timestep", type=float, default=None,
                   help="the fine rope's longest physics step (default the engine's: newton 5e-4, mujoco 2.5e-4 s); "
                        "newton sets made before this option ran at 200 Hz with 0.625 ms steps")
    g.add_argument("--markers", type=int, default=12)
    g.add_argument("--duration", type=float, default=1.5)
    g.add_argument("--segments", type=int, default=None,
                   help="segments of the fine rope (default the generator's 64; MuJoCo's thick rope takes at most 39)")
    g.add_argument("--annotate", action="store_true", help="store the simulator's contact as critical_time")
    s = sub.add_parser("score", help="score the detector on a folder of references")
    s.add_argument("dirs", nargs="+")
    add_numbers(s, "--markers", default=[8, 12, 24], lo=2, integer=True, help="marker counts to score")
    add_number(s, "--noise", default=0.0, lo=0.0, unit="m", help="marker noise sigma")
    add_number(s, "--occlude", default=0, lo=0, integer=True, help="occlusions per file (1-4 frames each)")
    s.add_argument("--gaps", type=int, default=0,
                   help="score each file with a contact this many times, each with 1-3 markers next to the contact "
                        "missing for 30-500 ms over it (files without a contact are skipped)")
    s.add_argument("--gaps-at", choices=("contact", "before"), default="contact",
                   help="where --gaps lie: over the contact, beside its markers (contact), or on any markers, ending "
                        "at least 50 ms before it (before)")
    add_number(s, "--seed", default=1, lo=0, integer=True)
    s.add_argument("--json", default=None, help="write every row and the summaries here")
    s.add_argument("--force", action="store_true", help="replace an existing --json file")
    s.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    if a.cmd == "generate":
        return generate(a)
    if a.gaps < 0:
        print(f"score: --gaps: {a.gaps} is below 0 (gaps per file with a contact)", file=sys.stderr)
        return 2
    for d in a.dirs:
        if not Path(d).is_dir() or not any(Path(d).glob("*.npz")):
            print(f"score: {d}: {'is not a folder' if not Path(d).is_dir() else 'holds no .npz reference'} (a folder "
                  "that `generate` wrote)", file=sys.stderr)
            return 2
    if a.json and Path(a.json).exists() and not a.force:
        print(f"score: {a.json}: --json: exists; --force replaces it", file=sys.stderr)
        return 2
    files = sorted(f for d in a.dirs for f in Path(d).glob("*.npz"))
    result = {}
    for m in a.markers:
        rows = score(files, m, a.noise, a.occlude, a.seed, a.verbose, a.gaps, a.gaps_at)
        if not rows and not a.gaps:  # with --gaps, files without a contact are skipped by design
            print(f"score: none of the {len(files)} files could be scored (each left out above)", file=sys.stderr)
            return 2
        result[str(m)] = {"summary": summarise(rows), "rows": rows}
        print(f"{m} markers: {json.dumps(result[str(m)]['summary'])}", flush=True)
    if a.json:
        from wrenorm.results import write_json

        write_json(a.json, {"dirs": a.dirs, "noise": a.noise, "occlude": a.occlude, "gaps": a.gaps,
                            "gaps_at": a.gaps_at, "seed": a.seed, "results": result})
    return 0


if __name__ == "__main__":
    sys.exit(main())
