"""Robot command for the flying-knot rope: a vector u of offsets of a hand path's Bezier
waypoints in space and time, with box bounds and the hand's speed/acceleration limits.

A C1 hand path (``HandPath.through``) is a chain of cubic Bezier segments whose interior control
points are fixed by the waypoints (t_i, p_i, v_i): moving a waypoint position or velocity moves
three control points together, which keeps the path C1 (a lone control point would put a kink,
i.e. an infinite acceleration, into the hand motion). So u acts on waypoints:

  for every waypoint after the first:  position offset on each of `axes`, / POSITION_SCALE
  for every interior waypoint:         velocity offset on each of `axes`, / VELOCITY_SCALE
  for every segment:                   log of its duration ratio,        / LOG_TIME_SCALE

The first waypoint is fixed (the rope hangs still below it at t=0) and the end velocities stay 0
(the hand starts and ends at rest). Units of u are these scales, so a unit step is 5 cm, 0.5 m/s
or 10 % of a segment's time: comparable "sizes" of command change for the QP's regulariser.
The default axes are x and z: the built-in throws are planar, and a sideways offset lets the
loop miss the rope (see rope_paths).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError
from wrenorm.tasks.rope.reference.paths import DEFAULT_MAX_ACCELERATION, DEFAULT_MAX_SPEED, HandPath

POSITION_SCALE = 0.05  # m per unit of u
VELOCITY_SCALE = 0.5  # m/s per unit of u
LOG_TIME_SCALE = 0.1  # natural-log duration ratio per unit of u
DEFAULT_BOUND = 3.0  # |u_i| <= 3: 15 cm, 1.5 m/s, x1.35 in time around the start command
AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def waypoints(path: HandPath) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times (K+1,), points (K+1, 3), velocities (K+1, 3)) of a Bezier chain.

    A waypoint's velocity is taken from its outgoing segment (the last one's from its incoming
    segment); for a C1 path both sides agree.
    """
    cp, d = path.control_points, path.durations
    times = np.concatenate([[0.0], np.cumsum(d)])
    pts = cp[0::3].copy()
    vel = np.zeros_like(pts)
    for k in range(len(d)):
        vel[k] = 3.0 * (cp[3 * k + 1] - cp[3 * k]) / d[k]
    vel[-1] = 3.0 * (cp[-1] - cp[-2]) / d[-1]
    return times, pts, vel


