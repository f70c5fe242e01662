"""Differentiable coarse chain for smooth observables (no self-collision): the state after a
fixed number of steps, with gradients of a weighted sum of it with respect to every chain
parameter by Warp's tape.

Same step as kernels/rope.py (implicit drag, XPBD bending with damping, XPBD links with
compliance, position-based velocities) without the collision search, whose first-hit time is
not differentiable. Tape-safe: launch s reads states[s] and writes states[s + 1] only, so no
value the backward pass needs is overwritten; inside a launch the chain is unrolled over a
fixed node count, so every intermediate is its own SSA value.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from wrenorm.kernels.rope.model import GRAVITY, node_w
from wrenorm.kernels.rope.sim import ChainParams

_CACHE: dict = {}
GRAD_FIELDS = ("node_mass", "lead_mass", "bend_k", "bend_b", "drag_lin", "drag_quad", "stretch", "mass_slope")


def _step_kernel(n: int, iters: int):
    key = (int(n), int(iters))
    if key in _CACHE:
        return _CACHE[key]
    N, LAST, ITERS = n, n - 1, iters
    BEND_ORDER = [i for c in range(3) for i in range(1 + c, n - 1, 3)]
    LINK_ORDER = [i for p in range(2) for i in range(p, n - 1, 2)]
    NBEND, NLINK = len(BEND_ORDER), len(LINK_ORDER)
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)
    Vec = wp.types.vector(length=n, dtype=wp.float32)

    @wp.kernel(module="unique", module_options={"enable_backward": True, "max_unroll": 256})
    def step_kernel(
        xs: wp.array3d(dtype=wp.vec3),  # (steps + 1, B, N)
        vs: wp.array3d(dtype=wp.vec3),
        hand: wp.array2d(dtype=wp.vec3),
        path_index: wp.array(dtype=wp.int32),
        node_mass: wp.array(dtype=float),
        lead_mass: wp.array(dtype=float),
        bend_k: wp.array(dtype=float),
        bend_b: wp.array(dtype=float),
        drag_lin: wp.array(dtype=float),
        drag_quad: wp.array(dtype=float),
        stretch: wp.array(dtype=float),
        mass_slope: wp.array(dtype=float),
        link: float,
        dt: float,
        gravity: wp.vec3,
        s: int,
    ):
        b = wp.tid()
        m = node_mass[b]
        ml = lead_mass[b]
        slope = mass_slope[b]
        k = wp.max(bend_k[b], 1.0e-12)
        alpha_t = link * link / (k * dt * dt)
        gamma = bend_b[b] / (k * dt)
        at_s = stretch[b] / (dt * dt)
        dl = drag_lin[b]
        dq = drag_quad[b]
        W = Vec()
        for i in range(N):
            W[i] = node_w(i, N, m, ml, slope)
        P = Mat()
        Q = Mat()
        L = Mat()
        LL = Vec()
        Q[0] = xs[s, b, 0]
        P[0] = hand[path_index[b], s + 1]
        for i in range(1, N):
            xi = xs[s, b, i]
            vi = vs[s, b, i]
            Q[i] = xi
            li = link
            if i == LAST:
                li = 0.5 * link
            c = (dl + dq * wp.length(vi)) * li
            vi = (vi + dt * gravity) * (1.0 / (1.0 + dt * c * W[i]))
            P[i] = xi + dt * vi
        for it in range(ITERS):
            for kk in range(NBEND):
                i = wp.static(BEND_ORDER[kk])
                x0 = P[i - 1]
                x1 = P[i]
                x2 = P[i + 1]
                cv = x0 - 2.0 * x1 + x2
                dcv = cv - (Q[i - 1] - 2.0 * Q[i] + Q[i + 1])
                lm = L[i]
                den_b = (1.0 + gamma) * (W[i - 1] + 4.0 * W[i] + W[i + 1]) + alpha_t
                dlam = (-cv - alpha_t * lm - gamma * dcv) / den_b
                L[i] = lm + dlam
                P[i - 1] = x0 + W[i - 1] * dlam
                P[i] = x1 - (2.0 * W[i]) * dlam
                P[i + 1] = x2 + W[i + 1] * dlam
            for kk in range(NLINK):
                i = wp.static(LINK_ORDER[kk])
                den = W[i] + W[i + 1] + at_s
                xa = P[i]
                xb = P[i + 1]
                d = xb - xa
                ln = wp.length(d)
                e = ln - link + at_s * LL[i]
                LL[i] = LL[i] - e / den
                corr = d * (e / ln)
                P[i] = xa + (W[i] / den) * corr
                P[i + 1] = xb - (W[i + 1] / den) * corr
        for i in range(N):
            xs[s + 1, b, i] = P[i]
            vs[s + 1, b, i] = (P[i] - Q[i]) / dt

    _CACHE[key] = step_kernel
    return step_kernel


class GradRope:
    """Chains of `n_nodes` masses (node 0 on the hand) for gradient work; CPU or CUDA."""

    def __init__(self, n_nodes: int, link_length: float, dt: float = 0.005, iterations: int = 4,
                 device: str = "cpu", gravity=GRAVITY):
        wp.init()
        self.n, self.link, self.dt, self.iterations = int(n_nodes), float(link_length), float(dt), int(iterations)
        self.device, self.gravity = device, wp.vec3(*[float(g) for g in gravity])
        self.kernel = _step_kernel(self.n, self.iterations)
        # P[i] = ... on the local state must be copy-on-write for correct adjoints; Warp takes
        # that from a global flag at build time, so set it only while this module builds
        old = wp.config.enable_vector_component_overwrites
        wp.config.enable_vector_component_overwrites = True
        try:
            wp.load_module(self.kernel.module, device=device)
        finally:
            wp.config.enable_vector_component_overwrites = old

    def value_and_grad(self, pos0, vel0, hand, path_index, params: ChainParams, steps: int, weights):
        """J_b = sum(weights_b * x_b(steps)) per chain; returns (J (B,), {field: dJ/dfield (B,)},
        final positions (B, N, 3)). weights (B, N, 3) or broadcastable."""
        dev, n, B = self.device, self.n, params.batch
        xs = wp.zeros((steps + 1, B, n), dtype=wp.vec3, device=dev, requires_grad=True)
        vs = wp.zeros((steps + 1, B, n), dtype=wp.vec3, device=dev, requires_grad=True)
        x0 = np.broadcast_to(np.asarray(pos0, np.float32), (B, n, 3))
        v0 = np.broadcast_to(np.asarray(vel0, np.float32), (B, n, 3))
        xs0 = np.zeros((steps + 1, B, n, 3), np.float32)
        vs0 = np.zeros_like(xs0)
        xs0[0], vs0[0] = x0, v0
        xs.assign(xs0)
        vs.assign(vs0)
        hand_w = wp.array(np.ascontiguousarray(hand, np.float32), dtype=wp.vec3, device=dev)
        pidx = wp.array(np.broadcast_to(np.asarray(path_index, np.int32), (B,)).copy(), dtype=wp.int32, device=dev)
        pa = {f: wp.array(getattr(params, f).astype(np.float32), dtype=float, device=dev, requires_grad=True)
              for f in GRAD_FIELDS}
        wts = wp.array(np.ascontiguousarray(np.broadcast_to(weights, (B, n, 3)), np.float32), dtype=wp.vec3, device=dev)
        J = wp.zeros(B, dtype=float, device=dev, requires_grad=True)
        tape = wp.Tape()
        with tape:
            for s in range(steps):
                wp.launch(self.kernel, dim=B, device=dev, inputs=[
                    xs, vs, hand_w, pidx, *[pa[f] for f in GRAD_FIELDS], self.link, self.dt, self.gravity, s])
            wp.launch(_weighted_sum, dim=(B, n), device=dev, inputs=[xs, wts, steps], outputs=[J])
        tape.backward(grads={J: wp.ones(B, dtype=float, device=dev)})
        grads = {f: pa[f].grad.numpy().copy() for f in GRAD_FIELDS}
        out = (J.numpy().copy(), grads, xs.numpy()[steps].copy())
        tape.zero()
        return out


@wp.kernel
def _weighted_sum(xs: wp.array3d(dtype=wp.vec3), w: wp.array2d(dtype=wp.vec3), s: int, out: wp.array(dtype=float)):
    b, i = wp.tid()
    wp.atomic_add(out, b, wp.dot(xs[s, b, i], w[b, i]))
