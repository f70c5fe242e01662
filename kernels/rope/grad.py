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

from wrenorm.kernels.rope.model import (
    GRAVITY,
    ChainParameters,
    ChainSettings,
    bend_project,
    chain_constants,
    inverse_masses,
    link_project,
    predict,
)
from wrenorm.kernels.rope.sim import ChainParams

_CACHE: dict = {}
GRAD_FIELDS = ("node_mass", "lead_mass", "bend_k", "bend_b", "drag_lin", "drag_quad", "stretch", "mass_slope")


def _kernels(n: int, iters: int):
    """The rollout kernel for chains of n nodes and `iters` constraint passes: steps first .. first + steps - 1 in
    one launch (a whole rollout, or one step per launch). Its adjoint replays the step loop backwards, each step
    from the states it read (never overwritten), so a whole-rollout launch's gradients are the per-step launches'
    (tested bit for bit)."""
    key = (int(n), int(iters))
    if key in _CACHE:
        return _CACHE[key]
    N, LAST, ITERS = n, n - 1, iters
    BEND_ORDER = [i for c in range(3) for i in range(1 + c, n - 1, 3)]
    LINK_ORDER = [i for p in range(2) for i in range(p, n - 1, 2)]
    NBEND, NLINK = len(BEND_ORDER), len(LINK_ORDER)
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)
    Vec = wp.types.vector(length=n, dtype=wp.float32)

    def chain_step(xs: wp.array3d(dtype=wp.vec3), vs: wp.array3d(dtype=wp.vec3), hand: wp.array2d(dtype=wp.vec3),
                   path_index: wp.array(dtype=wp.int32), params: ChainParameters, cfg: ChainSettings, s: int, b: int):
        m, ml, slope, alpha_t, gamma, at_s, dl, dq = chain_constants(params, cfg, b)
        link = cfg.link
        dt = cfg.dt
        W = inverse_masses(Vec(), N, m, ml, slope)
        P = Mat()
        Q = Mat()
        L = Mat()
        LL = Vec()
        Q[0] = xs[s, b, 0]
        P[0] = hand[path_index[b], s + 1]
        for i in range(1, N):
            xi = xs[s, b, i]
            Q[i] = xi
            li = link
            if i == LAST:
                li = 0.5 * link
            xn, vn = predict(xi, vs[s, b, i], W[i], li, dl, dq, dt, cfg.gravity)
            P[i] = xn
        for _ in range(ITERS):
            for kk in range(NBEND):
                i = wp.static(BEND_ORDER[kk])
                inv = 1.0 / ((1.0 + gamma) * (W[i - 1] + 4.0 * W[i] + W[i + 1]) + alpha_t)
                x0, x1, x2, lm = bend_project(P[i - 1], P[i], P[i + 1], Q[i - 1] - 2.0 * Q[i] + Q[i + 1], L[i],
                                              W[i - 1], W[i], W[i + 1], inv, alpha_t, gamma)
                P[i - 1] = x0
                P[i] = x1
                P[i + 1] = x2
                L[i] = lm
            for kk in range(NLINK):
                i = wp.static(LINK_ORDER[kk])
                den = W[i] + W[i + 1] + at_s
                xa, xb, ll = link_project(P[i], P[i + 1], LL[i], link, at_s, W[i] / den, W[i + 1] / den, den)
                P[i] = xa
                P[i + 1] = xb
                LL[i] = ll
        for i in range(N):
            xs[s + 1, b, i] = P[i]
            vs[s + 1, b, i] = (P[i] - Q[i]) / dt

    chain_step.__name__ = f"chain_step_{n}_{iters}"
    step_func = wp.func(chain_step, module="unique")
    options = {"enable_backward": True, "max_unroll": 256}

    @wp.kernel(module="unique", module_options=options)
    def rollout_kernel(
        xs: wp.array3d(dtype=wp.vec3),
        vs: wp.array3d(dtype=wp.vec3),
        hand: wp.array2d(dtype=wp.vec3),
        path_index: wp.array(dtype=wp.int32),
        params: ChainParameters,
        cfg: ChainSettings,
        first: int,
        steps: int,
    ):
        b = wp.tid()
        for s in range(first, first + steps):
            step_func(xs, vs, hand, path_index, params, cfg, s, b)

    _CACHE[key] = rollout_kernel
    return _CACHE[key]


class GradRope:
    """Chains of `n_nodes` masses (node 0 on the hand) for gradient work; CPU or CUDA."""

    def __init__(self, n_nodes: int, link_length: float, dt: float = 0.005, iterations: int = 4,
                 device: str = "cpu", gravity=GRAVITY):
        wp.init()
        self.n, self.link, self.dt, self.iterations = int(n_nodes), float(link_length), float(dt), int(iterations)
        self.device, self.gravity = device, wp.vec3(*[float(g) for g in gravity])
        self.kernel = _kernels(self.n, self.iterations)
        # P[i] = ... on the local state must be copy-on-write for correct adjoints; Warp takes
        # that from a global flag at build time, so set it only while these modules build
        old = wp.config.enable_vector_component_overwrites
        wp.config.enable_vector_component_overwrites = True
        try:
            wp.load_module(self.kernel.module, device=device)
        finally:
            wp.config.enable_vector_component_overwrites = old

    def value_and_grad(self, pos0, vel0, hand, path_index, params: ChainParams, steps: int, weights,
                       per_step: bool = False):
        """J_b = sum(weights_b * x_b(steps)) per chain; returns (J (B,), {field: dJ/dfield (B,)},
        final positions (B, N, 3)). weights (B, N, 3) or broadcastable. The rollout is one launch (per_step: one
        launch per step, the reference it is tested against)."""
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
              for f in ChainParams.FIELDS}
        prm = ChainParameters()
        for f, a in pa.items():
            setattr(prm, f, a)
        cfg = ChainSettings()
        cfg.n, cfg.link, cfg.dt, cfg.gravity = n, self.link, self.dt, self.gravity
        wts = wp.array(np.ascontiguousarray(np.broadcast_to(weights, (B, n, 3)), np.float32), dtype=wp.vec3, device=dev)
        J = wp.zeros(B, dtype=float, device=dev, requires_grad=True)
        tape = wp.Tape()
        with tape:
            if per_step:
                for s in range(steps):
                    wp.launch(self.kernel, dim=B, device=dev, inputs=[xs, vs, hand_w, pidx, prm, cfg, s, 1])
            else:
                wp.launch(self.kernel, dim=B, device=dev, inputs=[xs, vs, hand_w, pidx, prm, cfg, 0, steps])
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
