"""The planar robot fish: a free head driven by a tail with prescribed kinematics, every part carrying
MuJoCo's ellipsoid fluid model with five shared coefficients.

fluid.py    the planar ellipsoid fluid wrench (MuJoCo's model) and the ellipsoid's shape constants
kernel.py   the batched swimmer step (one thread per candidate x motor rate), speed and yaw measured on the fly
batch.py    host side: per-sample sums over parts, and SwimBatch, which launches the kernel
"""
from wrenorm.kernels.swimmer.batch import SwimBatch, reduce_table
from wrenorm.kernels.swimmer.fluid import fluid_wrench_local
from wrenorm.kernels.swimmer.kernel import ROW

__all__ = ["ROW", "SwimBatch", "fluid_wrench_local", "reduce_table"]
