"""SIMD-lane variant of kernels/rope_fast.py: LANES chains per thread, one per vector lane.

Same model, same operation order, same arguments (plus `end`), and bit-identical results
(tests/test_rope_kernel.py compares it with the generic kernel testing every pair). A Warp CPU
launch runs its threads one after another, so a thread that holds one chain leaves the CPU's
vector units idle; here a thread holds LANES chains and keeps each coordinate of each node as a
length-LANES vector, so the integration and every constraint pass are element-wise vector
operations that the compiler turns into AVX instructions (measured on this CPU's AVX-512: the
constraint passes of 16 chains take the time of 2). The arithmetic of every lane is exactly the
scalar kernel's, so the results are the same bits.

The self-collision test stays scalar, lane by lane, as rope_fast.py does it: temporal culling
with each lane's own bounds up to TEMPORAL_MAX_NODES nodes, spatial culling beyond (it branches
on the chain's geometry, which lanes do not share). Lanes whose chain is finished (blown up, or
hit with stop_at_hit) are still integrated (their neighbours need the vector width) but write
nothing more and skip the collision test; a thread returns once all of its lanes are finished.
Measured (bench, one run, batch 4096, 2 cores): N = 16 2.3x, N = 21 2.0x, N = 32 1.9x the
one-chain-per-thread kernel.
"""
from __future__ import annotations

import warp as wp