@dataclass(frozen=True)
class CommandSpace:
    """u <-> HandPath around a base path (u = 0 is the base)."""

    base: HandPath
    axes: tuple = ("x", "z")
    bound: float = DEFAULT_BOUND
    max_speed: float = DEFAULT_MAX_SPEED
    max_acceleration: float = DEFAULT_MAX_ACCELERATION

    def __post_init__(self):
        bad = [a for a in self.axes if a not in AXIS_INDEX]
        if bad or not self.axes or len(set(self.axes)) != len(self.axes):
            raise InputError("CommandSpace", "axes", f"need distinct axes from x, y, z; got {self.axes}")
        if not self.bound > 0:
            raise InputError("CommandSpace", "bound", f"must be > 0, got {self.bound}")
        t, p, v = waypoints(self.base)
        # u only describes C1 paths; a kinked base would be silently smoothed by decode(encode()).
        for k in range(1, len(t) - 1):
            d0, d1 = self.base.durations[k - 1], self.base.durations[k]
            cp = self.base.control_points
            v_in = 3.0 * (cp[3 * k] - cp[3 * k - 1]) / d0
            v_out = 3.0 * (cp[3 * k + 1] - cp[3 * k]) / d1
            if np.linalg.norm(v_in - v_out) > 1e-6 * (1.0 + np.linalg.norm(v_out)):
                raise InputError("CommandSpace", "base", f"hand path is not C1 at waypoint {k}")
        if np.linalg.norm(v[0]) > 1e-9 or np.linalg.norm(v[-1]) > 1e-9:
            raise InputError("CommandSpace", "base", "hand path must start and end at rest")

    # ------------------------------------------------------------------ layout
    @property
    def n_segments(self) -> int:
        return len(self.base.durations)

    @property
    def names(self) -> list[str]:
        K, out = self.n_segments, []
        for i in range(1, K + 1):
            out += [f"p{i}.{a}" for a in self.axes]
            if i < K:
                out += [f"v{i}.{a}" for a in self.axes]
        out += [f"log_T{k + 1}" for k in range(K)]
        return out

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def scales(self) -> np.ndarray:
        """Physical size of one unit of each u component (m, m/s or log ratio)."""
        return np.array([POSITION_SCALE if n[0] == "p" else VELOCITY_SCALE if n[0] == "v" else LOG_TIME_SCALE
                         for n in self.names])

    @property
    def lower(self) -> np.ndarray:
        return np.full(self.dim, -self.bound)

    @property
    def upper(self) -> np.ndarray:
        return np.full(self.dim, self.bound)

    # ------------------------------------------------------------------ mapping
    def decode(self, u) -> HandPath:
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        if u.shape[0] != self.dim or not np.all(np.isfinite(u)):
            raise InputError("command", "u", f"need {self.dim} finite numbers, got shape {u.shape}")
        t, p, v = waypoints(self.base)
        p, v = p.copy(), v.copy()
        ax = [AXIS_INDEX[a] for a in self.axes]
        K, j = self.n_segments, 0
        for i in range(1, K + 1):
            p[i, ax] += u[j:j + len(ax)] * POSITION_SCALE
            j += len(ax)
            if i < K:
                v[i, ax] += u[j:j + len(ax)] * VELOCITY_SCALE
                j += len(ax)
        d = self.base.durations * np.exp(u[j:j + K] * LOG_TIME_SCALE)
        return HandPath.through(np.concatenate([[0.0], np.cumsum(d)]), p, v)

    def encode(self, path: HandPath) -> np.ndarray:
        """u of a path with the same waypoint structure and start point (exact inverse of decode)."""
        if len(path.durations) != self.n_segments:
            raise InputError("command", "path", f"has {len(path.durations)} segments, the command space "
                                                f"{self.n_segments}")
        t0, p0, v0 = waypoints(self.base)
        t1, p1, v1 = waypoints(path)
        ax = [AXIS_INDEX[a] for a in self.axes]
        off = [a for a in range(3) if a not in ax]
        if np.abs(p1[0] - p0[0]).max() > 1e-9 or (off and np.abs((p1 - p0)[:, off]).max() > 1e-9) \
                or (off and np.abs((v1 - v0)[:, off]).max() > 1e-9):
            raise InputError("command", "path", "differs from the base outside the command's axes or start point")
        K, u = self.n_segments, []
        for i in range(1, K + 1):
            u += list((p1[i, ax] - p0[i, ax]) / POSITION_SCALE)
            if i < K:
                u += list((v1[i, ax] - v0[i, ax]) / VELOCITY_SCALE)
        u += list(np.log(path.durations / self.base.durations) / LOG_TIME_SCALE)
        return np.array(u)

    # ------------------------------------------------------------------ batches
    def batch_waypoints(self, U) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """decode() for many commands at once: (times (B, K+1), points (B, K+1, 3), velocities)."""
        U = np.atleast_2d(np.asarray(U, dtype=np.float64))
        B, K = U.shape[0], self.n_segments
        t, p, v = waypoints(self.base)
        P, V = np.repeat(p[None], B, 0), np.repeat(v[None], B, 0)
        ax = [AXIS_INDEX[a] for a in self.axes]
        j = 0
        for i in range(1, K + 1):
            P[:, i, ax] += U[:, j:j + len(ax)] * POSITION_SCALE
            j += len(ax)
            if i < K:
                V[:, i, ax] += U[:, j:j + len(ax)] * VELOCITY_SCALE
                j += len(ax)
        d = self.base.durations[None] * np.exp(U[:, j:j + K] * LOG_TIME_SCALE)
        return np.concatenate([np.zeros((B, 1)), np.cumsum(d, 1)], 1), P, V

    def batch_positions(self, U, times) -> np.ndarray:
        """(B, T, 3) hand positions of many commands (cubic Hermite, as HandPath.through builds)."""
        T, P, V = self.batch_waypoints(U)
        B, K = T.shape[0], self.n_segments
        t = np.clip(np.asarray(times, dtype=np.float64)[None, :], 0.0, T[:, -1:])
        k = np.clip((t[:, :, None] >= T[:, None, 1:K]).sum(-1), 0, K - 1)  # (B, T) segment index
        r = np.arange(B)[:, None]
        t0, d = T[r, k], T[r, k + 1] - T[r, k]
        s = np.clip((t - t0) / d, 0.0, 1.0)[..., None]
        d = d[..., None]
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        return h00 * P[r, k] + h10 * d * V[r, k] + h01 * P[r, k + 1] + h11 * d * V[r, k + 1]

    def batch_peaks(self, U, per_segment: int = 200) -> tuple[np.ndarray, np.ndarray]:
        """(peak speed (B,), peak acceleration (B,)) on HandPath's own per-segment grid."""
        T, P, V = self.batch_waypoints(U)
        s = np.linspace(0.0, 1.0, per_segment)[None, None, :, None]
        d = np.diff(T, axis=1)[:, :, None, None]
        p0, p1, v0, v1 = P[:, :-1, None], P[:, 1:, None], V[:, :-1, None] * d, V[:, 1:, None] * d
        vel = ((6 * s**2 - 6 * s) * p0 + (3 * s**2 - 4 * s + 1) * v0 + (-6 * s**2 + 6 * s) * p1
               + (3 * s**2 - 2 * s) * v1) / d
        acc = ((12 * s - 6) * p0 + (6 * s - 4) * v0 + (-12 * s + 6) * p1 + (6 * s - 2) * v1) / d**2
        B = T.shape[0]
        return (np.linalg.norm(vel, axis=-1).reshape(B, -1).max(1), np.linalg.norm(acc, axis=-1).reshape(B, -1).max(1))

    def limit_excess(self, U) -> np.ndarray:
        """(B,) how far each command is outside the hand limits (relative excess, 0 = feasible)."""
        vs, acc = self.batch_peaks(U)
        return np.maximum(vs / self.max_speed - 1.0, 0.0) + np.maximum(acc / self.max_acceleration - 1.0, 0.0)

    # ------------------------------------------------------------------ limits
    def violations(self, u) -> list[str]:
        u = np.asarray(u, dtype=np.float64)
        out = []
        if np.any(u < self.lower - 1e-12) or np.any(u > self.upper + 1e-12):
            worst = int(np.argmax(np.abs(u)))
            out.append(f"{self.names[worst]} = {u[worst]:.3g} outside +-{self.bound:g}")
        return out + self.decode(u).limit_violations(self.max_speed, self.max_acceleration)

    def feasible(self, u) -> bool:
        return not self.violations(u)

    def limit_step(self, u, du, shrink: float = 0.5, tries: int = 12) -> tuple[np.ndarray, float]:
        """Largest u + s du (s = 1, 1/2, 1/4, ...) inside the box and the hand limits, and s.

        u itself must be feasible; the box is met by clipping first, the speed and acceleration
        limits (not convex in u) by shortening the step.
        """
        u = np.asarray(u, dtype=np.float64)
        du = np.clip(u + np.asarray(du, dtype=np.float64), self.lower, self.upper) - u
        s = 1.0
        for _ in range(tries):
            if self.feasible(u + s * du):
                return u + s * du, s
            s *= shrink
        return u.copy(), 0.0

    def hand_samples(self, u, t0: float, dt: float, steps: int) -> np.ndarray:
        """(steps + 1, 3) hand positions at t0 + k dt for the command u (the coarse model's input)."""
        return self.decode(u).positions(t0 + dt * np.arange(steps + 1))
