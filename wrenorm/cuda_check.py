"""CUDA checks that need no GPU, and the CPU/CUDA parity check that does.

`compile_for_cuda` builds each kernel module to an sm_XX cubin with the NVRTC that ships inside
warp-lang (no driver needed), so a CPU-only machine catches CUDA code-generation failures. The
cubin's `.nv.info` attributes give each kernel's registers and stack frame per thread: 255
registers plus a large frame means spills to local memory and few resident warps, which bounds
GPU throughput before any GPU is at hand.

`parity(device)` runs every registered system's kernels on the CPU and on `device` with the same
inputs (each system's `parity`) and reports how far the outputs differ (float32 differs between the
two: FMA contraction, fast maths).
"""
from __future__ import annotations

import struct
import tempfile
from pathlib import Path

# .nv.info attribute codes (EIATTR_*) read from the cubin
_REGCOUNT, _FRAME_SIZE = 0x2F, 0x11


def kernel_modules() -> dict:
    """name -> Warp module for every registered system's kernels."""
    from .system import resolve, systems

    mods = {}
    for system in systems().values():
        if system.kernel_modules is not None:
            mods.update(resolve(system.kernel_modules)())
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
def parity(device: str) -> dict:
    """Per system, the largest CPU-vs-`device` differences of its kernels' outputs on the same inputs."""
    from .system import resolve, systems

    return {name: resolve(s.parity)(device) for name, s in systems().items() if s.parity is not None}
