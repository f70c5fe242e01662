"""GPU variant of the fixed-size rollout (fixed.py): one chain per thread, the state the constraint passes carry in
registers, everything else in shared memory, and no stack frame.

Same model, same operation order, same arguments, and bit-identical results on the CPU (tests/test_rope_kernel.py
compares it with the generic kernel testing every pair, with one lane per block and with real blocks), but for the
critical velocity of a hit in a launch's first step: the velocity of the step before it is rebuilt from the launch's
stored velocity through the positions buffer, (x - (x - dt v)) / dt, within float32 rounding of v (1e-7 m/s). fixed.py
keeps the whole chain in kernel-local matrices; on sm_90 that needs 255 registers and a 1.4 KB stack frame per
thread at N = 16 (the pair test indexes positions at run time, and one run-time index puts a whole local matrix
in the frame), so the constraint passes run out of local memory. Here:
  - registers hold the positions and the bending and link multipliers: what every projection reads and writes,
    indexed by compile-time constants only (the node count is a constant, the passes are unrolled);
  - shared memory holds what is read-only during the passes (per-node inverse masses and the constraint factors
    built from them, the positions at the start of the step) and what the pair test indexes at run time (the
    positions at the end of the step and the segments' bounding spheres). The positions are triple-buffered by
    step modulo 3: the end of one step is the start of the next, and the step before's gives the velocity a hit
    interpolates from (model.record_hit);
  - the pair test culls with the generic kernel's segment spheres (no temporal bookkeeping to keep per thread);
    like every culled variant it gives the all-pairs record.

Tiles are laid out [.., node, lane], so the threads of a warp touch consecutive words. Writing a tile element
synchronises the block, so every thread of a block runs the same steps: a finished chain (blown up, stopped at
its hit, or past the end of the batch) keeps stepping but writes nothing, and a block stops once none of its chains
runs. Launch with block_dim=BLOCK over a multiple of BLOCK threads (RopeSim does). On the CPU a block has one
thread unless wp.config.enable_cpu_blocks is set; the results are the same either way.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope import model as chain

BLOCK = 32  # chains (threads) per block: one warp, so a block barrier costs no waiting on other warps
OPTIONS = {"enable_backward": False, "optimization_level": 3, "cpu_compiler_flags": "-march=native",
           "max_unroll": 64, "block_dim": BLOCK}
MAX_NODES = 16  # sm_90 build within 255 registers and a few spilled words (tests/test_cuda_build.py)
_CACHE: dict = {}


def tiled_kernel(n: int):
    key = int(n)
    if key not in _CACHE:
        if not 3 <= key <= MAX_NODES:
            raise ValueError(f"the tiled kernel covers 3..{MAX_NODES} nodes, got {n}")
        _CACHE[key] = _build(key)
    return _CACHE[key]


def _build(n: int):
    N = n
    NM1 = n - 1
    LAST = n - 1
    BEND_ORDER = [i for c in range(3) for i in range(1 + c, n - 1, 3)]
    LINK_ORDER = [i for p in range(2) for i in range(p, n - 1, 2)]
    NBEND = len(BEND_ORDER)
    NLINK = len(LINK_ORDER)
    BEND_FIRST = [k for k in range(NBEND) if k == 0 or BEND_ORDER[k] % 3 != BEND_ORDER[k - 1] % 3]  # of a colour
    LINK_FIRST = [k for k in range(NLINK) if k == 0 or LINK_ORDER[k] % 2 != LINK_ORDER[k - 1] % 2]
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)
    Vec = wp.types.vector(length=n, dtype=wp.float32)
    W, IB, FA, FB = range(4)  # rows of the per-node constants tile

    # grid_stride=False: one chain per thread; the loop Warp otherwise wraps around the body costs registers
    @chain.rollout_variant(module="unique", module_options=OPTIONS, grid_stride=False)
    def rollout_tiled(state, hand, path_index, params, cfg, step0, nsteps, stop_at_hit, events, offset, end):
        tid = wp.tid()
        lane = tid % BLOCK
        b = wp.min(tid + offset, end - 1)  # threads past the end mirror the last chain and never write
        st = events.status[b]
        act = chain.running(st, stop_at_hit)
        if tid + offset >= end:
            act = 0
        m, ml, slope, alpha_t, gamma, at_s, dl, dq = chain.chain_constants(params, cfg, b)
        dt = cfg.dt
        link = cfg.link
        margin = cfg.margin
        min_sep = cfg.min_sep
        cull = cfg.cull
        two_r = 2.0 * params.radius[b]
        cl = events.clearance[b]
        vmax2 = cfg.vmax * cfg.vmax
        inv_dt = 1.0 / dt
        nseg = cfg.n - 1  # a run-time bound keeps the pair loops rolled (code size)
        # per node: inverse mass, bending factor 1 / ((1 + gamma)(w0 + 4 w1 + w2) + alpha~) by centre node, and
        # the links' mass-weighted shares by first node (fixed.py's W, IB, FA, FB)
        K = wp.tile_empty(shape=(4, N, BLOCK), dtype=float, storage="shared")
        for i in range(N):
            K[W, i, lane] = chain.node_w(i, N, m, ml, slope)
        for i in range(1, NM1):
            K[IB, i, lane] = 1.0 / ((1.0 + gamma) * (K[W, i - 1, lane] + 4.0 * K[W, i, lane] + K[W, i + 1, lane])
                                    + alpha_t)
        for i in range(NM1):
            den = K[W, i, lane] + K[W, i + 1, lane] + at_s
            K[FA, i, lane] = K[W, i, lane] / den
            K[FB, i, lane] = K[W, i + 1, lane] / den
        X = wp.tile_empty(shape=(3, N, BLOCK), dtype=wp.vec3, storage="shared")  # [step modulo 3, node, lane]
        S = wp.tile_empty(shape=(NM1, BLOCK), dtype=wp.vec4, storage="shared")  # segment spheres
        BARRIER = wp.tile_empty(shape=(BLOCK,), dtype=float, storage="shared")
        P = Mat()
        L = Mat()  # bending multipliers (row i: centre node i)
        LL = Vec()  # link multipliers
        for i in range(N):
            X[(step0 + 2) % 3, i, lane] = state.pos[b, i]
            # the step before the launch's first, as its velocity says, for a hit in that first step: a branch to
            # state.vel in the hit's loop instead spilled 224 bytes a thread on sm_90 (16 without)
            X[(step0 + 1) % 3, i, lane] = state.pos[b, i] - dt * state.vel[b, i]
        for step in range(step0, step0 + nsteps):
            cur = step % 3  # X[cur]: the positions at the end of this step, written once its passes are done
            prv = (step + 2) % 3  # the positions at the start of this step
            old = (step + 1) % 3  # those at the start of the step before
            # no chain state stays in registers from one step to the next (the pair test needs them for its own):
            # positions and velocities come back from the shared copies, bit for bit what the last step computed
            P[0] = hand[path_index[b], step + 1]
            for i in range(1, N):
                xi = X[prv, i, lane]
                vi = state.vel[b, i]
                if step != step0:
                    vi = (xi - X[old, i, lane]) * inv_dt
                li = link
                if i == LAST:
                    li = 0.5 * link
                xn, vn = chain.predict(xi, vi, K[W, i, lane], li, dl, dq, dt, cfg.gravity)
                P[i] = xn
                L[i] = wp.vec3(0.0)
                LL[i - 1] = 0.0
            for it in range(cfg.iters):
                for kk in range(NBEND):
                    # a block barrier per colour: without one the compiler loads every shared value a pass reads
                    # once, up front, and keeps it in a register for the whole pass (at N = 16, 75 constants and 48
                    # start positions), which spills the multipliers to the stack frame
                    if wp.static(kk in BEND_FIRST):
                        BARRIER[lane] = float(it)
                    i0 = wp.static(BEND_ORDER[kk] - 1)
                    i1 = wp.static(BEND_ORDER[kk])
                    i2 = wp.static(BEND_ORDER[kk] + 1)
                    # the curvature at the start of the step damps the bending
                    c_start = X[prv, i0, lane] - 2.0 * X[prv, i1, lane] + X[prv, i2, lane]
                    x0, x1, x2, lm = chain.bend_project(P[i0], P[i1], P[i2], c_start, L[i1], K[W, i0, lane],
                                                        K[W, i1, lane], K[W, i2, lane], K[IB, i1, lane], alpha_t, gamma)
                    P[i0] = x0
                    P[i1] = x1
                    P[i2] = x2
                    L[i1] = lm
                for kk in range(NLINK):
                    if wp.static(kk in LINK_FIRST):
                        BARRIER[lane] = float(it)
                    ia = wp.static(LINK_ORDER[kk])
                    ib = wp.static(LINK_ORDER[kk] + 1)
                    wa = K[W, ia, lane]
                    xa, xb, ll = chain.link_project(P[ia], P[ib], LL[ia], link, at_s, K[FA, ia, lane], K[FB, ia, lane],
                                                    wa + K[W, ib, lane] + at_s)
                    P[ia] = xa
                    P[ib] = xb
                    LL[ia] = ll
            vv = float(0.0)
            for i in range(N):
                v = (P[i] - X[prv, i, lane]) * inv_dt
                vv = vv + wp.dot(v, v)  # a sum propagates NaN (max would drop it)
            if act != 0 and not (vv < vmax2):
                act = 0
                events.status[b] = 2
                events.clearance[b] = cl
                for i in range(N):
                    state.pos[b, i] = P[i]
                    state.vel[b, i] = (P[i] - X[prv, i, lane]) * inv_dt
                fr = chain.frames_from(step, cfg.frame_every, cfg.frame_end)
                for k in range(fr[0], fr[1] + 1):
                    for i in range(N):
                        state.frames[k, b, i] = P[i]
            # ---- self-collision, on the shared copies (the pair loops index nodes at run time)
            for i in range(N):
                X[cur, i, lane] = P[i]
            for a in range(NM1):
                pa = P[a]
                pb = P[a + 1]
                mid = 0.5 * (pa + pb)
                S[a, lane] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
            best = float(2.0)
            best_a = int(-1)
            best_b = int(-1)
            if act != 0:
                for a in range(nseg - min_sep):
                    sa = S[a, lane]
                    for j in range(a + min_sep, nseg):
                        sb = S[j, lane]
                        far = chain.spheres_apart(sa, sb, two_r, margin)
                        if cull == 0 or not far:
                            res = chain.seg_closest(X[cur, a, lane], X[cur, a + 1, lane], X[cur, j, lane],
                                              X[cur, j + 1, lane])
                            gap = res[0] - two_r
                            if not far:
                                cl = wp.min(cl, wp.min(gap, margin))
                            if gap <= 0.0 and st == 0:
                                best, best_a, best_b = chain.first_contact(gap, X[prv, a, lane], X[prv, a + 1, lane],
                                                                           X[prv, j, lane], X[prv, j + 1, lane], two_r,
                                                                           a, j, best, best_a, best_b)
                        elif margin < cl:
                            cl = margin
            if best_a >= 0:
                st = 1
                events.status[b] = 1
                events.hit_frame[b] = step + 1
                events.hit_alpha[b] = best
                for i in range(N):
                    p0 = X[prv, i, lane]
                    p1 = X[cur, i, lane]
                    events.crit_pos[b, i] = p0 + best * (p1 - p0)
                    events.crit_vel[b, i] = chain.hit_velocity((p1 - p0) * inv_dt, (p0 - X[old, i, lane]) * inv_dt,
                                                               best, step)
                res = chain.seg_closest(X[cur, best_a, lane], X[cur, best_a + 1, lane], X[cur, best_b, lane],
                                  X[cur, best_b + 1, lane])
                events.hit_s[b] = wp.vec2((float(best_a) + res[1]) / float(NM1), (float(best_b) + res[2]) / float(NM1))
                if stop_at_hit != 0:
                    act = 0
                    events.clearance[b] = cl
                    for i in range(N):
                        p1 = X[cur, i, lane]
                        state.pos[b, i] = p1
                        state.vel[b, i] = (p1 - X[prv, i, lane]) * inv_dt
                    fr = chain.frames_from(step, cfg.frame_every, cfg.frame_end)
                    for k in range(fr[0], fr[1] + 1):
                        for i in range(N):
                            state.frames[k, b, i] = X[cur, i, lane]
            frame = chain.frame_after(step, cfg.frame_every, cfg.frame_end)
            if act != 0 and frame >= 0:
                for i in range(N):
                    state.frames[frame, b, i] = X[cur, i, lane]
            if wp.tile_max(wp.tile(act))[0] == 0:  # the block's chains have all finished
                break
        if act != 0 and nsteps > 0:  # chains that ran every step (with none, the state stays as it was)
            cur = (step0 + nsteps - 1) % 3
            events.clearance[b] = cl
            for i in range(N):
                p1 = X[cur, i, lane]
                state.pos[b, i] = p1
                state.vel[b, i] = (p1 - X[(step0 + nsteps + 1) % 3, i, lane]) * inv_dt

    return rollout_tiled
