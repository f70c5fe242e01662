"""The coarse rope chain (the flying knot's model): N point masses, inextensible links, bending, drag, and
the first self-collision of each chain, thousands of chains per launch.

model.py     shared definitions (constants, segment distance, node masses)
generic.py   the size-generic kernel (the reference the faster variants are tested against, bit for bit)
fixed.py     one kernel per chain size, state in kernel-local matrices, culled collision test (long chains)
lanes.py     16 chains per CPU thread in vector lanes (the CPU default)
tiled.py     one chain per GPU thread, state in registers and shared memory (the CUDA default up to 16 nodes)
grad.py      a tape-differentiable variant without collisions, for smooth observables
sim.py       RopeSim: picks the variant for the device and size, launches it over slices of the batch
"""
from wrenorm.kernels.rope.generic import rollout_kernel
from wrenorm.kernels.rope.model import GRAVITY, VMAX, node_w, seg_closest
from wrenorm.kernels.rope.sim import ChainParams, RolloutResult, RopeSim, hanging_state

__all__ = ["GRAVITY", "VMAX", "ChainParams", "RolloutResult", "RopeSim", "hanging_state", "node_w", "rollout_kernel",
           "seg_closest"]
