"""A sweep's spec (TOML) and its cells.

    task = "fit pd"                 # a command and a system, as typed after `python -m wrenorm`
    seeds = [0, 1, 2]               # each cell's --seed (default [0])

    [options]                       # the same for every cell: the task's options without "--"
    search = "cmaes"
    generations = 40
    no-record = true                # a switch: true adds it, false leaves it out

    [axes]                          # varied: every combination of these values, times the seeds
    f-sim = [100, 200, 400]
    integrator = ["semi-implicit", "explicit"]

Option names may use "-" or "_" (`f-sim`, `f_sim`); an option that takes several values takes a list (and an axis
of it a list of lists). `--out`, `--seed`, `--device`, `--resume`, `--force` and `--quiet` belong to the sweep.
Every cell's command line is checked with the task's own parser before anything runs: an unknown task or option,
a value out of range, an axis with repeated values (as the task reads them: 100 and 100.0 are one, and so are two
orders of a list that names a set, ListAction's unordered: --free, --freeze, --train), a parameter name the system
does not have, an option given twice (`K_D` and `K-D` are one, fixed or varied) is one line naming the key and the
problem (exit 2); so is a file or folder a cell is given (an option whose metavar says FILE or DIR) that does not
exist or cannot be read. The spec is UTF-8 (a byte-order mark is fine).
"""
from __future__ import annotations

import argparse
import codecs
import contextlib
import io
import itertools
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from wrenorm.errors import InputError
from wrenorm.options import ListAction, path_kind

TOP_LEVEL = ("task", "seeds", "options", "axes", "description")
RESERVED = {"out": "each cell's run folder is DIR/cells/<cell>", "seed": "use `seeds = [...]` at the top level",
            "device": "pass --device to the sweep command", "resume": "pass --resume to the sweep command",
            "force": "pass --force to the sweep command", "quiet": "cells always run quietly"}


@dataclass(frozen=True)
class Cell:
    index: int
    id: str
    axes: dict  # axis key -> value, as written in the spec
    seed: int
    argv: tuple  # verb, system, options..., --seed S (the sweep adds --out, --quiet, --device)

    def command(self, out: str | Path) -> str:
        import shlex

        return "python -m wrenorm " + " ".join(shlex.quote(a) for a in (*self.argv, "--out", str(out)))


@dataclass
class Spec:
    path: Path
    text: str
    verb: str
    system: str
    options: dict
    axes: dict
    seeds: list
    description: str = ""
    cells: list = field(default_factory=list)
    inputs: list = field(default_factory=list)  # the files and folders cells read, as the spec names them
    hashes: dict = field(default_factory=dict)  # input -> sha256 of its content (wrenorm.cli.content_hashes)

    @property
    def task(self) -> str:
        return f"{self.verb} {self.system}"


def _task_parser(verb: str, system: str) -> argparse.ArgumentParser | None:
    """The parser of `verb system` (None if there is no such command)."""
    from wrenorm.cli import build_parser

    parser = build_parser([verb, system])
    for level in (verb, system):
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or level not in sub.choices:
            return None
        parser = sub.choices[level]
    return parser


def _tasks_text() -> str:
    from wrenorm.system import systems

    out = []
    for s in systems().values():
        out += [f"fit {s.name}"] + ([f"flow {s.name}"] if s.flow else []) + [f"{c.verb} {s.name}" for c in s.commands]
    return ", ".join(out)


def _action(parser: argparse.ArgumentParser, key: str) -> argparse.Action | None:
    name = key.lstrip("-")
    flags = {"--" + name, "--" + name.replace("_", "-")}
    for a in parser._actions:
        if flags & set(a.option_strings) or (a.option_strings and a.dest == name.replace("-", "_")):
            return a
    return None


def _scalar(v, where: str, path: Path) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise InputError(path, where, f"expected a number or a string, got {v!r}")
    return repr(v) if isinstance(v, float) else str(v)


def _tokens(action: argparse.Action, value, where: str, path: Path) -> list[str]:
    """The command-line words that give `action` this value."""
    flag = next(f for f in action.option_strings if f.startswith("--"))
    if action.nargs == 0:  # a switch
        if not isinstance(value, bool):
            raise InputError(path, where, f"{flag} is a switch: give true or false, got {value!r}")
        if isinstance(action, argparse.BooleanOptionalAction):
            return [flag if value else "--no-" + flag[2:]]
        return [flag] if value else []
    many = action.nargs in ("+", "*") or (isinstance(action.nargs, int) and action.nargs > 1)
    if isinstance(value, list):
        if not many:
            raise InputError(path, where, f"{flag} takes one value, got a list")
        if not value:
            raise InputError(path, where, f"{flag} needs at least one value")
        return [flag, *(_scalar(v, where, path) for v in value)]
    return [flag, _scalar(value, where, path)]


