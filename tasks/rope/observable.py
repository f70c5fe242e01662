"""The rope's one observable: its state at the first self-collision (the flying knot's "critical point"),
for a reference rope (markers) and for batches of coarse chains, and its error to a target state.

Z = positions and velocities at SAMPLES common arc-length points, the collision time from the start of the
motion, and the two arc-length fractions of the contact. The fit (problem.py), the correction and the
sensitivity (control/) all score through `Target`, so they agree about the same rope.

Error (dimensionless), total = sum of WEIGHTS[term] * term:
  shape    RMS distance between the two states at the K points, / rope length
  velocity RMS velocity difference at those points, / the target's RMS speed there (>= MIN_SPEED)
  time     |t - t_target| / t_target (times from the start of the motion)
  place    mean |s - s_target| of the two arc-length fractions of the contact
  Why these weights: 0.1 on velocity mirrors the flying knot's 5.0 (m) : 0.00375 (m/s) on squared errors
  once shape is divided by ~1 m and velocity by a ~5 m/s speed; at the fitted optimum of the built-in
  references the four weighted terms are then of one order, so none is ignored and none dominates. place is
  halved because it double-counts the time error when a contact slides along the rope.
The residual e = W (Z - Z_target), block by block, has |e_pos| = w_shape * shape, |e_vel| = w_velocity *
velocity, |e_t| = w_time * time and |e_s| <= w_place * place, so |e|^2 is a least-squares form of the same
error (the correction's QP objective, the Gauss-Newton uncertainty's residual).

A rope that never hits itself has no critical state: it costs NO_HIT plus its closest approach over a tenth
of the length, capped at 1 (finite, and smaller the closer it came, so a search is pulled toward a hit); a
blow-up costs the largest miss. This one rule serves chains and real ropes alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError
from wrenorm.kernels.rope import critical

WEIGHTS = {"shape": 1.0, "velocity": 0.1, "time": 1.0, "place": 0.5}
NO_HIT = 5.0  # above any colliding candidate's error (each term is O(1) at worst)
SAMPLES = 21
MIN_SPEED = 0.1  # m/s
VELOCITY_WINDOW = 0.005  # s: a recording's velocities are slopes over about this long (the chain's step), however fast
# it was sampled. A 1 ms frame difference of 1000 Hz markers with 0.5 mm of noise read the critical state's velocity
# 1.15 m/s RMS off (the rope's own: 2.36 m/s) and the chain's start 1.08 m/s off, in silence (review of stop 54);
# recordings at 250 Hz or slower keep the one-frame difference (5 ms / the frame step rounds to 1)
NO_HIT_SCALE = 0.1  # of the rope length: a closest approach this far (or farther) adds 1 to NO_HIT


def resample(points: np.ndarray, arclength: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Piecewise-linear resampling of (..., M, 3) along `arclength` (M,) at `samples` (K,)."""
    points = np.asarray(points, np.float64)
    idx = np.clip(np.searchsorted(arclength, samples, side="right") - 1, 0, len(arclength) - 2)
    u = (samples - arclength[idx]) / (arclength[idx + 1] - arclength[idx])
    return points[..., idx, :] * (1 - u)[:, None] + points[..., idx + 1, :] * u[:, None]


@dataclass
class CriticalStates:
    """A batch of critical states; rows with hit == False carry no state (NaN)."""

    pos: np.ndarray  # (B, K, 3) m
    vel: np.ndarray  # (B, K, 3) m/s
    time: np.ndarray  # (B,) s from the start of the motion
    s: np.ndarray  # (B, 2) arc-length fractions of the contact (held-end side, free-end side)
    hit: np.ndarray  # (B,) bool
    clearance: np.ndarray  # (B,) m, closest approach of ropes that never hit (0 for hits)

    @property
    def batch(self) -> int:
        return self.pos.shape[0]

    def take(self, rows) -> CriticalStates:
        rows = np.atleast_1d(rows)
        return CriticalStates(self.pos[rows], self.vel[rows], self.time[rows], self.s[rows], self.hit[rows],
                              self.clearance[rows])

    def row(self, i: int) -> CriticalStates:
        return self.take([i])


