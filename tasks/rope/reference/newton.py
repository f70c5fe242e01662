"""Fine reference rope simulated with newton 1.8: a rod of capsules (``ModelBuilder.add_rod``) with
bending, twist and capsule self-contact, solved by ``SolverVBD``.

The held end is a ball joint from the world to the first capsule whose world anchor
(``model.joint_X_p``) is moved along the hand path every substep: the fingertip drags the rope's
first node but does not clamp its direction, like the point-mass-on-the-fingertip coarse model.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass

import numpy as np
import warp as wp

from wrenorm.errors import InputError
from wrenorm.tasks.rope.reference.materials import RopeMaterial

TIMESTEP = 5e-4  # s: the built-in references' step (250 frames a second, 8 steps a frame)


@dataclass
class RopeRun:
    time: np.ndarray  # (T,) s
    nodes: np.ndarray  # (T, N+1, 3) m, held end first
    hand: np.ndarray  # (T, 3) m, the anchor commanded at each frame
    wall_s: float
    substeps: int


@wp.kernel
def _set_anchor(src: wp.array(dtype=wp.transform), k: int, joint: int, joint_X_p: wp.array(dtype=wp.transform)):
    joint_X_p[joint] = src[k]


def _quat_axis_z(q: np.ndarray) -> np.ndarray:
    """World direction of each body's local +Z (the capsule axis); q is (..., 4) xyzw."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def nodes_from_body_q(body_q: np.ndarray, half_lengths: np.ndarray) -> np.ndarray:
    """Centreline nodes (N+1, 3) from capsule poses (N, 7): each body origin is its midpoint."""
    p = body_q[:, :3].astype(np.float64)
    ax = _quat_axis_z(body_q[:, 3:7].astype(np.float64)) * half_lengths[:, None]
    starts = p - ax
    return np.concatenate([starts, (p[-1] + ax[-1])[None]], axis=0)


