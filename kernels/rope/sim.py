"""Host side of the coarse rope chain: per-chain parameters, rollout results, and `RopeSim`, which picks
the fastest kernel variant for the device and chain size and launches it over slices of the batch."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from wrenorm.kernels.launch import launch_sliced
from wrenorm.kernels.rope.generic import rollout_kernel
from wrenorm.kernels.rope.model import GRAVITY, VMAX, ChainEvents, ChainParameters, ChainSettings, ChainState


@dataclass
class ChainParams:
    """Per-chain physical parameters, each (B,) float: masses in kg, k in N m/rad per joint,
    b in N m s/rad per joint, drag_lin in N s/m^2 and drag_quad in N s^2/m^3 (per unit length),
    radius in m (collision capsule)."""

    node_mass: np.ndarray
    lead_mass: np.ndarray
    bend_k: np.ndarray
    bend_b: np.ndarray
    drag_lin: np.ndarray
    drag_quad: np.ndarray
    radius: np.ndarray
    mass_slope: np.ndarray | float = 0.0  # interior mass profile, see node_w (0: uniform)
    stretch: np.ndarray | float = 0.0  # link compliance in m/N (XPBD; 0: inextensible)

    FIELDS = ("node_mass", "lead_mass", "bend_k", "bend_b", "drag_lin", "drag_quad", "radius", "mass_slope",
              "stretch")
    DEFAULTS = {"mass_slope": 0.0, "stretch": 0.0}

    def __post_init__(self):
        arrs = [np.atleast_1d(np.asarray(getattr(self, f), dtype=np.float32)) for f in self.FIELDS]
        size = max(a.shape[0] for a in arrs)
        for f, a in zip(self.FIELDS, arrs):
            setattr(self, f, np.array(np.broadcast_to(a, (size,))))

    @property
    def batch(self) -> int:
        return self.node_mass.shape[0]

    @classmethod
    def uniform(cls, batch: int, **values) -> ChainParams:
        return cls(**{f: np.full(batch, values.get(f, cls.DEFAULTS.get(f)), dtype=np.float32) for f in cls.FIELDS})

    def node_masses(self, n: int) -> np.ndarray:
        """(B, n) masses as the kernels use them (node 0, held by the hand, as inf)."""
        u = np.linspace(0.0, 1.0, n - 2) if n > 3 else np.array([0.5])
        interior = self.node_mass[:, None] * (1.0 + self.mass_slope[:, None] * (1.0 - 2.0 * u[None]))
        return np.concatenate([np.full((self.batch, 1), np.inf), interior, self.lead_mass[:, None]], 1)


@dataclass
class RolloutResult:
    status: np.ndarray      # (B,) 0 no hit, 1 hit, 2 blew up
    hit_frame: np.ndarray   # (B,) first frame with a gap <= 0 (-1 if none)
    hit_alpha: np.ndarray   # (B,) fraction of the step [hit_frame-1, hit_frame] at the crossing
    hit_time: np.ndarray    # (B,) s, nan if no hit
    s_a: np.ndarray         # (B,) arc-length fraction of the hit point on the segment nearer the hand
    s_b: np.ndarray         # (B,) ... on the segment nearer the free end
    crit_pos: np.ndarray    # (B, N, 3)
    crit_vel: np.ndarray    # (B, N, 3)
    clearance: np.ndarray   # (B,) min over frames and pairs of min(gap, margin)
    final_pos: np.ndarray   # (B, N, 3) state after the last simulated step
    final_vel: np.ndarray
    trajectory: np.ndarray | None = None        # (K, B, N, 3) positions every `trajectory_every` steps
    trajectory_times: np.ndarray | None = None  # (K,) s
    events: Any = None  # the ChainEvents on the rollout's device (what critical.chain_states reads)
    dt: float = 0.0
    t0: float = 0.0


class RopeSim:
    """Coarse chains of `n_nodes` masses (node 0 held) with links of `link_length` metres."""

    def __init__(self, n_nodes: int, link_length: float, dt: float = 0.005, device: str = "cpu",
                 iterations: int = 4, cull: bool = True, margin: float | None = None,
                 gravity=GRAVITY, workers: int | None = None, min_sep: int = 2, fixed: bool = True,
                 lanes: int | None = None, tiled: bool | None = None):
        if not (3 <= int(n_nodes) <= 256):
            raise ValueError(f"n_nodes must be in [3, 256], got {n_nodes}")
        wp.init()
        self.n = int(n_nodes)
        self.link = float(link_length)
        self.dt = float(dt)
        self.device = str(device)
        self.iterations = int(iterations)
        self.cull = bool(cull)
        self.margin = float(0.25 * self.link if margin is None else margin)
        self.gravity = tuple(float(g) for g in gravity)
        self.workers = workers
        self.min_sep = max(2, int(min_sep))
        # fixed: a per-size kernel (lanes.py on the CPU, tiled.py on a GPU, else fixed.py), same results as the
        # generic one, faster. Only the kernel that runs is built: building one costs a second or more per process.
        self.kernel = rollout_kernel
        self.lanes = 0  # chains per thread of the SIMD-lane kernel; 0: one
        self.block = 0  # threads per block of the tiled kernel; 0: Warp's default launch
        if fixed:
            from wrenorm.kernels.rope import fixed as fixed_kernels
            from wrenorm.kernels.rope import lanes as lane_kernels
            from wrenorm.kernels.rope import tiled as tiled_kernels

            cpu = self.device.startswith("cpu")
            # lanes fill a CPU's vector units; a GPU runs one chain per thread, its state in registers and
            # shared memory (tiled.py) up to tiled.MAX_NODES nodes
            if tiled is None:
                tiled = not cpu and self.n <= tiled_kernels.MAX_NODES and not lanes
            if lanes is None:
                lanes = lane_kernels.LANES if cpu and self.n <= lane_kernels.MAX_NODES and not tiled else 0
            if tiled and lanes:
                raise ValueError("choose the tiled kernel or the lane kernel, not both")
            if tiled:
                self.kernel = tiled_kernels.tiled_kernel(self.n)
                self.block = tiled_kernels.BLOCK
            elif lanes:
                self.kernel = lane_kernels.lanes_kernel(self.n, lanes)
                self.lanes = int(lanes)
            elif self.n <= fixed_kernels.MAX_NODES:
                self.kernel = fixed_kernels.fast_kernel(self.n)
        self._loaded = False

    def rollout(self, pos0: np.ndarray, vel0: np.ndarray, hand: np.ndarray, path_index: np.ndarray,
                params: ChainParams, steps: int, t0: float = 0.0, stop_at_hit: bool = True,
                chunk: int | None = None, trajectory_every: int | None = None, host: bool = True) -> RolloutResult:
        """pos0/vel0 (B, N, 3); hand (P, S, 3) hand samples at t0 + s dt with S > steps. host=False leaves the
        results on the device (`events`; the per-chain arrays None): for an observable computed there."""
        n, dev = self.n, self.device
        B = params.batch
        hand = np.asarray(hand, dtype=np.float32)
        if hand.ndim != 3 or hand.shape[1] <= steps:
            raise ValueError(f"hand must be (paths, >{steps}, 3), got {hand.shape}")
        pos0 = np.broadcast_to(np.asarray(pos0, np.float32), (B, n, 3))
        vel0 = np.broadcast_to(np.asarray(vel0, np.float32), (B, n, 3))
        path_index = np.broadcast_to(np.asarray(path_index, np.int32), (B,))
        f32 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=float, device=dev)  # noqa: E731
        v3 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=dev)  # noqa: E731
        state = ChainState()
        state.pos, state.vel = v3(pos0), v3(vel0)
        state.prev = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        state.prev_vel = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        state.lam = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        state.lam_link = wp.zeros((B, n), dtype=float, device=dev)
        state.seg = wp.zeros((B, n), dtype=wp.vec4, device=dev)
        # the kernels record the trajectory themselves: a whole rollout stays one launch (no host step per frame)
        every = int(trajectory_every or 0)
        n_frames = -(-steps // every) + 1 if every else 1
        frames = np.zeros((n_frames, B, n, 3) if every else (1, 1, 1, 3), np.float32)
        if every:
            frames[0] = pos0
        state.frames = wp.array(frames, dtype=wp.vec3, device=dev)
        hand_w = v3(hand)
        pidx = wp.array(np.ascontiguousarray(path_index), dtype=wp.int32, device=dev)
        prm = ChainParameters()
        for f in ChainParams.FIELDS:
            setattr(prm, f, f32(getattr(params, f)))
        cfg = ChainSettings()
        cfg.n, cfg.min_sep, cfg.link, cfg.dt = n, self.min_sep, self.link, self.dt
        cfg.gravity, cfg.iters, cfg.cull = wp.vec3(*self.gravity), self.iterations, int(self.cull)
        cfg.margin, cfg.vmax = self.margin, VMAX
        cfg.frame_every, cfg.frame_end = every, steps
        ev = ChainEvents()
        ev.status = wp.zeros(B, dtype=wp.int32, device=dev)
        ev.hit_frame = wp.array(np.full(B, -1, np.int32), dtype=wp.int32, device=dev)
        ev.hit_alpha = wp.zeros(B, dtype=float, device=dev)
        ev.hit_s = wp.zeros(B, dtype=wp.vec2, device=dev)
        ev.crit_pos = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        ev.crit_vel = wp.zeros((B, n), dtype=wp.vec3, device=dev)
        ev.clearance = wp.array(np.full(B, self.margin, np.float32), dtype=float, device=dev)
        if not self._loaded:
            # build before the sliced launch: two threads meeting an unbuilt module both compile it
            wp.load_module(self.kernel.module, device=dev)
            self._loaded = True
        chunk = max(1, int(chunk or steps))
        wp.synchronize_device(dev)
        t_kernel = time.perf_counter()
        for s0 in range(0, steps, chunk):
            ns = min(chunk, steps - s0)

            def launch(offset, count, s0=s0, ns=ns):
                threads = -(-count // self.lanes) if self.lanes else count
                if self.block:  # whole blocks: every thread of a block takes part in its barriers
                    threads = -(-count // self.block) * self.block
                wp.launch(self.kernel, dim=threads, device=dev, block_dim=self.block or 256, inputs=[
                    state, hand_w, pidx, prm, cfg, s0, ns, int(stop_at_hit), ev, offset, offset + count])

            # Warp's CPU tiles share one static buffer per module: concurrent slices would race on it
            launch_sliced(launch, B, dev, 1 if self.block and dev.startswith("cpu") else self.workers)
        wp.synchronize_device(dev)
        # launches alone, without host<->device copies: what a GPU kernel sustains
        self.last_kernel_seconds = time.perf_counter() - t_kernel
        if not host:
            return RolloutResult(*[None] * 11, events=ev, dt=self.dt, t0=t0)
        st = ev.status.numpy()
        hf = ev.hit_frame.numpy()
        ha = ev.hit_alpha.numpy()
        hs = ev.hit_s.numpy()
        hit = st == 1
        return RolloutResult(
            status=st, hit_frame=hf, hit_alpha=ha,
            hit_time=np.where(hit, t0 + (hf - 1 + ha.astype(np.float64)) * self.dt, np.nan),
            s_a=np.where(hit, hs[:, 0], np.nan), s_b=np.where(hit, hs[:, 1], np.nan),
            crit_pos=ev.crit_pos.numpy(), crit_vel=ev.crit_vel.numpy(), clearance=ev.clearance.numpy(),
            final_pos=state.pos.numpy(), final_vel=state.vel.numpy(),
            trajectory=state.frames.numpy() if every else None,
            trajectory_times=t0 + self.dt * np.minimum(np.arange(n_frames) * every, steps) if every else None,
            events=ev, dt=self.dt, t0=t0)


# ---------------------------------------------------------------------------------- helpers
def hanging_state(hand0: np.ndarray, n_nodes: int, link: float) -> tuple[np.ndarray, np.ndarray]:
    """A chain hanging straight down from the hand at rest: (N, 3) positions and velocities."""
    pos = np.asarray(hand0, np.float64)[None, :] + np.outer(np.arange(n_nodes) * link, [0.0, 0.0, 1.0]) * -1.0
    return pos.astype(np.float32), np.zeros_like(pos, dtype=np.float32)