def _parse(parser: argparse.ArgumentParser, head: list[str], words: list[str], where: str, path: Path, what: str):
    """Parse with the task's own parser; its one-line error becomes ours, naming the spec's key."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args([*words, "--out", "cell"])
    except SystemExit:
        msg = err.getvalue().strip().splitlines()
        text = msg[-1] if msg else "rejected by the task's parser"
        text = re.sub(r"^wrenorm: error: ", "", text)
        text = re.sub(rf"^{re.escape(' '.join(head))}: ", "", text)
        raise InputError(path, where, f"{what}{text}") from None


def _seeds(raw, path: Path) -> list[int]:
    if not isinstance(raw, list) or not raw:
        raise InputError(path, "seeds", f"expected a non-empty list of integers, got {raw!r}")
    for s in raw:
        if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < 2**31:
            raise InputError(path, "seeds", f"expected integers in [0, 2^31), got {s!r}")
    if len(set(raw)) != len(raw):
        raise InputError(path, "seeds", f"repeated seed {next(s for i, s in enumerate(raw) if s in raw[:i])}")
    return list(raw)


def _slug(value) -> str:
    text = ",".join(map(str, value)) if isinstance(value, list) else str(value)
    return re.sub(r"[^A-Za-z0-9.,+-]+", "_", text)[:40]


def load(path: str | Path) -> Spec:
    """Read, check and expand a spec; every problem is an InputError naming the key (the CLI: one line, exit 2)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(path, "spec", f"cannot be read: {e.strerror or e}") from None
    body = data.removeprefix(codecs.BOM_UTF8)  # what editors on Windows write first: a mark, not a statement
    try:  # TOML is UTF-8; newlines as a text-mode read gives them
        text = body.decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")
    except UnicodeDecodeError as e:
        at = e.start + len(data) - len(body)  # in the file, the mark included
        line, column = data.count(b"\n", 0, at) + 1, at - data.rfind(b"\n", 0, at)
        raise InputError(path, "encoding", f"not UTF-8 (TOML must be): byte 0x{data[at]:02x} at offset {at} (line "
                                           f"{line}, column {column}): {e.reason}; save the file as UTF-8") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, "toml", str(e)) from None
    for key in raw:
        if key not in TOP_LEVEL:
            raise InputError(path, key, f"unknown key; a spec has {', '.join(TOP_LEVEL)}")
    task = raw.get("task")
    if not isinstance(task, str) or len(task.split()) != 2:
        raise InputError(path, "task", f"expected a command and a system, e.g. \"fit pd\"; got {task!r}")
    verb, system = task.split()
    parser = _task_parser(verb, system)
    if parser is None:
        raise InputError(path, "task", f"unknown task {task!r}; known: {_tasks_text()}")
    if _action(parser, "out") is None or _action(parser, "seed") is None:
        raise InputError(path, "task", f"{task!r} takes no --out and --seed, so it cannot be a sweep's cell")
    options, axes = raw.get("options", {}), raw.get("axes", {})
    for key, table in (("options", options), ("axes", axes)):
        if not isinstance(table, dict):
            raise InputError(path, key, f"expected a table ([{key}]), got {table!r}")
    seeds = _seeds(raw.get("seeds", [0]), path)
    head = [verb, system]

    given: dict = {}  # option -> the key that gives it: `K_D` and `K-D` are one option, which the last would win
    for table, entries in (("options", options), ("axes", axes)):
        for key in entries:
            where = f"{table}.{key}"
            action = _check_key(parser, key, where, path, task)
            first = given.setdefault(action, where)
            if first.startswith("options.") and table == "axes":
                raise InputError(path, first, f"is also an axis ([axes] {key}): fix it or vary it, not both")
            if first != where:
                raise InputError(path, where, f"is the same option as {first} "
                                              f"({next(f for f in action.option_strings if f.startswith('--'))}): "
                                              "give it once")

    fixed: list[str] = []
    for key, value in options.items():
        fixed += _tokens(_action(parser, key), value, f"options.{key}", path)
    _parse(parser, head, [*fixed], "options", path, "")

    axis_words: dict[str, list[list[str]]] = {}
    for key, values in axes.items():
        where = f"axes.{key}"
        action = _check_key(parser, key, where, path, task)
        if not isinstance(values, list) or not values:
            raise InputError(path, where, f"expected a non-empty list of values, got {values!r}")
        words = [_tokens(action, v, where, path) for v in values]
        read = []  # each value as the cell's command reads it: 100 and 100.0 are one value
        for i, w in enumerate(words):
            value = getattr(_parse(parser, head, [*fixed, *w], where, path, f"value {values[i]!r}: "), action.dest)
            if getattr(action, "unordered", False):
                value = sorted(value, key=repr)
            if value in read:
                same = values[read.index(value)]
                raise InputError(path, where, f"repeated value {values[i]!r}"
                                              + ("" if repr(same) == repr(values[i]) else f" (the same as {same!r})"))
            read.append(value)
        axis_words[key] = words

    spec = Spec(path=path, text=text, verb=verb, system=system, options=dict(options), axes=dict(axes), seeds=seeds,
                description=str(raw.get("description", "")))
    keys = list(axes)
    combos = list(itertools.product(*[range(len(axes[k])) for k in keys]))
    names_given = [(t, k) for t, entries in (("options", options), ("axes", axes)) for k in entries
                   if _action(parser, k).dest in ("free", "freeze")]
    n = len(combos) * len(seeds)
    width = max(3, len(str(n - 1)))
    index = 0
    for combo in combos:
        words = [w for k, i in zip(keys, combo) for w in axis_words[k][i]]
        values = {k: axes[k][i] for k, i in zip(keys, combo)}
        if len(keys) > 1 or names_given:  # options that are fine alone may clash together
            where = "axes." + "+".join(keys) if keys else "options"
            what = "combination " + ", ".join(f"{k}={v!r}" for k, v in values.items()) + ": " if keys else ""
            parsed = _parse(parser, head, [*fixed, *words], where, path, what)
            if names_given:
                _check_names(parsed, parser, system, names_given, path, what)
        for seed in seeds:
            cid = f"{index:0{width}d}" + "".join(f"_{_slug(k)}-{_slug(v)}" for k, v in values.items()) + f"_seed-{seed}"
            spec.cells.append(Cell(index=index, id=cid, axes=values, seed=seed,
                                   argv=(*head, *fixed, *words, "--seed", str(seed))))
            index += 1
    _check_paths(spec, parser)
    return spec


