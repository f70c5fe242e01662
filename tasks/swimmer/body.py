"""The robot fish as parts on a kinematic chain, and its prescribed tail motion per rate.

Geometry (srl-ethz/fishsim hardware figures; head frame: origin at head marker 0, x towards the
tail, metres). Each fluid part is the ellipsoid whose semi-axes are the half-sizes of the box that
MuJoCo's model gives that part (MuJoCo uses box half-sizes as the ellipsoid's semi-axes).
Left out: the rotating crank (it turns about the lateral axis, out of this plane), the tendon
guides and the 1 mm connector strips between plates (small; the coefficients absorb them).

Tail kinematics: the head-frame tail markers of each video are fitted by a travelling wave
y(xi, t) = sum_n xi^n sum_k [A_nk cos 2pi k f t + B_nk sin 2pi k f t], n = 1..3 (the head end
does not move sideways), k = 0..3, xi the position between the tail-base marker and the tip marker.
The robot's links (five plates and the fin) are then laid along that curve joint by joint, which
gives each link's angle relative to the head over one tail beat; a 3-harmonic Fourier series of
those angles, mean removed (the head axis from two markers carries a small unknown offset), is
the prescribed gait.

Coarser tails (merge_links): consecutive links merged into one rigid body each, for the
resolution flow over the number of tail bodies. A merged link points along the chord between
the robot's gait joints at the ends of its run, so the joints the coarse fish keeps move as the
robot's do.
"""
from __future__ import annotations

import math

import numpy as np

from wrenorm.kernels import swimmer as kern
from wrenorm.tasks.swimmer.options import DEFAULT_DT

# head parts: (x centre, semi-axes)
HEAD_FLUID = [
    (0.077, (0.077, 0.0025, 0.05)),     # acrylic head plate
    (0.177, (0.023, 0.015, 0.05)),      # head attachment block
    (0.2775, (0.0775, 0.01, 0.0525)),   # aluminium body block
]
# head masses: (mass kg, x centre, length, width) for the yaw inertia of boxes
HEAD_MASSES = [
    (0.0909, 0.077, 0.154, 0.005),    # head plate
    (0.0227, 0.087, 0.16, 0.04),      # top plate
    (0.53, 0.082, 0.12, 0.08),        # electronics box
    (0.08, 0.177, 0.046, 0.03),       # attachment
    (0.60, 0.2775, 0.155, 0.02),      # body block
    (0.065, 0.2425, 0.015, 0.12),     # motor, shaft and crank
    (0.01, 0.337, 0.04, 0.002),       # top fin
]
JOINT0_X = 0.362            # first tail hinge
TAIL_BASE_X = 0.357         # tail-base marker (rigid with the head)
TAIL_TIP_X = 0.551          # caudal-fin tip marker
# links: (length to the next joint, part centre along the link, semi-axes, mass, yaw inertia)
LINKS = [
    (0.0295, 0.0145, (0.0075, 0.0015, 0.05), 0.018, 1e-5),
    (0.031, 0.015, (0.0075, 0.0015, 0.0475), 0.018, 1e-5),
    (0.0305, 0.016, (0.0075, 0.0015, 0.045), 0.018, 1e-5),
    (0.025, 0.0145, (0.0075, 0.0015, 0.0425), 0.018, 1e-5),
    (0.028, 0.0105, (0.0075, 0.0015, 0.04), 0.018, 1e-5),
    (0.045, 0.022, (0.02, 0.001, 0.08), 0.011, 3.3e-6),   # caudal fin, hinge to tip marker
]
HEAD_MARKER_X1 = 0.142      # second head marker
HEAD_REF_X = 0.071          # midpoint of the two head markers: the point whose speed is measured
HARMONICS = 3
WAVE_DEGREE = 3


