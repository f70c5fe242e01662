"""A second fine reference rope, independent of newton: MuJoCo's elastic rod (mujoco >= 4.0).

MuJoCo 4.0 removed the ``composite type="cable"`` element and the ``mujoco.elasticity.cable`` plugin; their
documented successor is a 1D ``flexcomp`` with ``<elasticity>``: a discrete elastic rod (Bergou et al. 2008)
with per-vertex point masses, per-edge twist, bending ``EI/(l0+l1) |kappa b|^2`` per interior vertex, torsion,
Rayleigh damping (``damping`` in seconds: that time times the stiffness matrix), inextensible edges through an
edge-equality constraint, and capsule self-contact between flex elements. This module builds that rod from the
shared rope materials (materials.py); nothing here is tuned to newton.

Model
  * ``segments`` capsules of radius ``radius`` between ``segments + 1`` vertices, hanging straight down from
    the hand's start at rest at t = 0. Each vertex carries its share of the mass (rho ds inside, rho ds / 2 at
    the ends, ``tip_mass`` on the free end); the held vertex's half share rides on the hand.
  * Held end: vertex 0 is a heavy (1e3 kg, gravity-compensated) point on three world-axis slide joints whose
    position and velocity are set from the hand path before every physics step (velocity = the secant to the
    next step, so the implicit step lands on the path). It is a point: the rope's direction at the hand and the
    first edge's twist are free, like newton's ball joint. (MuJoCo 4.0 does not allow a mocap pin on a damped
    elastic flex; an equality ``connect`` to a mocap body would lag the hand by ~2 timeconst x speed.)
  * Self-contact: MuJoCo's flex self-collision (condim 3, friction, soft constraint ``solref = (contact_
    timeconst, contact_dampratio)``). MuJoCo skips only element pairs that share a vertex; there is no per-pair
    exclusion for flexes, so elements two apart could touch once ds <= 2r: `check_resolution` refuses
    ds <= 1.1 x 2r (default rope: at most 99 segments), and ``near_contacts`` counts steps with a contact
    between points closer than pi * diameter along the rope (0 in every measured run).
  * Integrator ``discrete`` (the one MuJoCo 4.0 supports for rod elasticity), Newton solver, edges as equality
    constraints with solref (2 timestep, 1). Default 64 segments at 0.25 ms: first-contact times move < 3 ms
    against 96 segments at 0.125 ms.

The simulator's own first self-contact
  After each ``mj_step`` the contact list describes the state at the START of that step (t_k). The event is the
  first step with a rope-rope contact whose ``dist <= 0`` and whose two contact points (projected on each
  capsule's axis) are more than pi * diameter apart along the rope (MuJoCo 4.0 creates flex self-contacts only
  on penetration). Reported: the step time t_k, and the time interpolated linearly in the signed gap between
  step k-1 (the capsule surface gap of the rope's vertices, `events.polyline_gap`) and step k (MuJoCo's dist),
  and the arc-length fractions s_a < s_b of the deepest such contact. Its first impacts last only 1.5-3 ms,
  after which the pieces rest with gaps within +-0.2 mm: a 200 Hz frame grid often misses them.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np

from wrenorm.errors import InputError
from wrenorm.tasks.rope.reference.events import polyline_gap
from wrenorm.tasks.rope.reference.materials import RopeMaterial

HAND_MASS = 1e3  # kg: the held vertex; it is reset to the hand path every step
MIN_SPACING = 1.1  # ds / diameter below which elements two apart overlap (nearly) at rest
INSTALL_HINT = "the MuJoCo reference rope needs the mujoco package: pip install 'mujoco>=4.0'"


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise InputError("--engine", "mujoco", f"not installed: {INSTALL_HINT}") from None
    if int(str(mujoco.__version__).split(".")[0]) < 4:
        raise InputError("--engine", "mujoco", f"version {mujoco.__version__} has no 1D flexcomp elastic rod; "
                                               f"{INSTALL_HINT}")
    return mujoco


TIMESTEP = 2.5e-4  # s: contact times move < 3 ms against 0.125 ms (module docstring)


@dataclass(frozen=True)
class ContactEvent:
    step: int  # physics step k (state at t_k = k * timestep)
    step_time: float  # s, t_k
    time: float  # s, interpolated inside (t_{k-1}, t_k]
    s_a: float  # arc-length fraction, held-end side
    s_b: float  # arc-length fraction, free-end side
    dist: float  # m, MuJoCo's contact dist at step k (<= 0)
    gap_before: float  # m, capsule surface gap at step k-1


@dataclass
class MujocoRun:
    time: np.ndarray  # (T,) s, frames
    nodes: np.ndarray  # (T, segments + 1, 3) m, held end first
    hand: np.ndarray  # (T, 3) m
    contact: ContactEvent | None  # MuJoCo's own first self-contact
    wall_s: float
    segments: int
    timestep: float
    near_contacts: int  # steps with a contact between points closer than pi * diameter along the rope
    max_stretch: float  # largest relative stretch of the whole centre line
    warnings: dict = field(default_factory=dict)
    name: str = ""


def check_resolution(material: RopeMaterial, segments: int) -> None:
    """Elements two apart are ds apart at their nearest ends; with ds <= 2r they would touch at rest (MuJoCo has
    no per-pair exclusion for flex self-collision; a 128-segment default rope explodes at once)."""
    ds = material.length / segments
    if segments < 4 or ds <= MIN_SPACING * 2.0 * material.radius:
        most = int(np.ceil(material.length / (MIN_SPACING * 2 * material.radius))) - 1
        raise InputError("--segments", "segments", f"{segments}: MuJoCo's rope needs 4 to {most} segments for this "
                                                   f"rope (element length above {MIN_SPACING:g} x the diameter "
                                                   f"{2e3 * material.radius:.1f} mm)")


def _fmt(a) -> str:
    return " ".join(f"{float(x):.10g}" for x in np.ravel(a))


def build_model(material: RopeMaterial, start, segments: int = 64, timestep: float = TIMESTEP):
    """Compile the MuJoCo rope: returns (model, info)."""
    mujoco = _mujoco()
    mt, n = material, int(segments)
    check_resolution(mt, n)
    r = mt.radius
    start = np.asarray(start, dtype=np.float64).reshape(3)
    pts = np.repeat(start[None], n + 1, axis=0)
    pts[:, 2] -= np.linspace(0.0, mt.length, n + 1)
    young = mt.bend_stiffness / (np.pi * r**4 / 4.0)  # MuJoCo uses I, J of the flex radius's circle
    shear = mt.twist_stiffness / (np.pi * r**4 / 2.0)
    rho_ds = mt.mass / n
    elements = np.stack([np.arange(n), np.arange(1, n + 1)], 1)
    xml = f"""<mujoco model="rope">
  <option timestep="{timestep:.10g}" integrator="discrete" solver="Newton" gravity="0 0 -9.81"/>
  <worldbody>
    <flexcomp name="rope" type="direct" dim="1" radius="{r:.10g}" mass="{rho_ds * (n + 1):.10g}"
              point="{_fmt(pts)}" element="{' '.join(str(int(v)) for v in elements.ravel())}">
      <contact selfcollide="auto" condim="3" friction="{mt.friction:.6g} 0.005 0.0001"
               solref="{mt.contact_timeconst:.6g} {mt.contact_dampratio:.6g}" solimp="0.95 0.99 0.001"/>
      <edge equality="true" solref="{2.0 * timestep:.6g} 1" solimp="0.99 0.999 0.001"/>
      <elasticity young="{young:.10g}" shear="{shear:.10g}" damping="{mt.bend_damping_time:.6g}"/>
    </flexcomp>
  </worldbody>
