"""Hand paths for the flying-knot rope task: chained cubic Bezier segments in space over time.

A path is C1 by construction when built with :meth:`HandPath.through` (waypoints with velocities,
i.e. cubic Hermite segments written as Bezier control points), so the rope is never given an
infinite acceleration at a segment joint. It starts and ends at rest, which lets the rope start
hanging still (no self-contact at t=0) and lets the reference horizon run past the end of the
motion with the hand held still.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError

# A robot wrist flicking a rope: roughly the envelope of a UR5/UR10-class arm's fingertip.
DEFAULT_MAX_SPEED = 6.0  # m/s
DEFAULT_MAX_ACCELERATION = 150.0  # m/s^2


@dataclass(frozen=True)
class HandPath:
    """Chained cubic Bezier segments.

    control_points: (3K+1, 3) m; segment k uses rows 3k .. 3k+3 (shared end points).
    durations: (K,) s, each > 0. Before t=0 and after the end the hand rests at the end points.
    """

    control_points: np.ndarray
    durations: np.ndarray

    def __post_init__(self):
        cp = np.asarray(self.control_points, dtype=np.float64)
        d = np.asarray(self.durations, dtype=np.float64).reshape(-1)
        if cp.ndim != 2 or cp.shape[1] != 3 or (cp.shape[0] - 1) % 3 != 0 or cp.shape[0] < 4:
            raise InputError("HandPath", "control_points", f"need shape (3K+1, 3) with K >= 1, got {cp.shape}")
        if d.shape[0] != (cp.shape[0] - 1) // 3:
            raise InputError("HandPath", "durations", f"need {(cp.shape[0] - 1) // 3} durations, got {d.shape[0]}")
        if not (np.all(np.isfinite(cp)) and np.all(np.isfinite(d))):
            raise InputError("HandPath", "control_points", "contains NaN or Inf")
        if np.any(d <= 0.0):
            raise InputError("HandPath", "durations", "every duration must be > 0")
        object.__setattr__(self, "control_points", cp)
        object.__setattr__(self, "durations", d)

    @classmethod
    def through(cls, times, points, velocities) -> HandPath:
        """Cubic Hermite segments through waypoints (t_i, p_i, v_i), written as Bezier control points."""
        t = np.asarray(times, dtype=np.float64)
        p = np.asarray(points, dtype=np.float64)
        v = np.asarray(velocities, dtype=np.float64)
        if t.ndim != 1 or t.shape[0] < 2 or p.shape != (t.shape[0], 3) or v.shape != p.shape:
            raise InputError("HandPath.through", "waypoints", "need times (N,), points (N,3), velocities (N,3), N >= 2")
        d = np.diff(t)
        cps = [p[0]]
        for k in range(len(d)):
            cps += [p[k] + v[k] * d[k] / 3.0, p[k + 1] - v[k + 1] * d[k] / 3.0, p[k + 1]]
        return cls(np.array(cps), d)

    @property
    def duration(self) -> float:
        return float(self.durations.sum())

    @property
    def start(self) -> np.ndarray:
        return self.control_points[0].copy()

    def _locate(self, times):
        t = np.clip(np.asarray(times, dtype=np.float64).reshape(-1), 0.0, self.duration)
        edges = np.concatenate([[0.0], np.cumsum(self.durations)])
        k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(self.durations) - 1)
        u = np.clip((t - edges[k]) / self.durations[k], 0.0, 1.0)
        idx = 3 * k[:, None] + np.arange(4)[None, :]
        return k, u, self.control_points[idx]  # (T,4,3)

    def positions(self, times) -> np.ndarray:
        _, u, c = self._locate(times)
        u = u[:, None]
        w = 1.0 - u
        return w**3 * c[:, 0] + 3 * w**2 * u * c[:, 1] + 3 * w * u**2 * c[:, 2] + u**3 * c[:, 3]

    def velocities(self, times) -> np.ndarray:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        k, u, c = self._locate(t)
        u = u[:, None]
        w = 1.0 - u
        dpdu = 3 * (w**2 * (c[:, 1] - c[:, 0]) + 2 * w * u * (c[:, 2] - c[:, 1]) + u**2 * (c[:, 3] - c[:, 2]))
        v = dpdu / self.durations[k][:, None]
        # The hand rests outside [0, duration].
        v[(t < 0.0) | (t > self.duration)] = 0.0
        return v

    def accelerations(self, times) -> np.ndarray:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        k, u, c = self._locate(t)
        u = u[:, None]
        d2 = 6 * ((1.0 - u) * (c[:, 2] - 2 * c[:, 1] + c[:, 0]) + u * (c[:, 3] - 2 * c[:, 2] + c[:, 1]))
        a = d2 / self.durations[k][:, None] ** 2
        a[(t < 0.0) | (t > self.duration)] = 0.0
        return a

    def _dense_times(self, per_segment: int = 200) -> np.ndarray:
        edges = np.concatenate([[0.0], np.cumsum(self.durations)])
        return np.concatenate([np.linspace(edges[k], edges[k + 1], per_segment) for k in range(len(self.durations))])

    def max_speed(self) -> float:
        return float(np.linalg.norm(self.velocities(self._dense_times()), axis=1).max())

    def max_acceleration(self) -> float:
        return float(np.linalg.norm(self.accelerations(self._dense_times()), axis=1).max())

    def limit_violations(self, max_speed: float = DEFAULT_MAX_SPEED,
                         max_acceleration: float = DEFAULT_MAX_ACCELERATION) -> list[str]:
        """Human-readable list of exceeded limits (empty when the path is feasible)."""
        problems = []
        vs, acc = self.max_speed(), self.max_acceleration()
        if vs > max_speed:
            problems.append(f"peak speed {vs:.2f} m/s exceeds {max_speed:.2f} m/s")
        if acc > max_acceleration:
            problems.append(f"peak acceleration {acc:.1f} m/s^2 exceeds {max_acceleration:.1f} m/s^2")
        return problems

    def check_limits(self, source: str = "HandPath", max_speed: float = DEFAULT_MAX_SPEED,
                     max_acceleration: float = DEFAULT_MAX_ACCELERATION) -> None:
        problems = self.limit_violations(max_speed, max_acceleration)
        if problems:
            raise InputError(source, "hand path", "; ".join(problems))


_REST = np.zeros(3)
HAND_START = np.array([0.0, 0.0, 1.6])  # fingertip height: a 1.1 m rope hangs clear of the floor


def _path(waypoints) -> HandPath:
    """waypoints: list of (t, offset from HAND_START, velocity)."""
    t = [w[0] for w in waypoints]
    p = [HAND_START + np.asarray(w[1], dtype=np.float64) for w in waypoints]
    v = [np.asarray(w[2], dtype=np.float64) for w in waypoints]
    return HandPath.through(t, p, v)


def _overhead_flick(reach: float, lift: float, speed: float, t_swing: float, t_flick: float, side: float = 0.0):
    """Swing forward and up so the rope trails behind, then snap back and down: the rope's free
    end keeps going, flies over the hand and falls across the rope."""
    # A sideways component lets the loop miss the rope (measured: side=0.03-0.12 m never hit within 2 s),
    # so the built-in paths stay in the x-z plane.
    return _path([
        (0.0, (0.0, 0.0, 0.0), _REST),
        (t_swing, (reach, side, lift), (speed * 0.6, 0.0, speed * 0.8)),
        (t_swing + t_flick, (0.1 * reach, -side, 0.5 * lift), (-0.5 * speed, 0.0, -0.3 * speed)),
        (t_swing + t_flick + 0.3, (0.0, 0.0, 0.3 * lift), _REST),
    ])


def builtin_hand_paths() -> dict[str, HandPath]:
    """Named hand paths, each throwing the rope into a loop that hits itself within ~1-2 s."""
    return {
        "flick": _overhead_flick(reach=0.35, lift=0.35, speed=3.0, t_swing=0.35, t_flick=0.20),
        "flick_fast": _overhead_flick(reach=0.40, lift=0.40, speed=3.6, t_swing=0.30, t_flick=0.18),
        "flick_wide": _overhead_flick(reach=0.50, lift=0.30, speed=3.5, t_swing=0.40, t_flick=0.22),
        "flick_high": _overhead_flick(reach=0.25, lift=0.45, speed=3.2, t_swing=0.35, t_flick=0.20),
        "flick_slow": _overhead_flick(reach=0.30, lift=0.30, speed=2.6, t_swing=0.40, t_flick=0.24),
    }


FIT_PATHS = ["flick", "flick_fast", "flick_wide"]
HELD_OUT_PATHS = ["flick_high", "flick_slow"]


def get_hand_path(name: str, source: str = "--path") -> HandPath:
    paths = builtin_hand_paths()
    if name not in paths:
        raise InputError(source, "path", f"unknown hand path {name!r}; choose one of {sorted(paths)}")
    return paths[name]