def head_inertia() -> tuple[float, float, float]:
    """Head mass, centre x, yaw inertia about that centre."""
    m = np.array([h[0] for h in HEAD_MASSES])
    x = np.array([h[1] for h in HEAD_MASSES])
    lx = np.array([h[2] for h in HEAD_MASSES])
    ly = np.array([h[3] for h in HEAD_MASSES])
    mass = m.sum()
    xc = (m * x).sum() / mass
    j = (m * (lx ** 2 + ly ** 2) / 12.0).sum() + (m * (x - xc) ** 2).sum()
    return float(mass), float(xc), float(j)


def merge_runs(bodies: int) -> list:
    """Indices of LINKS in each of `bodies` tail bodies (see merge_links)."""
    if not 2 <= bodies <= len(LINKS):
        raise ValueError(f"tail bodies must be within [2, {len(LINKS)}], got {bodies}")
    return [r.tolist() for r in np.array_split(np.arange(len(LINKS) - 1), bodies - 1)] + [[len(LINKS) - 1]]


def merge_links(bodies: int = len(LINKS)) -> list:
    """The tail as `bodies` rigid links: the fin stays one body (its shape is not a plate's) and
    the plates are split into bodies - 1 runs of consecutive plates, front runs one longer when
    they do not divide evenly. A merged body keeps the run's length (joint to joint) and mass;
    its part sits at the run's mass centre with the yaw inertia of the straight run about it
    (parallel axes); its ellipsoid keeps the run's lateral projected area (sum r0 r2, with
    r0 = sum r0) and volume (sum r0 r1 r2). Why area and volume, not an ellipsoid spanning the
    whole run: the plates are 15 mm wide with gaps between them, and the fluid model's drag
    and lift scale with these, so the merged fish meets the same water.
    All bodies returns the links unchanged, so that fish is the default one bit for bit."""
    links = list(LINKS)
    runs = merge_runs(bodies)
    if bodies == len(links):
        return links
    out = []
    for run in runs:
        if len(run) == 1:
            out.append(links[run[0]])
            continue
        lengths = np.array([links[i][0] for i in run])
        start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        x = start + np.array([links[i][1] for i in run])             # part centres along the run
        r = np.array([links[i][2] for i in run])
        m = np.array([links[i][3] for i in run])
        j = np.array([links[i][4] for i in run])
        xc = float((m * x).sum() / m.sum())
        r0 = float(r[:, 0].sum())
        r2 = float((r[:, 0] * r[:, 2]).sum() / r0)
        r1 = float((r[:, 0] * r[:, 1] * r[:, 2]).sum() / (r0 * r2))
        out.append((float(lengths.sum()), xc, (r0, r1, r2), float(m.sum()),
                    float((j + m * (x - xc) ** 2).sum())))
    return out


def ellipsoid_kappa(semi) -> np.ndarray:
    """kappa_i = int_0^inf r_x r_y r_z / sqrt((r_i^2+l)^3 (r_j^2+l)(r_k^2+l)) dl (Tuckerman)."""
    from scipy.integrate import quad

    r = np.asarray(semi, dtype=np.float64)
    out = np.zeros(3)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3

        # substitute l = s^2 r_max^2 / (1 - s)^2 ... keep it simple: integrate in log space
        def f(t, i=i, j=j, k=k):
            lam = math.exp(t)
            return lam * r.prod() / math.sqrt((r[i] ** 2 + lam) ** 3 * (r[j] ** 2 + lam) * (r[k] ** 2 + lam))

        lo, hi = math.log(r.min() ** 2) - 40.0, math.log(r.max() ** 2) + 40.0
        val, _ = quad(f, lo, hi, limit=400, epsabs=1e-13, epsrel=1e-11)
        out[i] = val
    return out


