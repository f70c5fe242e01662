"""Fixed-size variant of the generic rollout kernel (generic.py): one kernel per chain size.

Same model, same operation order, same arguments (the structs of model.py), and bit-identical results
(tests/test_rope_kernel.py compares it with the generic kernel testing every pair). What differs is how
the hardware executes it:
  - the chain state lives in kernel-local fixed-size matrices for a whole launch instead of global
    arrays; only the final state goes back to memory;
  - the node count is a compile-time constant, so each constraint pass unrolls into straight-line code
    (colour loops with constant bounds, end-node branches folded) and the per-node inverse masses and
    constraint denominators are computed once per launch, not per constraint. The pass count and the pair
    loops stay rolled: unrolling them made the N = 16 kernel take 50 s to compile for no further gain;
  - the self-collision test is culled exactly, in time or in space (collide.py, shared with lanes.py).

Each kernel is its own Warp module ("unique"), so building the kernel for a new chain size never forces
the others to recompile. On the CPU, chains of up to 64 nodes run in lanes.py instead (16 chains per
thread in vector lanes), on CUDA chains of up to 16 in tiled.py (registers and shared memory: on sm_90 this
kernel needs a 1.4 KB stack frame per thread at N = 16); this kernel serves the other sizes.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.collide import collide_func, finish_func, types
from wrenorm.kernels.rope.model import (
    bend_project,
    chain_constants,
    frame_after,
    inverse_masses,
    link_project,
    predict,
    record_hit,
    rollout_variant,
    running,
)

OPTIONS = {"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native",
           "max_unroll": 64}
MAX_NODES = 64  # beyond this the unrolled code is large; RopeSim falls back to the generic kernel
_CACHE: dict = {}


def fast_kernel(n: int):
    if int(n) not in _CACHE:
        _CACHE[int(n)] = _build(int(n))
    return _CACHE[int(n)]


def _build(n: int):
    N = n
    NM1 = n - 1  # links / segments
    LAST = n - 1
    BEND_ORDER = [i for c in range(3) for i in range(1 + c, n - 1, 3)]
    LINK_ORDER = [i for p in range(2) for i in range(p, n - 1, 2)]
    NBEND = len(BEND_ORDER)
    NLINK = len(LINK_ORDER)
    t = types(n)
    Mat, Flags = t["Mat"], t["Flags"]
    Vec = wp.types.vector(length=n, dtype=wp.float32)
    NB = t["NB"]
    collide = collide_func(n)
    finish = finish_func(n)

    @rollout_variant(module="unique", module_options=OPTIONS)
    def rollout_fixed(state, hand, path_index, params, cfg, step0, nsteps, stop_at_hit, events, offset, end):
        b = wp.tid() + offset
        st = events.status[b]
        if running(st, stop_at_hit) == 0:
            return
        m, ml, slope, alpha_t, gamma, at_s, dl, dq = chain_constants(params, cfg, b)
        dt = cfg.dt
        link = cfg.link
        # per-node inverse masses and the constraint factors built from them, once per launch
        W = inverse_masses(Vec(), N, m, ml, slope)
        IB = Vec()  # bending: 1 / ((1 + gamma)(w0 + 4 w1 + w2) + alpha~), by centre node
        for i in range(1, NM1):
            IB[i] = 1.0 / ((1.0 + gamma) * (W[i - 1] + 4.0 * W[i] + W[i + 1]) + alpha_t)
        FA = Vec()  # links: mass-weighted split of the correction, by first node
        FB = Vec()
        GL = Vec()  # wa + wb + alpha~, for the link multipliers
        for i in range(NM1):
            den = W[i] + W[i + 1] + at_s
            FA[i] = W[i] / den
            FB[i] = W[i + 1] / den
            GL[i] = den
        LL = Vec()  # link multipliers
        two_r = 2.0 * params.radius[b]
        cl = events.clearance[b]
        vmax2 = cfg.vmax * cfg.vmax
        inv_dt = 1.0 / dt
        nm1 = cfg.n - 1  # runtime bounds keep the pair loops rolled (code size, compile time)
        P = Mat()
        V = Mat()
        VB = Mat()  # velocities of the step before, for the hit's (record_hit)
        Q = Mat()  # positions at the start of the step
        L = Mat()  # bending multipliers (row i: centre node i)
        CQ = Mat()
        KB = Flags()  # temporal culling state (collide.py)
        for ba in range(NB):
            for bb in range(NB):
                KB[ba, bb] = -1.0e30  # every block pair is tested in the first step of a launch
        CP = Flags()
        G = float(0.0)
        for i in range(N):
            P[i] = state.pos[b, i]
            V[i] = state.vel[b, i]
        for step in range(step0, step0 + nsteps):
            for i in range(N):
                VB[i] = V[i]
            Q[0] = P[0]
            P[0] = hand[path_index[b], step + 1]
            for i in range(1, N):
                xi = P[i]
                Q[i] = xi
                li = link
                if i == LAST:
                    li = 0.5 * link
                xn, vn = predict(xi, V[i], W[i], li, dl, dq, dt, cfg.gravity)
                P[i] = xn
                L[i] = wp.vec3(0.0)
                LL[i - 1] = 0.0
            # curvature at the start of the step, for the bending damping (the same every pass)
            for i in range(1, NM1):
                CQ[i] = Q[i - 1] - 2.0 * Q[i] + Q[i + 1]
            for _ in range(cfg.iters):
                # bending in three colours (centre i mod 3), then links in two (even, odd): the
                # generic kernel's order, unrolled; within a colour nothing shares a node
                for kk in range(NBEND):
                    i0 = wp.static(BEND_ORDER[kk] - 1)
                    i1 = wp.static(BEND_ORDER[kk])
                    i2 = wp.static(BEND_ORDER[kk] + 1)
                    x0, x1, x2, lm = bend_project(P[i0], P[i1], P[i2], CQ[i1], L[i1], W[i0], W[i1], W[i2], IB[i1],
                                                  alpha_t, gamma)
                    P[i0] = x0
                    P[i1] = x1
                    P[i2] = x2
                    L[i1] = lm
                for kk in range(NLINK):
                    ia = wp.static(LINK_ORDER[kk])
                    ib = wp.static(LINK_ORDER[kk] + 1)
                    xa, xb, ll = link_project(P[ia], P[ib], LL[ia], link, at_s, FA[ia], FB[ia], GL[ia])
                    P[ia] = xa
                    P[ib] = xb
                    LL[ia] = ll
            vv = float(0.0)
            for i in range(N):
                v = (P[i] - Q[i]) * inv_dt
                V[i] = v
                vv = vv + wp.dot(v, v)
            if not (vv < vmax2):
                st = 2
                events.status[b] = 2
                events.clearance[b] = cl
                finish(state, b, P, V, step, cfg.frame_every, cfg.frame_end)
                return
            best, best_a, best_b, cl, KB, CP, G = collide(P, Q, KB, CP, G, cl, st, two_r, cfg.margin, cfg.min_sep,
                                                          cfg.cull, link, nm1)
            if best_a >= 0:
                st = 1
                record_hit(events, b, step, best, best_a, best_b, P, Q, V, VB, NM1)
                if stop_at_hit != 0:
                    events.clearance[b] = cl
                    finish(state, b, P, V, step, cfg.frame_every, cfg.frame_end)
                    return
            frame = frame_after(step, cfg.frame_every, cfg.frame_end)
            if frame >= 0:
                for i in range(N):
                    state.frames[frame, b, i] = P[i]
        events.clearance[b] = cl
        for i in range(N):
            state.pos[b, i] = P[i]
            state.vel[b, i] = V[i]

    return rollout_fixed