def from_rollout(res, n_nodes: int, t0: float = 0.0) -> CriticalStates:
    """Critical states of a batch of coarse chains (kernels.rope.RolloutResult), resampled to the K points, on
    the host (the planner and the charts want them there; a fit keeps them on the device, see RopeProblem)."""
    states = critical.chain_states(res.events, np.zeros(len(res.status), np.int32), [np.iinfo(np.int32).max],
                                   res.dt, res.t0 - t0, SAMPLES)
    h = states.to_host()
    hit = h["status"] == 1
    # the host copy of a rollout may have been marked since (a hit after its condition's horizon counts as none)
    keep = hit & (res.status == 1)
    nan = np.nan
    return CriticalStates(np.where(keep[:, None, None], h["pos"], nan), np.where(keep[:, None, None], h["vel"], nan),
                          np.where(keep, h["time"], nan), np.where(keep[:, None], h["s"], nan), keep,
                          np.where(keep, 0.0, np.where(res.status == 2, np.inf, res.clearance.astype(np.float64))))


def velocity_intervals(ref) -> int:
    """How many frame steps a recording's velocity spans: the odd number nearest VELOCITY_WINDOW in frame steps, so
    that a window about a frame interval is centred on it (an even one sat half a frame late)."""
    steps = VELOCITY_WINDOW / float(ref.time[1] - ref.time[0])
    return max(1, 2 * int(round((steps - 1.0) / 2.0)) + 1)


def marker_velocity(ref, first: int, intervals: int) -> np.ndarray:
    """(markers, 3) the markers' least-squares velocity over frames first .. first + intervals (one interval: the frame
    difference). The slope of a constant acceleration over a window is its velocity at the window's middle, as a frame
    difference's is at its interval's."""
    if intervals == 1:  # to the bit as the chain's start and the critical state always read it
        return (ref.markers[first + 1] - ref.markers[first]) / (ref.time[first + 1] - ref.time[first])
    t = np.asarray(ref.time[first:first + intervals + 1], np.float64)
    x = np.asarray(ref.markers[first:first + intervals + 1], np.float64)
    dt = t - t.mean()
    return np.einsum("f,fmk->mk", dt / np.sum(dt * dt), x)