def virtual_mass_inertia(semi) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's virtual masses and moments of inertia of an ellipsoid, per unit fluid density."""
    r = np.asarray(semi, dtype=np.float64)
    kap = ellipsoid_kappa(r)
    vol = 4.0 / 3.0 * math.pi * r.prod()
    mass = vol * kap / (2.0 - kap)
    inertia = np.zeros(3)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        dj, dk = r[j] ** 2, r[k] ** 2
        num = (dj - dk) ** 2 * (kap[k] - kap[j])
        den = 2.0 * (dj - dk) + (dj + dk) * (kap[j] - kap[k])
        inertia[i] = vol / 5.0 * num / den if abs(den) > 1e-300 else 0.0
    return mass, inertia




def parts(links=LINKS) -> dict:
    """Per-part constants in kernel order: head fluid parts, head mass lump, then one per link."""
    semi, amass, inert, link, offset = [], [], [], [], []

    def add(r, m, j, lk, d):
        semi.append(r)
        if r[0] > 0:
            vm, vi = virtual_mass_inertia(r)
            amass.append((vm[0], vm[1], vi[2]))
        else:
            amass.append((0.0, 0.0, 0.0))
        inert.append((m, j))
        link.append(lk)
        offset.append(d)

    for x, r in HEAD_FLUID:
        add(r, 0.0, 0.0, -1, x)
    mass, xc, j = head_inertia()
    add((0.0, 0.0, 0.0), mass, j, -1, xc)
    for i, (_, d, r, m, jj) in enumerate(links):
        add(r, m, jj, i, d)
    return {"semi": np.array(semi), "amass": np.array(amass), "inert": np.array(inert),
            "link": np.array(link), "offset": np.array(offset)}


# --- gait from markers -----------------------------------------------------------------------

def _temporal(t, f, k_max):
    cols = [np.ones_like(t)]
    for k in range(1, k_max + 1):
        cols += [np.cos(2 * np.pi * k * f * t), np.sin(2 * np.pi * k * f * t)]
    return np.stack(cols, axis=-1)


def fit_wave(local: np.ndarray, keep: list[int], freq: float, fps: float):
    """Least-squares travelling wave through the tail markers. Returns y(X_robot, t) callable."""
    frames = len(local)
    t = np.arange(frames) / fps
    x = local[:, keep, 0]
    y = local[:, keep, 1]
    x0, x1 = x[:, 0].mean(), x[:, -1].mean()
    xi = (x - x0) / (x1 - x0)
    tb = _temporal(t, freq, HARMONICS)                          # (F, T)
    sb = np.stack([xi ** n for n in range(1, WAVE_DEGREE + 1)], axis=-1)  # (F, M, S)
    design = (sb[..., :, None] * tb[:, None, None, :]).reshape(frames * len(keep), -1)
    coef, *_ = np.linalg.lstsq(design, y.reshape(-1), rcond=None)
    coef = coef.reshape(WAVE_DEGREE, -1)
    rms = float(np.sqrt(np.mean((design @ coef.reshape(-1) - y.reshape(-1)) ** 2)))

    def curve(xr, tt):
        xir = (np.asarray(xr) - TAIL_BASE_X) / (TAIL_TIP_X - TAIL_BASE_X)
        s = np.stack([xir ** n for n in range(1, WAVE_DEGREE + 1)], axis=-1)
        tcoef = _temporal(np.asarray(tt, float), freq, HARMONICS) @ coef.T   # (..., S)
        return (s * tcoef).sum(-1)

    curve.coef = coef
    return curve, rms


def chain_angles(curve, freq: float, samples: int = 128) -> np.ndarray:
    """Lay the links along the wave joint by joint; angles (samples, links) over one beat."""
    t = np.arange(samples) / (samples * freq)
    px = np.full(samples, JOINT0_X)
    py = np.zeros(samples)
    out = []
    for length, *_ in LINKS:
        xa = px + length
        psi = np.arctan2(curve(xa, t) - py, length)
        for _ in range(30):  # fixed point on the circle of radius `length` around the joint
            qx = px + length * np.cos(psi)
            psi_new = np.arctan2(curve(qx, t) - py, qx - px)
            if np.max(np.abs(psi_new - psi)) < 1e-12:
                break
            psi = psi_new
        out.append(psi)
        px = px + length * np.cos(psi)
        py = py + length * np.sin(psi)
    return np.stack(out, axis=1)


