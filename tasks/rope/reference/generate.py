"""Reference rope trajectories (the "real" flying-knot data): file format, loader, writer, the
first self-collision, and generation with a fine newton rope.

File format (.npz): time (T,) s uniform; markers (T, M, 3) m, held end first; hand (T, 3) m;
scalars length (m), mass (kg), radius (m); optional bend_stiffness (N m^2); optional
marker_arclength (M,) in [0, 1] (default evenly spaced). Bad files raise InputError(path, field,
problem).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.tasks.rope.reference.events import CollisionEvent, first_collision

__all__ = ["RopeReference", "CollisionEvent", "load_reference", "save_reference", "first_self_collision",
           "generate_reference", "builtin_references", "add_reference_arguments", "run_reference"]

REQUIRED = ("time", "markers", "hand", "length", "mass", "radius")
OPTIONAL = ("bend_stiffness", "marker_arclength", "source")
FRAME_RATE = 250.0  # Hz: 4 ms frames resolve a tip moving at ~10 m/s to 4 cm
DEFAULT_DURATION = 1.5  # s: every built-in path collides by ~1.05 s


@dataclass
class RopeReference:
    time: np.ndarray  # (T,) s, uniform
    markers: np.ndarray  # (T, M, 3) m, held end to free end
    hand: np.ndarray  # (T, 3) m
    length: float  # m
    mass: float  # kg
    radius: float  # m
    bend_stiffness: float | None  # N m^2
    marker_arclength: np.ndarray  # (M,) in [0, 1]
    source: str = ""

    @property
    def dt(self) -> float:
        return float(self.time[1] - self.time[0])


def first_self_collision(ref: RopeReference, exclude_arclength: float | None = None) -> CollisionEvent | None:
    """First frame where two non-neighbouring parts of the marker polyline are within a rope
    diameter; see :mod:`wrenorm.tasks.rope.reference.events`."""
    return first_collision(ref.time, ref.markers, ref.marker_arclength, ref.length, ref.radius, exclude_arclength)


# ---------------------------------------------------------------------------------------------- loading

def _array(src: str, name: str, value) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "iuf":
        raise InputError(src, name, f"must be a real number array, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(src, name, "contains NaN or Inf")
    return a


def _scalar(src: str, name: str, value, lo: float, hi: float, unit: str) -> float:
    a = _array(src, name, value)
    if a.size != 1:
        raise InputError(src, name, f"must be a single number, got shape {a.shape}")
    x = float(a.reshape(()))
    if not lo <= x <= hi:
        raise InputError(src, name, f"{x:g} {unit} is outside the plausible range [{lo:g}, {hi:g}] {unit}")
    return x


def validate_arrays(src: str, data: dict) -> RopeReference:
    """Check every field of a reference given as a dict of arrays; returns the RopeReference."""
    for key in REQUIRED:
        if key not in data:
            raise InputError(src, key, f"missing required field (need {', '.join(REQUIRED)})")
    length = _scalar(src, "length", data["length"], 0.05, 20.0, "m")
    mass = _scalar(src, "mass", data["mass"], 1e-4, 1e3, "kg")
    if mass <= 0:
        raise InputError(src, "mass", "must be > 0")
    radius = _scalar(src, "radius", data["radius"], 0.0, length, "m")
    if not 0.0 < radius < 0.25 * length:
        raise InputError(src, "radius", f"{radius:g} m must be > 0 and well below the length {length:g} m")
    bend = None
    if data.get("bend_stiffness") is not None:
        bend = _scalar(src, "bend_stiffness", data["bend_stiffness"], 0.0, 1e3, "N m^2")

    time = _array(src, "time", data["time"])
    if time.ndim != 1 or time.shape[0] < 2:
        raise InputError(src, "time", f"must have shape (T,) with T >= 2, got {time.shape}")
    dt = np.diff(time)
    if not np.all(dt > 0):
        raise InputError(src, "time", "must be strictly increasing")
    mean_dt = (time[-1] - time[0]) / (len(time) - 1)
    if np.max(np.abs(dt - mean_dt)) > 1e-3 * mean_dt + 1e-9:
        raise InputError(src, "time", f"must be uniformly spaced (steps range {dt.min():g}..{dt.max():g} s)")
    if not 1e-5 <= mean_dt <= 0.1:
        raise InputError(src, "time", f"frame step {mean_dt:g} s is outside [1e-5, 0.1] s (seconds expected)")
    T = time.shape[0]

    markers = _array(src, "markers", data["markers"])
    if markers.ndim != 3 or markers.shape[0] != T or markers.shape[2] != 3 or markers.shape[1] < 2:
        raise InputError(src, "markers", f"must have shape ({T}, M>=2, 3), got {markers.shape}")
    M = markers.shape[1]
    hand = _array(src, "hand", data["hand"])
    if hand.shape != (T, 3):
        raise InputError(src, "hand", f"must have shape ({T}, 3), got {hand.shape}")

    if data.get("marker_arclength") is not None:
        s = _array(src, "marker_arclength", data["marker_arclength"])
        if s.shape != (M,):
            raise InputError(src, "marker_arclength", f"must have shape ({M},), got {s.shape}")
        if s.min() < 0.0 or s.max() > 1.0 or not np.all(np.diff(s) > 0):
            raise InputError(src, "marker_arclength", "must be strictly increasing inside [0, 1]")
    else:
        s = np.linspace(0.0, 1.0, M)

    # Units: a rope in millimetres sits hundreds of "metres" away or has links 1000x too long.
    box = 100.0
    if np.abs(markers).max() > box or np.abs(hand).max() > box:
        raise InputError(src, "markers" if np.abs(markers).max() > box else "hand",
                         f"coordinates beyond {box:g} m: metres expected (millimetres?)")
    chord = np.linalg.norm(np.diff(markers, axis=1), axis=2)  # (T, M-1)
    arc = np.diff(s) * length
    # A chord can never exceed its arc; 10 % slack for stretch and marker noise.
    worst = np.max(chord / arc[None, :])
    if worst > 1.1 + 0.002 / max(arc.min(), 1e-9):
        raise InputError(src, "markers", f"marker spacing up to {worst:.3g}x the arc length between markers "
                                         f"(length {length:g} m): wrong units or wrong length?")
    reach = np.linalg.norm(markers[:, 0] - hand, axis=1).max()
    allowed = s[0] * length * 1.1 + 0.05 * length + 0.01
    if reach > allowed:
        raise InputError(src, "markers", f"first marker is up to {reach:.3g} m from the hand, expected within "
                                         f"{allowed:.3g} m (marker 0 is the held end)")
    source = ""
    if data.get("source") is not None:
        source = str(np.asarray(data["source"]).reshape(-1)[0]) if np.asarray(data["source"]).size else ""
    return RopeReference(time, markers, hand, length, mass, radius, bend, s, source)


def load_reference(path) -> RopeReference:
    src = str(path)
    p = Path(path)
    if not p.exists():
        raise InputError(src, "file", "does not exist")
    if not p.is_file():
        raise InputError(src, "file", "is not a regular file")
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
    except OSError as e:
        raise InputError(src, "file", f"cannot be read: {e.strerror or e}") from None
    if head[:2] != b"PK":
        raise InputError(src, "file", "is not an .npz archive (no zip header)")
    data = {}
    try:
        with np.load(p, allow_pickle=False) as npz:
            for key in npz.files:
                if key in REQUIRED or key in OPTIONAL:
                    data[key] = npz[key]
    except InputError:
        raise
    except Exception as e:  # any failure to parse the archive is a bad file, not a crash
        raise InputError(src, "file", f"is not a readable .npz archive: {e}") from None
    if "source" in data and data["source"].dtype.kind not in "US":
        raise InputError(src, "source", "must be a string")
    return validate_arrays(src, data)


def save_reference(path, ref: RopeReference) -> None:
    """Validate, then write compressed npz atomically (temp file in the same folder + os.replace)."""
    path = Path(path)
    data = {"time": ref.time, "markers": ref.markers, "hand": ref.hand, "length": ref.length,
            "mass": ref.mass, "radius": ref.radius, "marker_arclength": ref.marker_arclength,
            "source": ref.source}
    if ref.bend_stiffness is not None:
        data["bend_stiffness"] = ref.bend_stiffness
    validate_arrays(str(path), {k: (np.asarray(v) if k != "source" else v) for k, v in data.items()})
    out = {k: np.asarray(v) for k, v in data.items()}
    # float32 keeps shipped files small; sub-micrometre rounding is far below any rope effect.
    out["markers"] = out["markers"].astype(np.float32)
    out["hand"] = out["hand"].astype(np.float32)
    out["source"] = np.array(str(ref.source))
    folder = path.parent if str(path.parent) else Path(".")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as e:
        raise InputError(str(path), "file", f"cannot be written: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(fh, **out)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; give the file the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# -------------------------------------------------------------------------------------------- generation

def generate_reference(path_name, out=None, segments: int = 64, variant: str = "default",
                       duration: float = DEFAULT_DURATION, markers: int | None = None,
                       frame_rate: float = FRAME_RATE, substeps_per_frame: int = 8, iterations: int = 10,
                       device: str = "cpu", progress=None) -> RopeReference:
    """Simulate the fine newton rope along a hand path and (if out is given) save it.

    markers: number of markers (subsampled nodes, held end and free end included); default all
    segments+1 nodes. The polyline through all nodes is exactly newton's capsule centre line, so the
    reference's collision detector sees the contact geometry the fine simulation resolved (33
    markers on 64 segments cut corners of the curled tip and called one contact 0.16 s early).
    """
    from wrenorm.tasks.rope.reference.materials import get_variant
    from wrenorm.tasks.rope.reference.newton import simulate
    from wrenorm.tasks.rope.reference.paths import HandPath, get_hand_path

    if isinstance(path_name, HandPath):
        hand_path, label = path_name, "custom"
    else:
        hand_path, label = get_hand_path(path_name), path_name
    material = get_variant(variant)
    if not 0.05 <= duration <= 30.0:
        raise InputError("--duration", "duration", f"{duration:g} s is outside [0.05, 30] s")
    if not 4 <= segments <= 1024:
        raise InputError("--segments", "segments", f"{segments} is outside [4, 1024]")
    run = simulate(hand_path, material, segments=segments, duration=duration, frame_rate=frame_rate,
                   substeps_per_frame=substeps_per_frame, iterations=iterations, device=device,
                   progress=progress)
    n_nodes = segments + 1
    m = n_nodes if markers is None else int(markers)
    if not 2 <= m <= n_nodes:
        raise InputError("--markers", "markers", f"{m} is outside [2, {n_nodes}]")
    idx = np.unique(np.round(np.linspace(0, segments, m)).astype(int))
    ref = RopeReference(
        time=run.time, markers=run.nodes[:, idx], hand=run.hand, length=material.length, mass=material.mass,
        radius=material.radius, bend_stiffness=material.bend_stiffness, marker_arclength=idx / segments,
        source=(f"newton {_newton_version()} SolverVBD rod: path={label} variant={variant} segments={segments} "
                f"substep={1.0 / (frame_rate * (substeps_per_frame + substeps_per_frame % 2)):.2e}s "
                f"iterations={iterations} wall={run.wall_s:.1f}s"))
    if out is not None:
        save_reference(out, ref)
    return ref


def _newton_version() -> str:
    try:
        import newton

        return str(newton.__version__)
    except Exception:  # version string is informational only
        return "?"


def cache_dir() -> Path:
    return Path(os.environ.get("WRENORM_CACHE") or Path.home() / ".cache" / "wrenorm")


def builtin_reference_path(path_name: str, variant: str = "default") -> Path:
    """Where the reference lives: shipped in wrenorm/data, else the user cache."""
    from wrenorm import data as data_pkg

    name = f"rope_{variant}_{path_name}.npz"
    shipped = Path(data_pkg.__file__).parent / name
    return shipped if shipped.exists() else cache_dir() / name


def builtin_references(kind: str = "fit", variant: str = "default", progress=None) -> list[RopeReference]:
    """The built-in references of one kind ("fit" or "held_out"); generated and cached when not shipped."""
    from wrenorm.tasks.rope.reference.paths import FIT_PATHS, HELD_OUT_PATHS

    names = {"fit": FIT_PATHS, "held_out": HELD_OUT_PATHS}.get(kind)
    if names is None:
        raise InputError("builtin_references", "kind", f"{kind!r} is not 'fit' or 'held_out'")
    refs = []
    for name in names:
        p = builtin_reference_path(name, variant)
        if p.exists():
            ref = load_reference(p)
        else:
            if progress is not None:
                progress(f"generating reference rope {variant}/{name} into {p}")
            ref = generate_reference(name, p, variant=variant)
        refs.append(ref)  # whether it hits itself is checked once, where its event is needed
    return refs


# --------------------------------------------------------------------------------------------------- CLI

def add_reference_arguments(parser: argparse.ArgumentParser) -> None:
    from wrenorm.tasks.rope.reference.materials import VARIANTS
    from wrenorm.tasks.rope.reference.paths import builtin_hand_paths

    parser.add_argument("--out", required=True, help="output .npz file (written atomically)")
    parser.add_argument("--path", default="flick", choices=sorted(builtin_hand_paths()), help="hand path")
    parser.add_argument("--segments", type=int, default=64, help="rod segments of the fine rope")
    parser.add_argument("--variant", default="default", choices=sorted(VARIANTS), help="rope material")
    parser.add_argument("--duration", type=float, default=DEFAULT_DURATION, help="simulated seconds")
    parser.add_argument("--markers", type=int, default=None, help="markers to keep (default: every node)")


def run_reference(args) -> int:
    def progress(done, total, wall):
        print(f"  frame {done}/{total}  wall {wall:.1f} s", flush=True)

    print(f"simulating rope variant={args.variant} path={args.path} segments={args.segments} "
          f"duration={args.duration:g} s with newton SolverVBD", flush=True)
    ref = generate_reference(args.path, args.out, segments=args.segments, variant=args.variant,
                             duration=args.duration, markers=getattr(args, "markers", None), progress=progress)
    ev = first_self_collision(ref)
    hit = "never" if ev is None else f"t = {ev.time:.4f} s (frame {ev.index}, s = {ev.s_a:.3f} / {ev.s_b:.3f})"
    print(f"wrote {args.out}: {len(ref.time)} frames x {ref.markers.shape[1]} markers; first self-collision {hit}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m wrenorm.tasks.rope.reference.generate",
                                     description="Generate a fine reference rope trajectory with newton.")
    add_reference_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_reference(args)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