from wrenorm.kernels.rope.model import node_w, seg_closest
from wrenorm.kernels.rope.fixed import _OPTIONS, BLOCK, MAX_NODES, TEMPORAL_MAX_NODES

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
    BS = BLOCK
    NB = (n - 1 + BLOCK - 1) // BLOCK
    BLO = [blk * BS for blk in range(NB)]
    BHI = [min(blk * BS + BS, n - 1) + 1 for blk in range(NB)]
    LV = wp.types.vector(length=L, dtype=wp.float32)  # one value per lane
    LI = wp.types.vector(length=L, dtype=wp.int32)
    LM = wp.types.matrix(shape=(N, L), dtype=wp.float32)  # per node (row), per lane (column)
    LF = wp.types.matrix(shape=(L, NB * NB if n <= TEMPORAL_MAX_NODES else 1), dtype=wp.float32)  # per lane, block pair
    Mat = wp.types.matrix(shape=(n, 3), dtype=wp.float32)  # one lane's chain, for the pair test
    Seg = wp.types.matrix(shape=(n, 4), dtype=wp.float32)
    BVec = wp.types.vector(length=NB, dtype=wp.float32)
    BMat = wp.types.matrix(shape=(NB, 3), dtype=wp.float32)
    Flags = wp.types.matrix(shape=(NB, NB), dtype=wp.float32)
    Blk = wp.types.matrix(shape=(NB, 4), dtype=wp.float32)
    TEMPORAL = n <= TEMPORAL_MAX_NODES
    NBT = NB * NB if TEMPORAL else 1  # per-lane temporal-culling state (none for spatial culling)

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def rollout_lanes(
        pos: wp.array2d(dtype=wp.vec3),
        vel: wp.array2d(dtype=wp.vec3),
        prev: wp.array2d(dtype=wp.vec3),
        lam: wp.array2d(dtype=wp.vec3),
        lam_link: wp.array2d(dtype=float),
        seg: wp.array2d(dtype=wp.vec4),
        hand: wp.array2d(dtype=wp.vec3),
        path_index: wp.array(dtype=wp.int32),
        node_mass: wp.array(dtype=float),
        lead_mass: wp.array(dtype=float),
        bend_k: wp.array(dtype=float),
        bend_b: wp.array(dtype=float),
        drag_lin: wp.array(dtype=float),
        drag_quad: wp.array(dtype=float),
        radius: wp.array(dtype=float),
        mass_slope: wp.array(dtype=float),
        stretch: wp.array(dtype=float),
        n: int,
        min_sep: int,
        link: float,
        dt: float,
        gravity: wp.vec3,
        iters: int,
        cull: int,
        margin: float,
        vmax: float,
        step0: int,
        nsteps: int,
        stop_at_hit: int,
        status: wp.array(dtype=wp.int32),
        hit_frame: wp.array(dtype=wp.int32),
        hit_alpha: wp.array(dtype=float),
        hit_s: wp.array(dtype=wp.vec2),
        crit_pos: wp.array2d(dtype=wp.vec3),
        crit_vel: wp.array2d(dtype=wp.vec3),
        clearance: wp.array(dtype=float),
        offset: int,
        end: int,
    ):
        base = offset + wp.tid() * L
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
            st = status[b]
            ST[l] = st
            act = int(1)
            if base + l >= end or st == 2 or (st == 1 and stop_at_hit != 0):
                act = 0
            ACT[l] = act
            n_act += act
            PATH[l] = path_index[b]
            m = node_mass[b]
            ml = lead_mass[b]
            slope = mass_slope[b]
            k = wp.max(bend_k[b], 1.0e-12)
            alpha_t = link * link / (k * dt * dt)
            gamma = bend_b[b] / (k * dt)
            ALPHA[l] = alpha_t
            GAMMA[l] = gamma
            for i in range(N):
                W[i, l] = node_w(i, N, m, ml, slope)
            for i in range(1, NM1):
                IB[i, l] = 1.0 / ((1.0 + gamma) * (W[i - 1, l] + 4.0 * W[i, l] + W[i + 1, l]) + alpha_t)
            at_s = stretch[b] / (dt * dt)
            ATS[l] = at_s
            for i in range(NM1):
                den = W[i, l] + W[i + 1, l] + at_s
                FA[i, l] = W[i, l] / den
                FB[i, l] = W[i + 1, l] / den
                GL[i, l] = den
            DL[l] = drag_lin[b]
            DQ[l] = drag_quad[b]
            TWO_R[l] = 2.0 * radius[b]
            CL[l] = clearance[b]
            for i in range(N):
                p = pos[b, i]
                v = vel[b, i]
                X[i, l] = p[0]
                Y[i, l] = p[1]
                Z[i, l] = p[2]
                VX[i, l] = v[0]
                VY[i, l] = v[1]
                VZ[i, l] = v[2]
        if n_act == 0:
            return
        vmax2 = vmax * vmax
        inv_dt = 1.0 / dt
        nm1 = n - 1
        npair_a = nm1 - min_sep
        tol_link = 2.0e-3 * link + 1.0e-5
        chain_len = float(N) * link
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
        # temporal culling state of every lane (see rope_fast.py), block pair (ba, bb) at ba * NB + bb
        KB = LF()
        CP = LF()
        for l in range(nl):
            for q in range(NBT):
                KB[l, q] = -1.0e30
        G = LV()
        # one lane's chain and the scratch of its pair test
        P = Mat()
        Q = Mat()
        S = Seg()
        FAR = Flags()
        MB = Flags()
        UB = BMat()
        DB = BVec()
        NEED = BVec()
        CB = Blk()
        for step in range(step0, step0 + nsteps):
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
            for it in range(iters):
                # bending in three colours (centre i mod 3), then links in two: the scalar order
                for c3 in range(3):
                    for i in range(1 + c3, nm1, 3):
                        x0 = X[i - 1]
                        y0 = Y[i - 1]
                        z0 = Z[i - 1]
                        x1 = X[i]
                        y1 = Y[i]
                        z1 = Z[i]
                        x2 = X[i + 1]
                        y2 = Y[i + 1]
                        z2 = Z[i + 1]
                        cvx = x0 - 2.0 * x1 + x2
                        cvy = y0 - 2.0 * y1 + y2
                        cvz = z0 - 2.0 * z1 + z2
                        lmx = LX[i]
                        lmy = LY[i]
                        lmz = LZ[i]
                        ib = IB[i]
                        dlx = wp.cw_mul(-cvx - wp.cw_mul(ALPHA, lmx) - wp.cw_mul(GAMMA, cvx - CX[i]), ib)
                        dly = wp.cw_mul(-cvy - wp.cw_mul(ALPHA, lmy) - wp.cw_mul(GAMMA, cvy - CY[i]), ib)
                        dlz = wp.cw_mul(-cvz - wp.cw_mul(ALPHA, lmz) - wp.cw_mul(GAMMA, cvz - CZ[i]), ib)
                        LX[i] = lmx + dlx
                        LY[i] = lmy + dly
                        LZ[i] = lmz + dlz
                        w0 = W[i - 1]
                        w1 = 2.0 * W[i]
                        w2 = W[i + 1]
                        X[i - 1] = x0 + wp.cw_mul(w0, dlx)
                        Y[i - 1] = y0 + wp.cw_mul(w0, dly)
                        Z[i - 1] = z0 + wp.cw_mul(w0, dlz)
                        X[i] = x1 - wp.cw_mul(w1, dlx)
                        Y[i] = y1 - wp.cw_mul(w1, dly)
                        Z[i] = z1 - wp.cw_mul(w1, dlz)
                        X[i + 1] = x2 + wp.cw_mul(w2, dlx)
                        Y[i + 1] = y2 + wp.cw_mul(w2, dly)
                        Z[i + 1] = z2 + wp.cw_mul(w2, dlz)
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
            # ---- per lane: blow-up, then the scalar self-collision test of rope_fast.py
            for l in range(nl):
                if ACT[l] == 0:
                    continue
                b = base + l
                for i in range(N):
                    P[i] = wp.vec3(X[i, l], Y[i, l], Z[i, l])
                if not (vv[l] < vmax2):
                    status[b] = 2
                    clearance[b] = CL[l]
                    for i in range(N):
                        pos[b, i] = P[i]
                        vel[b, i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])
                    ACT[l] = 0
                    n_act -= 1
                    continue
                for i in range(N):
                    Q[i] = wp.vec3(QX[i, l], QY[i, l], QZ[i, l])
                st = ST[l]
                cl = CL[l]
                two_r = TWO_R[l]
                any_t = int(1)
                if wp.static(TEMPORAL):
                    scale = wp.length(P[0]) + chain_len
                    if cull != 0:
                        for blk in range(NB):
                            su = wp.vec3(0.0)
                            for i in range(wp.static(BLO[blk]), wp.static(BHI[blk])):
                                su = su + (P[i] - Q[i])
                            u = su * wp.static(1.0 / float(BHI[blk] - BLO[blk]))
                            dB = float(0.0)
                            for i in range(wp.static(BLO[blk]), wp.static(BHI[blk])):
                                dr = P[i] - Q[i] - u
                                dB = wp.max(dB, wp.abs(dr[0]) + wp.abs(dr[1]) + wp.abs(dr[2]))
                            UB[blk] = u
                            DB[blk] = dB
                        gmx = float(0.0)
                        for ba in range(NB):
                            for bb in range(ba, NB):
                                du = UB[ba] - UB[bb]
                                inc = (DB[ba] + DB[bb] + wp.abs(du[0]) + wp.abs(du[1]) + wp.abs(du[2])) * 1.001 + 1.0e-6 * scale
                                CP[l, ba * NB + bb] = CP[l, ba * NB + bb] + inc
                                gmx = wp.max(gmx, inc)
                        G[l] = G[l] + gmx
                    thr = wp.min(cl, margin)
                    if st == 0:
                        thr = wp.max(thr, 0.0)
                    lim = thr + tol_link + 4.0e-6 * scale + 4.0e-6 * G[l]
                    any_t = int(0)
                    for ba in range(NB):
                        for bb in range(ba, NB):
                            FAR[ba, bb] = 0.0
                            if cull != 0 and KB[l, ba * NB + bb] - CP[l, ba * NB + bb] > lim:
                                FAR[ba, bb] = 1.0
                            else:
                                any_t = 1
                                MB[ba, bb] = 1.0e30
                                NEED[ba] = 1.0
                                NEED[bb] = 1.0
                    for blk in range(NB):
                        if NEED[blk] > 0.5:
                            NEED[blk] = 0.0
                            for a in range(wp.static(BLO[blk]), wp.static(BHI[blk] - 1)):
                                pa = P[a]
                                pb = P[a + 1]
                                mid = 0.5 * (pa + pb)
                                S[a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
                else:
                    for a in range(nm1):
                        pa = P[a]
                        pb = P[a + 1]
                        mid = 0.5 * (pa + pb)
                        S[a] = wp.vec4(mid[0], mid[1], mid[2], 0.5 * wp.length(pb - pa))
                    for blk in range(NB):
                        cen = wp.vec3(0.0)
                        cnt = float(0.0)
                        for a in range(blk * BS, wp.min(blk * BS + BS, nm1)):
                            cen = cen + wp.vec3(S[a][0], S[a][1], S[a][2])
                            cnt = cnt + 1.0
                        cen = cen / cnt
                        rad = float(0.0)
                        for a in range(blk * BS, wp.min(blk * BS + BS, nm1)):
                            rad = wp.max(rad, wp.length(wp.vec3(S[a][0], S[a][1], S[a][2]) - cen) + S[a][3])
                        CB[blk] = wp.vec4(cen[0], cen[1], cen[2], rad * 1.00001 + 1.0e-6)
                    for ba in range(NB):
                        for bb in range(ba, NB):
                            d = wp.vec3(CB[ba][0] - CB[bb][0], CB[ba][1] - CB[bb][1], CB[ba][2] - CB[bb][2])
                            reach_b = (CB[ba][3] + CB[bb][3] + two_r + margin) * 1.0001 + 1.0e-5
                            FAR[ba, bb] = 0.0
                            if cull != 0 and wp.dot(d, d) > reach_b * reach_b:
                                FAR[ba, bb] = 1.0
                best = float(2.0)
                best_a = int(-1)
                best_b = int(-1)
                if cull != 0 and npair_a > 0 and margin < cl:
                    cl = margin
                for a in range(npair_a * any_t):
                    sa = S[a]
                    blk_a = a // BS
                    j_first = a + min_sep
                    for blk in range(j_first // BS, NB):
                        if FAR[blk_a, blk] > 0.5:
                            continue
                        for j in range(wp.max(j_first, blk * BS), wp.min(blk * BS + BS, nm1)):
                            sb = S[j]
                            dx = sa[0] - sb[0]
                            dy = sa[1] - sb[1]
                            dz = sa[2] - sb[2]
                            reach = (sa[3] + sb[3] + two_r + margin) * 1.00001 + 1.0e-6
                            far = dx * dx + dy * dy + dz * dz > reach * reach
                            if cull == 0 or not far:
                                res = seg_closest(P[a], P[a + 1], P[j], P[j + 1])
                                gap = res[0] - two_r
                                if wp.static(TEMPORAL):
                                    MB[blk_a, blk] = wp.min(MB[blk_a, blk], gap)
                                if not far:
                                    cl = wp.min(cl, wp.min(gap, margin))
                                if gap <= 0.0 and st == 0:
                                    r0 = seg_closest(Q[a], Q[a + 1], Q[j], Q[j + 1])
                                    g0 = r0[0] - two_r
                                    al = float(0.0)
                                    if g0 > 0.0:
                                        al = g0 / (g0 - gap)
                                    if al < best:
                                        best = al
                                        best_a = a
                                        best_b = j
                            elif wp.static(TEMPORAL):
                                MB[blk_a, blk] = wp.min(MB[blk_a, blk], wp.sqrt(dx * dx + dy * dy + dz * dz) - sa[3] - sb[3] - two_r)
                if wp.static(TEMPORAL):
                    for ba in range(NB):
                        for bb in range(ba, NB):
                            if FAR[ba, bb] < 0.5:
                                KB[l, ba * NB + bb] = MB[ba, bb] + CP[l, ba * NB + bb]
                CL[l] = cl
                if best_a >= 0:
                    ST[l] = 1
                    status[b] = 1
                    hit_frame[b] = step + 1
                    hit_alpha[b] = best
                    for i in range(N):
                        p0 = Q[i]
                        crit_pos[b, i] = p0 + best * (P[i] - p0)
                        crit_vel[b, i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])
                    res = seg_closest(P[best_a], P[best_a + 1], P[best_b], P[best_b + 1])
                    hit_s[b] = wp.vec2((float(best_a) + res[1]) / float(NM1), (float(best_b) + res[2]) / float(NM1))
                    if stop_at_hit != 0:
                        clearance[b] = cl
                        for i in range(N):
                            pos[b, i] = P[i]
                            vel[b, i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])
                        ACT[l] = 0
                        n_act -= 1
            if n_act == 0:
                return
        for l in range(nl):
            if ACT[l] != 0:
                b = base + l
                clearance[b] = CL[l]
                for i in range(N):
                    pos[b, i] = wp.vec3(X[i, l], Y[i, l], Z[i, l])
                    vel[b, i] = wp.vec3(VX[i, l], VY[i, l], VZ[i, l])

    return rollout_lanes