def gait(rate, mode: str = "chain", bodies: int = len(LINKS)) -> dict:
    """Prescribed tail motion of one rate, mean (constant bend) removed.

    mode "wave": every tail part sits at its nominal x with the wave's lateral position and
    slope (lateral motion exactly as measured; links stretch slightly, no foreshortening).
    mode "chain": rigid links laid joint by joint along the wave (inextensible; the video's tail
    is longer than the robot's, so the fin tip then swings about 20 % less than the markers).
    Both carry the chain's Fourier link angles psi_j = sum_k a_jk cos + b_jk sin (2 pi k f t).
    `bodies` < 6 merges tail links (merge_links); the gait carries its tail as "links".
    """
    local, keep = rate.meta["local"], rate.meta["tail_markers"]
    curve, rms = fit_wave(local, keep, rate.tail_freq, rate.fps)
    samples = 128
    ang = chain_angles(curve, rate.tail_freq, samples)
    spec = np.fft.rfft(ang, axis=0) / samples
    a = 2 * spec[1:HARMONICS + 1].real.T      # (links, K)
    b = -2 * spec[1:HARMONICS + 1].imag.T
    links = merge_links(bodies)
    if bodies < len(LINKS):
        a, b = _merged_angles(a, b, rate.tail_freq, merge_runs(bodies), samples)
    wave = curve.coef.copy()
    wave[:, 0] = 0.0
    return {"freq": rate.tail_freq, "a": a, "b": b, "wave": wave, "wave_rms": rms, "mode": mode, "links": links}


def _merged_angles(a, b, freq, runs, samples):
    """Fourier angles of merged links: each points along the chord between the full gait's joints
    at the ends of its run, so the merged joints move with the robot's (to the foreshortening of
    a rigid link of the run's straight length)."""
    t = np.arange(samples) / (samples * freq)
    psi, _, _ = link_motion({"freq": freq, "a": a, "b": b}, t)
    lengths = np.array([lk[0] for lk in LINKS])
    jx = np.concatenate([np.zeros((samples, 1)), np.cumsum(lengths * np.cos(psi), 1)], 1)
    jy = np.concatenate([np.zeros((samples, 1)), np.cumsum(lengths * np.sin(psi), 1)], 1)
    chord = np.stack([np.arctan2(jy[:, r[-1] + 1] - jy[:, r[0]], jx[:, r[-1] + 1] - jx[:, r[0]]) for r in runs], 1)
    spec = np.fft.rfft(chord, axis=0) / samples
    return 2 * spec[1:HARMONICS + 1].real.T, -2 * spec[1:HARMONICS + 1].imag.T


def wave_eval(g: dict, x: np.ndarray, t: np.ndarray):
    """y, y_t, y_tt, y_x, y_xt, y_xtt of the gait's wave at head-frame x (P,), times t (T,) -> (T, P)."""
    span = TAIL_TIP_X - TAIL_BASE_X
    xi = (np.asarray(x, float) - TAIL_BASE_X) / span
    n = np.arange(1, WAVE_DEGREE + 1)
    s = xi[:, None] ** n[None, :]                         # (P, S)
    sx = n[None, :] * xi[:, None] ** (n[None, :] - 1) / span
    om = 2 * np.pi * g["freq"] * np.arange(1, HARMONICS + 1)
    ph = np.asarray(t, float)[:, None] * om[None, :]
    c, si = np.cos(ph), np.sin(ph)
    A = g["wave"][:, 1::2]                                # (S, K) cos
    B = g["wave"][:, 2::2]                                # (S, K) sin
    T0 = c @ A.T + si @ B.T                               # (T, S)
    T1 = (-si * om) @ A.T + (c * om) @ B.T
    T2 = (-c * om ** 2) @ A.T + (-si * om ** 2) @ B.T
    return T0 @ s.T, T1 @ s.T, T2 @ s.T, T0 @ sx.T, T1 @ sx.T, T2 @ sx.T


