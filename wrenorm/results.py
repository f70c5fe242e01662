"""Writing results atomically, and what goes in them besides numbers."""
from __future__ import annotations

import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

SCHEMA = "wrenorm.result/1"


def flow_point_std(parameter: dict):
    """A flow point's std of one parameter, as flow.json holds it (`std`; flows before stop 56 kept only the restarts'
    spread, `std_restarts`)."""
    return parameter.get("std", parameter.get("std_restarts"))


def jsonable(obj):
    """obj with numpy arrays and scalars as plain lists and numbers, and non-finite floats as None (JSON null)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


_UMASK = os.umask(0)
os.umask(_UMASK)


def stored_digest(obj) -> str:
    """sha256 of `obj` as write_json stores it (arrays as lists, non-finite numbers as null, keys sorted): a file
    read back hashes the same as the object that was written, so a resume can tell an edited state file."""
    import hashlib

    stored = json.loads(json.dumps(jsonable(obj), default=str))
    return hashlib.sha256(json.dumps(stored, sort_keys=True).encode()).hexdigest()


def write_atomic(path: str | os.PathLike, data: bytes | str, durable: bool = True) -> Path:
    """Write to a temporary file in the same folder, then rename over `path`: a reader sees the old file or the
    new one, never a part. durable: fsync before the rename, so the new file also survives a power loss (a
    per-generation checkpoint skips it: the kernel's page cache survives a killed process, and the fsync costs
    more than the generation)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # as an ordinary file would be (mkstemp makes it private)
        with os.fdopen(fd, mode) as f:
            f.write(data)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_json(path: str | os.PathLike, obj: dict, durable: bool = True) -> Path:
    return write_atomic(path, json.dumps(jsonable(obj), indent=2, allow_nan=False) + "\n", durable)


def versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("wrenorm", "warp-lang", "numpy", "scipy", "cma", "torch", "newton", "rerun-sdk", "mujoco"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out
