"""SIMD-lane variant of fixed.py: LANES chains per thread, one per vector lane.

Same model, same operation order, same arguments, and bit-identical results
(tests/test_rope_kernel.py compares it with the generic kernel testing every pair). A Warp CPU
launch runs its threads one after another, so a thread that holds one chain leaves the CPU's
vector units idle; here a thread holds LANES chains and keeps each coordinate of each node as a
length-LANES vector, so the integration and every constraint pass are element-wise vector
operations that the compiler turns into AVX instructions (measured on this CPU's AVX-512: the
constraint passes of 16 chains take the time of 2). The arithmetic of every lane is exactly the
scalar kernel's, so the results are the same bits.

The self-collision test stays scalar, lane by lane: collide.py's test, shared with fixed.py, with each
lane's own temporal bounds up to TEMPORAL_MAX_NODES nodes, spatial culling beyond (it branches on the
chain's geometry, which lanes do not share). Lanes whose chain is finished (blown up, or
hit with stop_at_hit) are still integrated (their neighbours need the vector width) but write
nothing more and skip the collision test; a thread returns once all of its lanes are finished.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.collide import TEMPORAL_MAX_NODES, collide_func, finish_func, types
from wrenorm.kernels.rope.fixed import MAX_NODES, OPTIONS
from wrenorm.kernels.rope.model import (
    bend_lanes,
    chain_constants,
    frame_after,
    node_w,
    record_hit,
    rollout_variant,
    running,
)

LANES = 16  # 16 float32 = one AVX-512 register; 8 lanes ran the constraint passes a third slower per chain
_CACHE: dict = {}


def lanes_kernel(n: int, lanes: int = LANES):
    key = (int(n), int(lanes))
    if key not in _CACHE:
        if not 3 <= key[0] <= MAX_NODES:
            raise ValueError(f"the lane kernel covers 3..{MAX_NODES} nodes, got {n}")
        _CACHE[key] = _build(*key)
    return _CACHE[key]


def _build(n: int, lanes: int):
    N = n
    NM1 = n - 1
    L = lanes
    t = types(n)
    NB = t["NB"]
    Mat, Flags = t["Mat"], t["Flags"]  # one lane's chain and culling state, for the shared collision test
    LV = wp.types.vector(length=L, dtype=wp.float32)  # one value per lane
    LI = wp.types.vector(length=L, dtype=wp.int32)
    LM = wp.types.matrix(shape=(N, L), dtype=wp.float32)  # per node (row), per lane (column)
    LF = wp.types.matrix(shape=(L, NB * NB if n <= TEMPORAL_MAX_NODES else 1), dtype=wp.float32)  # per lane, block pair
    collide = collide_func(n)
    finish = finish_func(n)
    TEMPORAL = n <= TEMPORAL_MAX_NODES
    NBT = NB * NB if TEMPORAL else 1  # per-lane temporal-culling state (none for spatial culling)

    @rollout_variant(module="unique", module_options=OPTIONS)
    def rollout_lanes(state, hand, path_index, params, cfg, step0, nsteps, stop_at_hit, events, offset, end):
        base = offset + wp.tid() * L
        n = cfg.n
        dt = cfg.dt
        link = cfg.link
        margin = cfg.margin
        min_sep = cfg.min_sep
        cull = cfg.cull
        gravity = cfg.gravity
        nl = L + 0 * end  # a runtime bound keeps the per-lane scalar loops rolled (16 copies: minutes to build)
        # ---- per-lane constants, as the scalar kernel computes them per chain
        ACT = LI()  # 1 while the lane's chain runs and writes
        ST = LI()
        PATH = LI()
        ALPHA = LV()
        GAMMA = LV()
        ATS = LV()
        DL = LV()
        DQ = LV()
        TWO_R = LV()
        CL = LV()
        W = LM()
        IB = LM()
        FA = LM()
        FB = LM()
        GL = LM()
        X = LM()
        Y = LM()
        Z = LM()
        VX = LM()
        VY = LM()
        VZ = LM()
        n_act = int(0)
        for l in range(nl):
            b = wp.min(base + l, end - 1)  # lanes past the end mirror the last chain and never write
            st = events.status[b]
            ST[l] = st
            act = running(st, stop_at_hit)
            if base + l >= end:
                act = 0
            ACT[l] = act
            n_act += act
            PATH[l] = path_index[b]
            m, ml, slope, alpha_t, gamma, at_s, dl, dq = chain_constants(params, cfg, b)
            ALPHA[l] = alpha_t
            GAMMA[l] = gamma
            for i in range(N):
                W[i, l] = node_w(i, N, m, ml, slope)
            for i in range(1, NM1):
                IB[i, l] = 1.0 / ((1.0 + gamma) * (W[i - 1, l] + 4.0 * W[i, l] + W[i + 1, l]) + alpha_t)
            ATS[l] = at_s
            for i in range(NM1):
                den = W[i, l] + W[i + 1, l] + at_s
                FA[i, l] = W[i, l] / den
                FB[i, l] = W[i + 1, l] / den
                GL[i, l] = den
            DL[l] = dl
            DQ[l] = dq
            TWO_R[l] = 2.0 * params.radius[b]
            CL[l] = events.clearance[b]
            for i in range(N):
                p = state.pos[b, i]
                v = state.vel[b, i]
                X[i, l] = p[0]
                Y[i, l] = p[1]
                Z[i, l] = p[2]
                VX[i, l] = v[0]
                VY[i, l] = v[1]
                VZ[i, l] = v[2]
        if n_act == 0:
            return
        vmax2 = cfg.vmax * cfg.vmax
        inv_dt = 1.0 / dt
        nm1 = n - 1
        GX = LV(gravity[0])
        GY = LV(gravity[1])
        GZ = LV(gravity[2])
        ONE = LV(1.0)
        QX = LM()
        QY = LM()
        QZ = LM()
        LX = LM()  # bending multipliers (row i: centre node i)
        LY = LM()
        LZ = LM()
        LL = LM()  # link multipliers
        CX = LM()  # curvature at the start of the step
        CY = LM()
        CZ = LM()
        # temporal culling state of every lane (collide.py), block pair (ba, bb) at ba * NB + bb
        KB = LF()
        CP = LF()
        for l in range(nl):
            for q in range(NBT):
                KB[l, q] = -1.0e30
        G = LV()
        # one lane's chain and the scratch of its pair test
        P = Mat()
        Q = Mat()
        V = Mat()
        VB = Mat()
        BX = LM()  # velocities of the step before, for the hit's (record_hit)
        BY = LM()
        BZ = LM()
        KBl = Flags()
        CPl = Flags()
        for step in range(step0, step0 + nsteps):
            for i in range(n):
                BX[i] = VX[i]
                BY[i] = VY[i]
                BZ[i] = VZ[i]
            QX[0] = X[0]
            QY[0] = Y[0]
            QZ[0] = Z[0]
            for l in range(L):
                h = hand[PATH[l], step + 1]
                X[0, l] = h[0]
                Y[0, l] = h[1]
                Z[0, l] = h[2]
            # node loops stay rolled (runtime bounds): unrolled, 16-lane code takes minutes to build
            # and measured no faster; each row operation is one vector instruction per 16 lanes
            for i in range(1, n):
                xi = X[i]
                yi = Y[i]
                zi = Z[i]
                QX[i] = xi
                QY[i] = yi
                QZ[i] = zi
                li = link
                if i == n - 1:
                    li = 0.5 * link
                sq = wp.cw_mul(VX[i], VX[i]) + wp.cw_mul(VY[i], VY[i]) + wp.cw_mul(VZ[i], VZ[i])
                sp = LV()
                for l in range(L):
                    sp[l] = wp.sqrt(sq[l])
                c = (DL + wp.cw_mul(DQ, sp)) * li
                inv = wp.cw_div(ONE, ONE + wp.cw_mul(dt * c, W[i]))
                vx = wp.cw_mul(VX[i] + dt * GX, inv)
                vy = wp.cw_mul(VY[i] + dt * GY, inv)
                vz = wp.cw_mul(VZ[i] + dt * GZ, inv)
                VX[i] = vx
                VY[i] = vy
                VZ[i] = vz
                X[i] = xi + dt * vx
                Y[i] = yi + dt * vy
                Z[i] = zi + dt * vz
                LX[i] = LV()
                LY[i] = LV()
                LZ[i] = LV()
                LL[i - 1] = LV()
            for i in range(1, nm1):
                CX[i] = QX[i - 1] - 2.0 * QX[i] + QX[i + 1]
                CY[i] = QY[i - 1] - 2.0 * QY[i] + QY[i + 1]
                CZ[i] = QZ[i - 1] - 2.0 * QZ[i] + QZ[i + 1]
            for _ in range(cfg.iters):
                # bending in three colours (centre i mod 3), then links in two: the scalar order
                for c3 in range(3):
                    for i in range(1 + c3, nm1, 3):
                        w0 = W[i - 1]
                        w1 = W[i]
                        w2 = W[i + 1]
                        ib = IB[i]
                        x0, x1, x2, lx = bend_lanes(X[i - 1], X[i], X[i + 1], CX[i], LX[i], ALPHA, GAMMA, ib, w0, w1,
                                                    w2)
                        y0, y1, y2, ly = bend_lanes(Y[i - 1], Y[i], Y[i + 1], CY[i], LY[i], ALPHA, GAMMA, ib, w0, w1,
                                                    w2)
                        z0, z1, z2, lz = bend_lanes(Z[i - 1], Z[i], Z[i + 1], CZ[i], LZ[i], ALPHA, GAMMA, ib, w0, w1,
                                                    w2)
                        X[i - 1] = x0
                        X[i] = x1
                        X[i + 1] = x2
                        Y[i - 1] = y0
                        Y[i] = y1
                        Y[i + 1] = y2
                        Z[i - 1] = z0
                        Z[i] = z1
                        Z[i + 1] = z2
                        LX[i] = lx
                        LY[i] = ly
                        LZ[i] = lz
                for p2 in range(2):
                    for i in range(p2, nm1, 2):
                        xa = X[i]
                        ya = Y[i]
                        za = Z[i]
                        xb = X[i + 1]
                        yb = Y[i + 1]
                        zb = Z[i + 1]
                        ex = xb - xa
                        ey = yb - ya
                        ez = zb - za
                        sq = wp.cw_mul(ex, ex) + wp.cw_mul(ey, ey) + wp.cw_mul(ez, ez)
                        ll = LL[i]
                        gl = GL[i]
                        f = LV()
                        for l in range(L):
                            ln = wp.sqrt(sq[l])
                            e = ln - link + ATS[l] * ll[l]
                            f[l] = wp.where(ln > 1.0e-9, e / ln, 0.0)
                            ll[l] = wp.where(ln > 1.0e-9, ll[l] - e / gl[l], ll[l])
                        LL[i] = ll
                        cx = wp.cw_mul(ex, f)
                        cy = wp.cw_mul(ey, f)
                        cz = wp.cw_mul(ez, f)
                        fa = FA[i]
                        fb = FB[i]
                        X[i] = xa + wp.cw_mul(fa, cx)
                        Y[i] = ya + wp.cw_mul(fa, cy)
                        Z[i] = za + wp.cw_mul(fa, cz)
                        X[i + 1] = xb - wp.cw_mul(fb, cx)
                        Y[i + 1] = yb - wp.cw_mul(fb, cy)
                        Z[i + 1] = zb - wp.cw_mul(fb, cz)
            vv = LV()
            for i in range(n):
                vx = (X[i] - QX[i]) * inv_dt
                vy = (Y[i] - QY[i]) * inv_dt
                vz = (Z[i] - QZ[i]) * inv_dt
                VX[i] = vx
                VY[i] = vy
                VZ[i] = vz
                vv = vv + (wp.cw_mul(vx, vx) + wp.cw_mul(vy, vy) + wp.cw_mul(vz, vz))
            # ---- per lane: blow-up, then the scalar self-collision test (collide.py)
            frame = frame_after(step, cfg.frame_every, cfg.frame_end)
            for l in range(nl):
                if ACT[l] == 0:
                    continue
                b = base + l
                for i in range(N):
                    P[i] = wp.vec3(X[i, l], Y[i, l], Z[i, l])
                if not (vv[l] < vmax2):
                    events.status[b] = 2
                    events.clearance[b] = CL[l]
                    for i in range(N):
                        V[i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])
                    finish(state, b, P, V, step, cfg.frame_every, cfg.frame_end)
                    ACT[l] = 0
                    n_act -= 1
                    continue
                for i in range(N):
                    Q[i] = wp.vec3(QX[i, l], QY[i, l], QZ[i, l])
                if wp.static(TEMPORAL):
                    for q in range(NBT):
                        KBl[q // NB, q % NB] = KB[l, q]
                        CPl[q // NB, q % NB] = CP[l, q]
                best, best_a, best_b, cl, KBl, CPl, Gl = collide(P, Q, KBl, CPl, G[l], CL[l], ST[l], TWO_R[l], margin,
                                                                 min_sep, cull, link, nm1)
                if wp.static(TEMPORAL):
                    G[l] = Gl
                    for q in range(NBT):
                        KB[l, q] = KBl[q // NB, q % NB]
                        CP[l, q] = CPl[q // NB, q % NB]
                CL[l] = cl
                if best_a >= 0:
                    ST[l] = 1
                    for i in range(N):
                        V[i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])
                        VB[i] = wp.vec3(BX[i, l], BY[i, l], BZ[i, l])
                    record_hit(events, b, step, best, best_a, best_b, P, Q, V, VB, NM1)
                    if stop_at_hit != 0:
                        events.clearance[b] = cl
                        finish(state, b, P, V, step, cfg.frame_every, cfg.frame_end)
                        ACT[l] = 0
                        n_act -= 1
                        continue
                if frame >= 0:
                    for i in range(N):
                        state.frames[frame, b, i] = P[i]
            if n_act == 0:
                return
        for l in range(nl):
            if ACT[l] != 0:
                b = base + l
                events.clearance[b] = CL[l]
                for i in range(N):
                    state.pos[b, i] = wp.vec3(X[i, l], Y[i, l], Z[i, l])
                    state.vel[b, i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])

    return rollout_lanes