def nominal_x(links=LINKS) -> tuple[np.ndarray, np.ndarray]:
    """x of the joints (links+1, tip last) and of the link parts' centres, tail straight."""
    joints = JOINT0_X + np.concatenate([[0.0], np.cumsum([lk[0] for lk in links])])
    centres = joints[:-1] + np.array([lk[1] for lk in links])
    return joints, centres


def tip_motion(g: dict, t: np.ndarray):
    """Fin-tip lateral position, its rate and the body slope there (head frame) over times t."""
    if g.get("mode") == "wave":
        y, yt, _, yx, _, _ = wave_eval(g, np.array([TAIL_TIP_X]), t)
        return y[:, 0], yt[:, 0], yx[:, 0]
    pts = tail_points(g, t)
    psi, psid, _ = link_motion(g, t)
    lengths = np.array([lk[0] for lk in g.get("links", LINKS)])
    yt = (lengths[None, :] * np.cos(psi) * psid).sum(axis=1)
    return pts[:, -1, 1], yt, np.tan(psi[:, -1])


def link_motion(g: dict, t: np.ndarray):
    """psi, psid, psidd (T, links) from the Fourier gait."""
    k = np.arange(1, HARMONICS + 1)
    om = 2 * np.pi * g["freq"] * k                      # (K,)
    ph = np.asarray(t)[:, None] * om[None, :]           # (T, K)
    c, s = np.cos(ph), np.sin(ph)
    a, b = g["a"], g["b"]
    psi = c @ a.T + s @ b.T
    psid = (-s * om) @ a.T + (c * om) @ b.T
    psidd = (-c * om ** 2) @ a.T + (-s * om ** 2) @ b.T
    return psi, psid, psidd


def part_table(g: dict, t: np.ndarray, prt: dict | None = None) -> np.ndarray:
    """(T, parts, ROW) head-frame kinematics of every part at times t."""
    links = g.get("links", LINKS)
    prt = prt or parts(links)
    if g.get("mode") == "wave":
        return _wave_table(g, t, prt)
    psi, psid, psidd = link_motion(g, t)
    n = len(t)
    jx, jy = np.full(n, JOINT0_X), np.zeros(n)
    jdx, jdy, jddx, jddy = (np.zeros(n) for _ in range(4))
    frames = []
    for i, (length, *_rest) in enumerate(links):
        c, s = np.cos(psi[:, i]), np.sin(psi[:, i])
        frames.append((jx, jy, jdx, jdy, jddx, jddy, c, s, psid[:, i], psidd[:, i]))
        w, al = psid[:, i], psidd[:, i]
        jx, jy = jx + length * c, jy + length * s
        jdx, jdy = jdx - length * w * s, jdy + length * w * c
        jddx = jddx + length * (-al * s - w * w * c)
        jddy = jddy + length * (al * c - w * w * s)
    table = np.zeros((n, len(prt["link"]), kern.ROW))
    for e, (lk, d) in enumerate(zip(prt["link"], prt["offset"])):
        if lk < 0:
            table[:, e, 0] = d
            table[:, e, 2] = 1.0
            continue
        px, py, pdx, pdy, pddx, pddy, c, s, w, al = frames[lk]
        table[:, e] = np.stack([
            px + d * c, py + d * s, c, s,
            pdx - d * w * s, pdy + d * w * c, w,
            pddx + d * (-al * s - w * w * c), pddy + d * (al * c - w * w * s), al], axis=1)
    return table


