"""Use every CPU core for Warp launches.

Warp runs a CPU launch on one core (a plain loop over threads). Kernels therefore take an
`offset` argument and are launched on contiguous slices of the batch from Python threads;
Warp releases the GIL while a CPU kernel runs, so the slices run concurrently. On CUDA one
launch covers the whole batch.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

_POOL: ThreadPoolExecutor | None = None


def cpu_workers() -> int:
    env = os.environ.get("WRENORM_THREADS")
    if env:
        return max(1, int(env))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def slices(n: int, parts: int, min_size: int = 64) -> list[tuple[int, int]]:
    """Split range(n) into at most `parts` contiguous (start, count) pieces of at least min_size."""
    parts = max(1, min(parts, n // min_size if n >= min_size else 1))
    base, extra = divmod(n, parts)
    out, start = [], 0
    for i in range(parts):
        count = base + (1 if i < extra else 0)
        if count:
            out.append((start, count))
        start += count
    return out


def launch_sliced(launch: Callable[[int, int], None], n: int, device: str, workers: int | None = None) -> None:
    """Call launch(offset, count) over the batch: once on CUDA, on one slice per core on the CPU.

    `launch` must only touch its own slice, and must synchronise itself if it needs results
    (Warp CPU launches are synchronous).
    """
    if not str(device).startswith("cpu"):
        launch(0, n)
        return
    parts = slices(n, workers or cpu_workers())
    if len(parts) == 1:
        launch(*parts[0])
        return
    global _POOL
    if _POOL is None or _POOL._max_workers < len(parts):
        _POOL = ThreadPoolExecutor(max_workers=len(parts), thread_name_prefix="wrenorm-launch")
    for f in [_POOL.submit(launch, s, c) for s, c in parts]:
        f.result()