def simulate(hand_path, material: RopeMaterial = RopeMaterial(), segments: int = 64, duration: float = 2.0,
             frame_rate: float = 250.0, timestep: float = TIMESTEP, iterations: int = 10,
             device: str = "cpu", capture: bool = True, progress=None) -> RopeRun:
    """Swing a rope hanging straight down from the hand's start point; record nodes at frame_rate.

    The solver's step is the largest that splits the frame interval into an even number of steps and is at most
    `timestep`, so the frame rate only samples the motion (as MuJoCo's rod does); above 1 / (2 timestep) frames
    per second the step is half the frame interval."""

    import newton

    if segments < 4:
        raise InputError("simulate", "segments", f"need >= 4 segments, got {segments}")
    if not (np.isfinite(timestep) and timestep > 0):
        raise InputError("simulate", "timestep", f"need a positive time step, got {timestep!r}")
    substeps_per_frame = max(1, int(np.ceil(1.0 / (frame_rate * timestep) - 1e-9)))
    # An even count returns the ping-ponged states to their roles, as a captured graph needs.
    substeps_per_frame += substeps_per_frame % 2
    m = material
    ds = m.length / segments
    start = np.asarray(hand_path.positions([0.0])[0], dtype=np.float64)
    pts = np.zeros((segments + 1, 3))
    pts[:, 2] = start[2] - np.linspace(0.0, m.length, segments + 1)
    pts[:, 0], pts[:, 1] = start[0], start[1]
    # A hair of deterministic out-of-line noise so perfectly symmetric states cannot stall in a saddle.
    pts[1:, 1] += 1e-5 * np.sin(np.arange(1, segments + 1) * 1.7)

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    cfg = newton.ModelBuilder.ShapeConfig(ke=m.contact_stiffness, kd=m.contact_damping, mu=m.friction,
                                          gap=m.radius)
    rod = newton.Rod([wp.vec3(*p) for p in pts], radius=m.radius)
    k_bend = m.bend_stiffness / ds
    k_twist = m.twist_stiffness / ds
    bodies, joints = builder.add_rod(
        rod=rod, cfg=cfg, stretch_stiffness=m.stretch_stiffness, stretch_damping=0.0,
        bend_stiffness=k_bend, bend_damping=k_bend * m.bend_damping_time,
        twist_stiffness=k_twist, twist_damping=k_twist * m.bend_damping_time,
        wrap_in_articulation=False, label="rope")
    # Capsule volume counts the end caps; rescale so the rope weighs exactly m.mass.
    scale = m.mass / sum(builder.body_mass[b] for b in bodies)
    for b in bodies:
        builder.body_mass[b] *= scale
        builder.body_inv_mass[b] /= scale
        builder.body_inertia[b] = builder.body_inertia[b] * scale
        builder.body_inv_inertia[b] = builder.body_inv_inertia[b] * (1.0 / scale)
    if m.tip_mass > 0:
        # a point mass at the free end rides on the last capsule: its mass grows, and its inertia about its
        # centre by the point's parallel-axis term (half a segment off the centre, across the axis)
        last = bodies[-1]
        mass = builder.body_mass[last] + m.tip_mass
        extra = m.tip_mass * (0.5 * ds) ** 2
        inertia = builder.body_inertia[last] + wp.mat33(extra, 0.0, 0.0, 0.0, extra, 0.0, 0.0, 0.0, 0.0)
        builder.body_mass[last], builder.body_inv_mass[last] = mass, 1.0 / mass
        builder.body_inertia[last], builder.body_inv_inertia[last] = inertia, wp.inverse(inertia)
    # Capsules two apart overlap once the rope bends sharply; that is bending, not contact.
    for a in range(len(bodies) - 2):
        for sa in builder.body_shapes.get(bodies[a], []):
            for sb in builder.body_shapes.get(bodies[a + 2], []):
                builder.add_shape_collision_filter_pair(int(sa), int(sb))
    anchor = builder.add_joint_ball(
        -1, bodies[0], parent_xform=wp.transform(wp.vec3(*pts[0]), wp.quat_identity()),
        child_xform=wp.transform(wp.vec3(0.0, 0.0, -0.5 * ds), wp.quat_identity()), label="hand")
    # The hand joint stays outside the articulation: its parent is the moving world anchor.
    builder.add_articulation(list(joints), label="rope")
    builder.color()
    model = builder.finalize(device=device)

    pipeline = newton.CollisionPipeline(model, contact_matching="latest")
    contacts = pipeline.contacts()
    solver = newton.solvers.SolverVBD(model, iterations=iterations, rigid_contact_history=True,
                                      rigid_body_contact_buffer_size=256, rigid_joint_linear_ke=1e7)
    state_0, state_1 = model.state(), model.state()
    control = model.control()

    dt_frame = 1.0 / frame_rate
    dt = dt_frame / substeps_per_frame
    n_frames = int(round(duration * frame_rate))
    anchors = wp.zeros(substeps_per_frame, dtype=wp.transform, device=device)

    half = np.full(segments, 0.5 * ds)
    states = [state_0, state_1]

    def substeps():
        for k in range(substeps_per_frame):
            s_in, s_out = states[k % 2], states[(k + 1) % 2]
            wp.launch(_set_anchor, dim=1, inputs=[anchors, k, anchor], outputs=[model.joint_X_p], device=device)
            pipeline.collide(s_in, contacts)
            solver.set_rigid_history_update(True)
            solver.step(s_in, s_out, control, contacts, dt)

    times = np.arange(n_frames + 1) * dt_frame
    nodes = np.empty((n_frames + 1, segments + 1, 3))
    nodes[0] = nodes_from_body_q(state_0.body_q.numpy(), half)
    graph = None
    t0 = _time.perf_counter()
    for f in range(n_frames):
        ts = times[f] + dt * np.arange(1, substeps_per_frame + 1)
        xf = np.zeros((substeps_per_frame, 7), dtype=np.float32)
        xf[:, :3] = hand_path.positions(ts)
        xf[:, 6] = 1.0
        anchors.assign(xf)
        # Capture after one plain frame so contact history buffers exist (newton's advice).
        if capture and graph is None and f >= 1:
            # Capturing records the launches without running them.
            with wp.ScopedCapture(device=device) as cap:
                substeps()
            graph = cap.graph
        if graph is not None:
            wp.capture_launch(graph)
        else:
            substeps()
        nodes[f + 1] = nodes_from_body_q(state_0.body_q.numpy(), half)
        if progress is not None and (f + 1) % max(1, n_frames // 10) == 0:
            progress(f + 1, n_frames, _time.perf_counter() - t0)
    wall = _time.perf_counter() - t0
    if not np.all(np.isfinite(nodes)):
        raise RuntimeError("newton rope simulation produced NaN/Inf")
    return RopeRun(times, nodes, hand_path.positions(times), wall, n_frames * substeps_per_frame)