def _check_names(parsed, parser, system: str, given: list, path: Path, what: str) -> None:
    """The parameters a cell frees or freezes are its system's (wrenorm.cli.check_parameter_set), before any cell
    runs: a misspelt name would otherwise fail every cell, each in its own log."""
    from wrenorm.cli import check_parameter_set
    from wrenorm.system import systems

    try:
        check_parameter_set(systems()[system], parsed)
    except InputError as e:
        dests = {"--free": ("free",), "--freeze": ("freeze",)}.get(e.source, ("free", "freeze"))
        table, key = next((t, k) for t, k in given if _action(parser, k).dest in dests)
        raise InputError(path, f"{table}.{key}", f"{what}{e.source} {e.field}: {e.problem}") from None


def _path_problem(p: Path, kind: str) -> str | None:
    """Why a cell could not read p as the option's file or folder (None: it can)."""
    try:
        if not p.exists():
            return "does not exist" + ("" if p.is_absolute() else f" (relative to {Path.cwd()}, where the sweep "
                                                                   "starts)")
        if kind == "file" and p.is_dir():
            return "is a folder, not a file"
        if kind == "folder" and not p.is_dir():
            return "is a file, not a folder"
        if p.is_dir():
            with os.scandir(p) as entries:
                next(entries, None)
        else:
            with open(p, "rb") as f:
                f.read(1)
    except OSError as e:
        return f"cannot be read: {e.strerror or e}"
    except ValueError as e:  # a NUL in the name
        return f"is not a usable path: {e}"
    return None


def _check_paths(spec: Spec, parser: argparse.ArgumentParser) -> None:
    """Every file and folder the spec gives a cell can be read, checked before any cell runs: a missing one would
    otherwise start Ray, fail each of its cells and be named only in their logs. Lists them in spec.inputs."""
    given = [("options", key, [value]) for key, value in spec.options.items()]
    given += [("axes", key, values) for key, values in spec.axes.items()]
    for table, key, values in given:
        action = _action(parser, key)
        kind, labels = path_kind(action)
        if kind is None:
            continue
        where, flag = f"{table}.{key}", next(f for f in action.option_strings if f.startswith("--"))
        split = isinstance(action, ListAction)  # --reference a.npz,b.npz: the parser splits it, and so must this
        for value in values:
            texts = [part.strip() for v in (value if isinstance(value, list) else [value])
                     for part in (_scalar(v, where, spec.path).split(",") if split else [_scalar(v, where, spec.path)])]
            if not any(texts):  # had passed here and failed in every cell, after Ray started (review of stop 54)
                raise InputError(spec.path, where, f"{_whose(spec, table, key, value)}: {flag}: an empty path")
            for text in texts:
                if not text or text in labels:  # an empty part of a list: the command skips it too
                    continue
                problem = _path_problem(Path(text), kind)
                if problem:
                    raise InputError(spec.path, where, f"{_whose(spec, table, key, value)}: {flag} {text}: {problem}")
                if text not in spec.inputs:
                    spec.inputs.append(text)


def _whose(spec: Spec, table: str, key: str, value) -> str:
    """The cells that get this value of the key."""
    if table == "options":
        return "every cell"
    cells = [c.id for c in spec.cells if c.axes[key] == value]
    return f"cell {cells[0]}" + (f" and {len(cells) - 1} more" if len(cells) > 1 else "")


def _check_key(parser, key: str, where: str, path: Path, task: str) -> argparse.Action:
    name = key.lstrip("-").replace("_", "-")
    if name in RESERVED or name.replace("-", "_") in RESERVED:
        raise InputError(path, where, f"is set by the sweep: {RESERVED[name.replace('-', '_')]}")
    action = _action(parser, key)
    if action is None or isinstance(action, argparse._HelpAction):
        known = sorted(f for a in parser._actions for f in a.option_strings
                       if f.startswith("--") and f[2:].replace("-", "_") not in RESERVED and f != "--help")
        raise InputError(path, where, f"unknown option of {task!r}; it has {', '.join(f[2:] for f in known)}")
    return action
