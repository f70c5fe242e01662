"""CUDA checks that need no GPU, and the CPU/CUDA parity check that does.

`compile_for_cuda` builds each kernel module to an sm_XX cubin with the NVRTC that ships inside
warp-lang (no driver needed), so a CPU-only machine catches CUDA code-generation failures. The
cubin's `.nv.info` attributes give each kernel's registers and stack frame per thread: 255
registers plus a large frame means spills to local memory and few resident warps, which bounds
GPU throughput before any GPU is at hand.

`parity(device)` runs the rope, swimmer and PD kernels on the CPU and on `device` with the same
inputs and reports how far the outputs differ (float32 differs between the two: FMA contraction,
fast maths; the rope after its first self-contact is chaotic, so events are compared, not states).
"""
from __future__ import annotations

import struct
import tempfile
from pathlib import Path

import numpy as np

# .nv.info attribute codes (EIATTR_*) read from the cubin
_REGCOUNT, _FRAME_SIZE = 0x2F, 0x11


def kernel_modules(rope_sizes=(8, 16)) -> dict:
    """name -> warp Module for every simulation kernel (per-size rope kernels for `rope_sizes`)."""
    from wrenorm.kernels import arm, pd
    from wrenorm.kernels.rope import fixed as rope_fast
    from wrenorm.kernels.rope import generic, grad
    from wrenorm.kernels.swimmer import fluid, kernel
    from wrenorm.tasks.rope.reference import newton as rope_newton

    mods = {"pd": pd, "arm": arm, "rope": generic, "swimmer": kernel, "swimmer_fluid": fluid,
            "rope_grad": grad, "rope_newton": rope_newton}
    for n in rope_sizes:
        mods[f"rope_fast[N={n}]"] = rope_fast.fast_kernel(n).module
    return mods


def _sections(data: bytes) -> list[tuple[str, int, int]]:
    shoff = struct.unpack_from("<Q", data, 0x28)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    raw = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize) for i in range(shnum)]
    strtab = raw[shstrndx][4]
    out = []
    for name, _typ, _flags, _addr, off, size, *_ in raw:
        end = data.index(b"\0", strtab + name)
        out.append((data[strtab + name:end].decode(), off, size))
    return out


def cubin_resources(path: Path) -> dict:
    """Largest register count and stack frame (bytes per thread) over the kernels of one cubin."""
    data = Path(path).read_bytes()
    if data[:4] != b"\x7fELF":
        raise ValueError(f"{path}: not an ELF cubin")
    regs, frame = [], []
    for name, off, size in _sections(data):
        if name != ".nv.info":
            continue
        p = off
        while p < off + size:
            fmt, attr = data[p], data[p + 1]
            if fmt == 0x04:  # EIFMT_SVAL: u16 size, then (function index, value)
                sz = struct.unpack_from("<H", data, p + 2)[0]
                if attr in (_REGCOUNT, _FRAME_SIZE) and sz >= 8:
                    val = struct.unpack_from("<I", data, p + 8)[0]
                    (regs if attr == _REGCOUNT else frame).append(val)
                p += 4 + sz
            elif fmt == 0x03:  # EIFMT_HVAL: u16 value
                p += 4
            elif fmt == 0x02:  # EIFMT_BVAL
                p += 4
            elif fmt == 0x01:  # EIFMT_NVAL
                p += 2
            else:
                raise ValueError(f"{path}: unknown .nv.info format {fmt:#x}")
    if not regs:
        raise ValueError(f"{path}: no register counts in .nv.info")
    return {"registers": max(regs), "frame_bytes": max(frame) if frame else 0}


def compile_for_cuda(modules: dict, arch: int = 90) -> dict:
    """name -> {registers, frame_bytes, cubin_bytes} after an ahead-of-time NVRTC build for sm_<arch>."""
    import warp as wp

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, mod in modules.items():
            files = wp.compile_aot_module(mod, device=None, arch=arch, module_dir=tmp, use_ptx=False)
            cubins = [Path(f) for f in files if str(f).endswith(".cubin")]
            if not cubins:
                raise RuntimeError(f"{name}: no cubin produced for sm_{arch}")
            res = cubin_resources(cubins[0])
            res["cubin_bytes"] = cubins[0].stat().st_size
            out[name] = res
    return out


# ------------------------------------------------------------------------------- parity (needs a GPU)
def _rope_case(device: str, batch: int = 512, steps: int = 240):
    from wrenorm.kernels import rope

    n, dt = 16, 0.005
    link = 1.1 / (n - 1)
    from wrenorm.tasks.rope.bench import swing_paths

    paths = swing_paths(8, steps, dt)
    pidx = np.arange(batch, dtype=np.int32) % paths.shape[0]
    rng = np.random.default_rng(3)
    params = rope.ChainParams(node_mass=np.full(batch, 0.2 / n), lead_mass=np.full(batch, 0.05),
                              bend_k=rng.uniform(0.5, 2.0, batch) * 1.5e-2, bend_b=np.full(batch, 1e-3),
                              drag_lin=np.zeros(batch), drag_quad=np.full(batch, 0.02), radius=np.full(batch, 0.01))
    p0, v0 = rope.hanging_state(paths[0, 0], n, link)
    pos0 = np.broadcast_to(p0, (batch, n, 3)) + (paths[pidx, 0] - paths[0, 0])[:, None, :]
    return rope.RopeSim(n, link, dt, device).rollout(pos0, v0, paths, pidx, params, steps)


def parity(device: str) -> dict:
    """Largest CPU-vs-`device` differences of each kernel's outputs on the same inputs."""
    from wrenorm.kernels import pd

    out = {}
    a, b = _rope_case("cpu"), _rope_case(device)
    both = (a.status == 1) & (b.status == 1)
    out["rope"] = {"status_agree": float(np.mean(a.status == b.status)),
                   "hit_time_max_abs_s": float(np.max(np.abs(a.hit_time[both] - b.hit_time[both]))) if both.any() else None,
                   "hit_fraction_cpu": float(np.mean(a.status == 1))}
    from wrenorm.tasks.swimmer import body as swimmer_body, data as swimmer_data

    rates = swimmer_data.load_builtin()
    rate = min(rates, key=lambda r: abs(r.label - 1.0))
    coef = np.tile(np.array([0.4, 7.79, 2.81, 3.84, 0.27]), (64, 1)) * np.linspace(0.8, 1.2, 64)[:, None]
    swim = {dev: swimmer_body.build_batch([rate], device=dev, dt=swimmer_body.DEFAULT_DT, warm_seconds=0.0,
                                          meas_seconds=2.0, max_warm_seconds=None).run(coef)
            for dev in ("cpu", device)}
    out["swimmer"] = {"speed_max_rel": float(np.max(np.abs(swim[device] / swim["cpu"] - 1.0)))}
    steps = 500
    q_des = np.random.default_rng(0).normal(size=(2, steps)) * 0.1
    zeros = np.zeros((2, steps))
    values = np.tile([0.05, 20.0, 0.5, 0.0, 0.0], (32, 1)) * np.linspace(0.9, 1.1, 32)[:, None]
    errs = {dev: pd.simulate(values, pd.PDCommands(q_des, zeros, zeros, np.full((2, steps + 1), 0.1),
                                                   np.zeros((2, 2)), dev), pd.SEMI_IMPLICIT, 1e-3)[0]
            for dev in ("cpu", device)}
    out["pd"] = {"error_max_rel": float(np.max(np.abs(errs[device] / errs["cpu"] - 1.0)))}
    return out