def _wave_table(g: dict, t: np.ndarray, prt: dict) -> np.ndarray:
    _, centres = nominal_x(g.get("links", LINKS))
    table = np.zeros((len(t), len(prt["link"]), kern.ROW))
    for e, (lk, d) in enumerate(zip(prt["link"], prt["offset"])):
        if lk < 0:
            table[:, e, 0] = d
            table[:, e, 2] = 1.0
            continue
        x = centres[lk]
        y, yt, ytt, yx, yxt, yxtt = (q[:, 0] for q in wave_eval(g, np.array([x]), t))
        q = 1.0 + yx * yx
        psi = np.arctan(yx)
        psid = yxt / q
        psidd = yxtt / q - 2.0 * yx * yxt * yxt / (q * q)
        table[:, e] = np.stack([np.full_like(y, x), y, np.cos(psi), np.sin(psi), np.zeros_like(y), yt, psid,
                                np.zeros_like(y), ytt, psidd], axis=1)
    return table


def tail_points(g: dict, t: np.ndarray) -> np.ndarray:
    """(T, links+1, 2) head-frame joint positions (for drawing the simulated fish)."""
    links = g.get("links", LINKS)
    if g.get("mode") == "wave":
        joints, _ = nominal_x(links)
        y = wave_eval(g, joints, t)[0]
        return np.stack([np.broadcast_to(joints, y.shape), y], axis=-1)
    psi, _, _ = link_motion(g, t)
    pts = [np.stack([np.full(len(t), JOINT0_X), np.zeros(len(t))], axis=1)]
    for i, (length, *_r) in enumerate(links):
        pts.append(pts[-1] + length * np.stack([np.cos(psi[:, i]), np.sin(psi[:, i])], axis=1))
    return np.stack(pts, axis=1)




def build_batch(rates, device: str = "cpu", dt: float = DEFAULT_DT, warm_seconds: float = 2.0,
                meas_seconds: float = 3.0, virtual_mass: bool = False, gaits=None,
                rho: float = 1000.0, mu: float = 0.0013, max_warm_seconds: float | None = 40.0,
                settle: float = 2e-4, scheme: int = 2, bodies: int | None = None):
    """SwimBatch for these rates: dt fitted to the tail beat; warm-up of whole beats, at least
    warm_seconds and until the beat-averaged surge changes by less than `settle` m/s (+0.2 %)
    between beats (at most max_warm_seconds; None: exactly warm_seconds); then whole beats
    covering meas_seconds for the speed. `bodies`: tail bodies (merge_links); default: the
    given gaits' tail, else the full one."""
    if bodies is None:
        bodies = len(gaits[0].get("links", LINKS)) if gaits is not None else len(LINKS)
    links = merge_links(bodies)
    prt = parts(links)
    tables, offs, n_per, dts, n_warm, n_meas, max_warm = [], [], [], [], [], [], []
    off = 0
    for i, r in enumerate(rates):
        g = gaits[i] if gaits is not None else gait(r, bodies=bodies)
        if len(g["a"]) != len(links):
            raise ValueError(f"gait has {len(g['a'])} link angles, the tail {len(links)} links")
        period = 1.0 / g["freq"]
        n = int(np.ceil(period / dt))
        step = period / n
        tables.append(part_table(g, np.arange(n) * step, prt))
        offs.append(off)
        off += n
        n_per.append(n)
        dts.append(step)
        n_warm.append(n * int(np.ceil(warm_seconds / period - 1e-9)))
        n_meas.append(n * max(1, int(np.ceil(meas_seconds / period - 1e-9))))
        cap = warm_seconds if max_warm_seconds is None else max(warm_seconds, max_warm_seconds)
        max_warm.append(n * int(np.ceil(cap / period - 1e-9)))
    return kern.SwimBatch(np.concatenate(tables), offs, n_per, dts, n_warm, n_meas, prt,
                          ref_x=HEAD_REF_X, rho=rho, mu=mu, virtual_mass=virtual_mass,
                          max_warm=max_warm, settle_abs=settle, device=device, scheme=scheme)