</mujoco>"""
    spec = mujoco.MjSpec.from_string(xml)
    # Masses are edited in the spec, before compiling, so every derived constant uses them (setting them on the
    # compiled model without recomputing the constants made the rope explode).
    hand = spec.body("rope_0")
    hand.mass = HAND_MASS
    hand.inertia = [1.0, 1.0, 1.0]
    hand.gravcomp = 1.0
    spec.body(f"rope_{n}").mass = 0.5 * rho_ds + mt.tip_mass
    model = spec.compile()
    b0 = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "rope_0")
    j0 = model.body_jntadr[b0]
    if model.body_jntnum[b0] != 3 or any(model.jnt_type[j0 + a] != mujoco.mjtJoint.mjJNT_SLIDE for a in range(3)):
        raise RuntimeError("unexpected flexcomp layout: rope_0 should carry three slide joints")
    axes = model.jnt_axis[j0:j0 + 3].copy()
    elem = model.flex_elem[model.flex_elemdataadr[0]:model.flex_elemdataadr[0] + 2 * n].reshape(n, 2)
    info = dict(qadr=int(model.jnt_qposadr[j0]), vadr=int(model.jnt_dofadr[j0]), axes=axes,
                elem=elem - model.flex_vertadr[0], xml=xml)
    return model, info


def _proj(x, va, vb, pos):
    """Vertex-index coordinate (va + u (vb - va)) of pos projected on the segment x[va]-x[vb]."""
    a, b = x[va], x[vb]
    d = b - a
    u = np.clip(np.einsum("ij,ij->i", pos - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-18), 0.0, 1.0)
    return va + u * (vb - va)


def simulate(hand_path, material: RopeMaterial = RopeMaterial(), segments: int = 64, duration: float = 1.5,
             frame_rate: float = 200.0, timestep: float = TIMESTEP, progress=None) -> MujocoRun:
    """Swing the rope along the hand path; record the vertices at frame_rate and MuJoCo's first self-contact.

    hand_path: a HandPath (or anything with `positions(times) -> (T, 3)`). The physics step is the largest
    that divides the frame interval and is at most `timestep`."""
    mujoco = _mujoco()
    pos_fn = hand_path.positions if hasattr(hand_path, "positions") else hand_path
    frame_dt = 1.0 / frame_rate
    sub = max(1, int(np.ceil(frame_dt / timestep - 1e-9)))
    dt = frame_dt / sub
    n_frames = int(round(duration * frame_rate))
    n_steps = n_frames * sub
    mt, n = material, int(segments)
    P = np.asarray(pos_fn(np.arange(n_steps + 1) * dt), dtype=np.float64)
    model, info = build_model(mt, P[0], n, dt)
    data = mujoco.MjData(model)
    qa, va, A = info["qadr"], info["vadr"], info["axes"]  # world displacement of the hand vertex = A^T qpos
    mujoco.mj_forward(model, data)
    base = data.flexvert_xpos[0].copy() - A.T @ data.qpos[qa:qa + 3]
    A_inv = np.linalg.inv(A.T)
    exclude = 2.0 * np.pi * mt.radius  # pi * diameter
    elem = info["elem"]
    arc_nodes = np.linspace(0.0, 1.0, n + 1)
    times = np.arange(n_frames + 1) * frame_dt
    nodes = np.empty((n_frames + 1, n + 1, 3))
    event, prev_x, near, stretch = None, None, 0, 0.0
    t0 = _time.perf_counter()
    for k in range(n_steps + 1):
        data.qpos[qa:qa + 3] = A_inv @ (P[k] - base)
        if k < n_steps:
            data.qvel[va:va + 3] = A_inv @ ((P[k + 1] - P[k]) / dt)
            mujoco.mj_step(model, data)  # forward at t_k (positions, contacts), then integrate to t_k+1
        else:
            data.qvel[va:va + 3] = 0.0
            mujoco.mj_forward(model, data)
        x = data.flexvert_xpos  # state at t_k
        if k % sub == 0:
            nodes[k // sub] = x
            stretch = max(stretch, float(np.linalg.norm(np.diff(x, axis=0), axis=1).sum()) / mt.length - 1.0)
        nc = data.ncon
        if nc:
            con = data.contact
            fl = con.flex[:nc]
            own = np.flatnonzero((fl[:, 0] == 0) & (fl[:, 1] == 0) & (con.geom[:nc, 0] < 0) & (con.geom[:nc, 1] < 0))
            if len(own):
                els, pos, dist = con.elem[:nc][own], con.pos[:nc][own], con.dist[:nc][own]
                s0 = _proj(x, elem[els[:, 0], 0], elem[els[:, 0], 1], pos) / n
                s1 = _proj(x, elem[els[:, 1], 0], elem[els[:, 1], 1], pos) / n
                sep = np.abs(s1 - s0) * mt.length
                near += int((sep <= exclude).any())
                ok = (sep > exclude) & (dist <= 0.0)
                if event is None and ok.any():
                    c = np.flatnonzero(ok)[np.argmin(dist[ok])]
                    g1 = float(dist[c])
                    sa, sb = sorted((float(s0[c]), float(s1[c])))
                    g0 = float(polyline_gap(prev_x, arc_nodes, mt.length, mt.radius)[0]) if prev_x is not None \
                        else float("nan")
                    tk = k * dt
                    t_int = tk - dt + dt * g0 / (g0 - g1) if np.isfinite(g0) and g0 > 0 and g0 > g1 else tk
                    event = ContactEvent(k, tk, t_int, sa, sb, g1, g0)
        prev_x = x.copy()
        if progress is not None and k % sub == 0 and k and (k // sub) % max(1, n_frames // 10) == 0:
            progress(k // sub, n_frames, _time.perf_counter() - t0)
    wall = _time.perf_counter() - t0
    if not np.all(np.isfinite(nodes)):
        raise RuntimeError("MuJoCo rope simulation produced NaN/Inf")
    warn = {mujoco.mjtWarning(i).name: int(data.warning[i].number) for i in range(len(data.warning))
            if data.warning[i].number}
    name = (f"mujoco {mujoco.__version__} elastic rod (1D flexcomp, edge equality, flex self-contact): "
            f"segments={n} timestep={dt:.3g}s integrator=discrete solver=Newton")
    return MujocoRun(times, nodes, np.asarray(pos_fn(times), dtype=np.float64), event, wall, n, dt, near, stretch,
                     warn, name)
