"""The coarse rope chain's shared definitions: constants, the segment distance and the node masses.

Every rollout variant (generic.py, fixed.py, lanes.py, grad.py) uses these, so all of them step the same model.
"""
from __future__ import annotations

import warp as wp

wp.config.quiet = True

GRAVITY = (0.0, 0.0, -9.81)  # z up, as in newton
VMAX = 1.0e3  # m/s; a node faster than this means the step blew up
# forward-only modules (the tape-safe variant sets its own); -march=native lets clang use the host's SIMD and
# FMA for the per-chain arithmetic. No fast-math: blow-up detection needs NaN.
FORWARD_OPTIONS = {"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native"}


@wp.func
def seg_closest(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3) -> wp.vec3:
    """(distance, s, t) between segments p1q1 and p2q2 (Ericson, Real-Time Collision Detection 5.1.9)."""
    eps = 1.0e-12
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = wp.clamp(f / e, 0.0, 1.0)
    else:
        c = wp.dot(d1, r)
        if e <= eps:
            t = 0.0
            s = wp.clamp(-c / a, 0.0, 1.0)
        else:
            bb = wp.dot(d1, d2)
            denom = a * e - bb * bb
            if denom > 1.0e-10 * a * e:
                s = wp.clamp((bb * f - c * e) / denom, 0.0, 1.0)
            else:
                s = 0.0
            t = (bb * s + f) / e
            if t < 0.0:
                t = 0.0
                s = wp.clamp(-c / a, 0.0, 1.0)
            elif t > 1.0:
                t = 1.0
                s = wp.clamp((bb - c) / a, 0.0, 1.0)
    c1 = p1 + d1 * s
    c2 = p2 + d2 * t
    return wp.vec3(wp.length(c1 - c2), s, t)


@wp.func
def node_w(i: int, n: int, m: float, ml: float, slope: float) -> float:
    """Inverse mass of node i: 0 for the held node, 1/lead for the free end; interior nodes
    m (1 + slope (1 - 2u)), u = 0 next to the hand and 1 next to the lead (mean m for any slope)."""
    w = float(0.0)
    if i == n - 1:
        w = 1.0 / ml
    elif i > 0:
        u = float(0.5)
        if n > 3:
            u = float(i - 1) / float(n - 3)
        w = 1.0 / (m * (1.0 + slope * (1.0 - 2.0 * u)))
    return w