def event_velocity(ref, k: int, frac: float) -> np.ndarray:
    """(markers, 3) the markers' velocity at an event frac of the way through frame interval (k-1, k]. The velocity
    over a window (marker_velocity) is the velocity at the window's middle, so the event's follows linearly in time
    from the window centred on its interval and the window one frame earlier, the chain kernel's rule for its steps
    (kernels/rope/model.hit_velocity). Never from a later window: after the first contact a rope's own contact forces
    act (the chain has none), and interpolating toward the next interval's velocity lost on held-out seeds (README,
    "The velocity at the contact"). Where no window starts before the event's (its first frames), the one window
    gives it, as before. The interval's velocity alone is up to a dt / 2 off the event's and jumps by a dt where the
    event crosses a frame."""
    t = np.asarray(ref.time, np.float64)
    n = velocity_intervals(ref)
    last = max(len(t) - 1 - n, 0)
    first = int(np.clip(k - 1 - (n - 1) // 2, 0, last))

    def middle(f: int) -> float:
        return 0.5 * (t[f] + t[f + n])

    here = marker_velocity(ref, first, n)
    if first == 0:
        return here
    other = first - 1
    when = t[k - 1] + frac * (t[k] - t[k - 1])
    return here + (when - middle(first)) / (middle(other) - middle(first)) * (marker_velocity(ref, other, n) - here)


def reference_critical(ref):
    """Where a reference's critical moment comes from (reference/events.py `critical`): the file's
    `critical_time` annotation when it has one, else the first self-contact detected in its markers, with
    its confidence, reasons and warnings; `.event` is None when there is no usable one."""
    from wrenorm.tasks.rope.reference.events import critical

    return critical(ref)


def reference_event(ref):
    """The reference's critical moment (annotated, else detected; a CollisionEvent), or None."""
    ev = reference_critical(ref).event
    return None if ev is None or ev.index == 0 else ev


def from_reference(ref, event=None) -> CriticalStates:
    """Critical state of one rope trajectory (a reference, a real trial), batch of one.

    At the event time t* inside frame interval (k-1, k]: positions interpolated linearly between the two
    frames, velocity extrapolated to t* from the frame differences over that interval and the one before
    (event_velocity; the chain kernel's rule too); where frames come faster than VELOCITY_WINDOW, from the slopes over
    the frames about that window centred on the intervals."""
    ev = reference_event(ref) if event is None else event
    if ev is None:
        from wrenorm.tasks.rope.reference.events import detect_reference

        clear = detect_reference(ref).diagnostics.get("summary", {}).get("min_gap_m")
        clear = np.inf if clear is None or not np.isfinite(clear) else float(clear)
        clear -= 2.0 * float(getattr(ref, "marker_offset", 0.0))  # surface markers: the centre lines may be nearer
        nan = np.full((1, SAMPLES, 3), np.nan)
        return CriticalStates(nan, nan.copy(), np.full(1, np.nan), np.full((1, 2), np.nan), np.zeros(1, bool),
                              np.array([max(clear, 0.0)]))
    t, k = ref.time, ev.index
    frac = (ev.time - t[k - 1]) / (t[k] - t[k - 1])
    pos = ref.markers[k - 1] + frac * (ref.markers[k] - ref.markers[k - 1])
    vel = event_velocity(ref, k, frac)
    s_k = np.linspace(0.0, 1.0, SAMPLES)
    s = ref.marker_arclength
    return CriticalStates(resample(pos, s, s_k)[None], resample(vel, s, s_k)[None],
                          np.array([ev.time - t[0]]), np.array([[ev.s_a, ev.s_b]]), np.ones(1, bool), np.zeros(1))


@dataclass
class Target:
    """The critical state to reproduce (a reference's, a goal's), with the scales that make errors
    dimensionless."""

    state: CriticalStates  # batch of one
    length: float  # m
    speed: float  # m/s, RMS speed of the target's critical state (>= MIN_SPEED)
    weights: dict

    @classmethod
    def from_reference(cls, ref, event=None, weights: dict | None = None, source: str = "goal") -> Target:
        st = from_reference(ref, event)
        if not st.hit[0]:
            raise InputError(source, "markers", "the rope never hits itself (no critical state to reach)")
        speed = max(float(np.sqrt(np.mean(np.sum(st.vel[0] ** 2, -1)))), MIN_SPEED)
        return cls(st, float(ref.length), speed, dict(WEIGHTS if weights is None else weights))

    @property
    def dim(self) -> int:
        return 6 * SAMPLES + 3

    @property
    def blocks(self) -> dict:
        K = SAMPLES
        return {"position": slice(0, 3 * K), "velocity": slice(3 * K, 6 * K), "time": slice(6 * K, 6 * K + 1),
                "place": slice(6 * K + 1, 6 * K + 3)}

    @property
    def error_groups(self) -> list:
        """Rows of the residual whose norms add up to a hit's total error: |e_pos| + |e_vel| + |e_t| + |e_s1| + |e_s2|
        (the module docstring; the place term is the mean of the two contact fractions' errors)."""
        b = self.blocks
        return [b["position"], b["velocity"], b["time"], slice(b["place"].start, b["place"].start + 1),
                slice(b["place"].start + 1, b["place"].stop)]

    def device_target(self, device: str = "cpu"):
        """This target as the observable kernel's TargetStates (one condition), made once per device."""
        cache = self.__dict__.setdefault("_device_targets", {})
        if device not in cache:
            cache[device] = stack_targets([self], device)
        return cache[device]

    def _score(self, st: CriticalStates, residual: bool):
        states = critical.DeviceStates.from_host(np.where(st.hit, 1, 0), st.time, st.s, st.clearance, st.pos, st.vel)
        return critical.critical_terms(states, np.zeros(st.batch, np.int32), self.device_target(), MISS, residual)

    def residual(self, st: CriticalStates) -> np.ndarray:
        """(B, dim) weighted residual e = W (Z - Z_target); NaN rows for ropes that never hit."""
        return self._score(st, residual=True)[1]

    def terms(self, st: CriticalStates) -> dict:
        """The error terms and their weighted total per row; a miss costs the no-hit rule."""
        terms = self._score(st, residual=False)[0]
        return {k: terms[:, i] for i, k in enumerate(critical.TERMS)}

    def state_error(self, pos: np.ndarray, vel: np.ndarray, time: float) -> float:
        """Shape and velocity error of one rope state (K, 3) at the K points plus the time error of `time`:
        how a rope that never hit is scored by its state at the target's critical time (no penalty). The same
        terms as a hit's, with the contact placed where the target's is (a state has no contact to place)."""
        st = CriticalStates(np.asarray(pos, np.float64)[None], np.asarray(vel, np.float64)[None],
                            np.array([float(time)]), self.state.s.copy(), np.ones(1, bool), np.zeros(1))
        return float(self.terms(st)["total"][0])


MISS = critical.no_hit_rule(NO_HIT, NO_HIT_SCALE)


def stack_targets(targets: list[Target], device: str):
    """The observable kernel's TargetStates for several conditions (one target each), on `device`."""
    g = [t.state for t in targets]
    return critical.target_states(
        np.concatenate([x.pos for x in g]), np.concatenate([x.vel for x in g]), np.concatenate([x.time for x in g]),
        np.concatenate([x.s for x in g]), [t.speed for t in targets], [t.length for t in targets],
        [[t.weights[k] for k in ("shape", "velocity", "time", "place")] for t in targets], device)
