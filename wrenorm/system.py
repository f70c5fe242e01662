"""The contract between a system (tasks/<name>/) and the engine, and the registry that lists systems.

A system declares, once, in its package's `SYSTEM`:
  - its name and one line of help;
  - its fit options and how to build one Problem per resolution from them (`add_arguments`, `build`);
  - its search defaults (method, generations, population, restarts, polish);
  - optionally a resolution flow (`flow`), extra commands (`commands`, e.g. `reference rope`), a kernel
    benchmark (`bench`), its kernel modules for the ahead-of-time CUDA build and a CPU-vs-CUDA parity check.
The CLI, fit, flow, bench and the CUDA checks read only this. Importing a system's package must stay cheap
(no Warp kernels, no heavy libraries): those belong in the callables, imported when one runs.

Adding a system: a folder tasks/<name>/ whose __init__.py defines SYSTEM, and one line in tasks/__init__.py.
"""
from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field

from .errors import InputError

Ref = Callable | str  # a callable, or "package.module:name", imported when first called


@dataclass(frozen=True)
class SearchDefaults:
    """How `fit` searches this system unless told otherwise."""

    method: str = "cmaes"  # "cmaes" (event and contact observables) or "least-squares" (smooth residuals)
    generations: int = 60
    popsize: int | None = None  # None: pycma's default for the dimension
    sigma0: float = 0.2  # initial step in normalised [0, 1] coordinates
    polish: int = 0  # L-BFGS evaluations on tape gradients after the search (systems with a tape)
    restarts: int = 0  # identifiability restarts after the fit (further seeded searches side by side)
    # Width on a wide device (cuda): many seeded searches with larger populations in every batched evaluation
    # cost little more than one there and bring the spread of the optima. Set by the device's kind, never by
    # its size, so a run is the same wherever it runs; the CPU keeps one search.
    wide_searches: int = 32
    wide_popsize_factor: int = 4  # times pycma's default population for the dimension (IPOP-style width)


@dataclass(frozen=True)
class Flow:
    """The resolution flow theta*(a): one Problem per resolution."""

    add_arguments: Callable[[argparse.ArgumentParser], None]
    build: Ref  # (args, device) -> [Problem], one per resolution
    resolutions_help: str
    generations: int = 60
    analytic: Ref | None = None  # (problem, fitted dict) -> dict of analytic predictions per point


@dataclass(frozen=True)
class ExtraCommand:
    """A verb beyond fit/flow, e.g. `python -m wrenorm reference rope`."""

    verb: str
    help: str
    add_arguments: Ref  # (parser) -> None; called only when this command is the one asked for
    run: Ref  # (args) -> exit code
    # (result dict) -> [row dict]: what a sweep's table shows of one finished cell of this command (its outcome, one
    # row per part, e.g. per arm of a correction); None: the result's top-level numbers and strings
    table_rows: Ref | None = None
    sweep_summary: Ref | None = None  # (the done cells' rows) -> [line]: what the sweep says of them all at its end
    sweep_plot: tuple[str, ...] = ()  # the table_rows columns sweep.png draws against the swept axes
    sweep_part: str | None = None  # the table_rows column that splits one cell into rows (a correction's arm)


@dataclass(frozen=True)
class System:
    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    build: Ref  # (args, device) -> [Problem], one per resolution
    search: SearchDefaults = field(default_factory=SearchDefaults)
    flow: Flow | None = None
    commands: tuple[ExtraCommand, ...] = ()
    bench: Ref | None = None  # (device, batches, quick) -> {"rows": [...], "table": markdown}
    kernel_modules: Ref | None = None  # () -> {name: Warp module}, for the ahead-of-time CUDA build
    parity: Ref | None = None  # (device) -> largest CPU-vs-device differences of the kernels' outputs
    report: Ref | None = None  # (result dict) -> [(title, html)], the system's own sections of report.html
    observable: str = ""  # what behaviour the fit must reproduce, one sentence (the report's first question)
    omitted: str = ""  # the physics the coarse model leaves out, one sentence
    # (args) -> the names --free and --freeze may give, without building a problem (cheap: a sweep checks every
    # cell's names with it before any cell runs, and fit and flow before loading references); a Ref whose module
    # lacks it, or None: not checked before the problems are built
    parameter_names: Ref | None = None


def parameter_names(system: System, args) -> list[str] | None:
    """The names --free and --freeze may give for these options (System.parameter_names), None where the system does
    not say them without building its problems."""
    names = resolve(system.parameter_names, optional=True) if system.parameter_names is not None else None
    return None if names is None else list(names(args))


def resolve(ref: Ref, optional: bool = False) -> Callable | None:
    """A callable from a Ref; "pkg.module:name" is imported now (heavy modules load only when used). optional: None
    where the module has no such name (a convention a system may leave out)."""
    if callable(ref):
        return ref
    module, _, name = str(ref).partition(":")
    found = getattr(importlib.import_module(module), name, None)
    if found is None and not optional:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    return found


def from_package(package: str, help: str, search: SearchDefaults = SearchDefaults(), flow: Flow | None = None,
                 commands: tuple = (), bench: bool | None = None, observable: str = "", omitted: str = "") -> System:
    """A system laid out by convention in tasks/<name>/: options.py `add_arguments`, problem.py `build_problems`
    (and `parameter_names`, where it has one),
    bench.py `bench`, `parity` and `kernel_modules` and report.py `sections` where they exist (bench=False: no
    benchmark even with a bench.py; True: one is required)."""
    import importlib.util

    has_bench = importlib.util.find_spec(f"{package}.bench") is not None
    if bench is None:
        bench = has_bench
    elif bench and not has_bench:
        raise ImportError(f"{package}: bench=True but there is no {package}.bench module")
    options = importlib.import_module(f"{package}.options")
    ref = (lambda module, name: f"{package}.{module}:{name}") if bench else (lambda module, name: None)
    report = f"{package}.report:sections" if importlib.util.find_spec(f"{package}.report") else None
    return System(name=package.rsplit(".", 1)[-1], help=help, add_arguments=options.add_arguments,
                  build=f"{package}.problem:build_problems", search=search, flow=flow, commands=tuple(commands),
                  bench=ref("bench", "bench"), kernel_modules=ref("bench", "kernel_modules"),
                  parity=ref("bench", "parity"), report=report, observable=observable, omitted=omitted,
                  parameter_names=f"{package}.problem:parameter_names")


_REGISTRY: dict[str, System] = {}
_LOADED = False


def register(system: System) -> System:
    """Add a system (the registry line does this through tasks/__init__.py; tests may add toys)."""
    if not isinstance(system, System):
        raise TypeError(f"expected a System, got {type(system).__name__}")
    _REGISTRY[system.name] = system
    return system


def unregister(name: str) -> None:
    _REGISTRY.pop(name, None)


def systems() -> dict[str, System]:
    """Every registered system by name, in registration order."""
    global _LOADED
    if not _LOADED:
        from wrenorm.tasks import SYSTEMS

        for module in SYSTEMS:
            register(importlib.import_module(module).SYSTEM)
        _LOADED = True
    return dict(_REGISTRY)


def get(name: str) -> System:
    found = systems()
    if name not in found:
        raise InputError("system", name, f"unknown system; registered: {', '.join(found)}")
    return found[name]
