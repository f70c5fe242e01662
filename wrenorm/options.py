"""Command-line options with their ranges declared where they are declared: every number is checked (finite,
inside its documented range) before any work starts, lists take commas or spaces alike and refuse repeats,
and a bad value is one line naming the option and the problem (exit 2)."""
from __future__ import annotations

import argparse
import math
import re
import sys


class OneLineParser(argparse.ArgumentParser):
    """argparse, but an error is one line on stderr (`wrenorm: error: --opt: problem`) and exit code 2."""

    def error(self, message: str):  # noqa: D401 (argparse's signature)
        m = re.match(r"argument (\S+?)(?:/\S+)?: (.*)$", message, re.S)
        if m:  # name the option and the field it sets, then the problem
            flag, problem = m.groups()
            dest = next((a.dest for a in self._actions if flag in a.option_strings), None)
            message = f"{flag}: {dest}: {problem}" if dest else f"{flag}: {problem}"
        if "unrecognized arguments" in message and "--verbose" in message.split():
            message += " (--verbose goes before the command: python -m wrenorm --verbose fit ...)"
        where = self.prog.split(" ", 1)[1] + ": " if " " in self.prog else ""  # the top parser is wrenorm itself
        print(f"wrenorm: error: {where}{' '.join(message.split())}", file=sys.stderr)
        raise SystemExit(2)


def _fmt(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def number(lo=None, hi=None, integer: bool = False, lo_open: bool = False):
    """An argparse `type` that accepts a finite number (an integer if asked) in [lo, hi] (or (lo, hi] with
    lo_open)."""
    def parse(text: str):
        s = str(text).strip()
        try:
            v = int(s) if integer else float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if integer else 'a number'}, got {text!r}") \
                from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise argparse.ArgumentTypeError(f"must be {'>' if lo_open else '>='} {_fmt(lo)}, got {s}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {_fmt(hi)}, got {s}")
        return v

    parse.__name__ = "integer" if integer else "number"
    return parse


def range_text(lo=None, hi=None, lo_open: bool = False) -> str:
    if lo is not None and hi is not None:
        return f"{'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}]"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_fmt(lo)}"
    return f"<= {_fmt(hi)}" if hi is not None else "any"


class _GivenList(list):
    """A list given on the command line, as against the option's default, which a second use replaces."""


class ListAction(argparse.Action):
    """nargs='+' whose items may also be comma-separated; every item parsed by `item`; no repeats. Given twice
    (`--reference a.npz --reference b.npz`) the lists join: argparse's plain nargs would keep only the last."""

    def __init__(self, *args, item=str, unique=True, unordered=False, **kw):
        self.item, self.unique = item, unique
        self.unordered = unordered  # the list names a set (parameters, training rates): order means nothing
        super().__init__(*args, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        out = []
        for v in values:
            for part in str(v).split(","):
                part = part.strip()
                if not part:
                    continue
                try:
                    out.append(self.item(part))
                except argparse.ArgumentTypeError as e:
                    parser.error(f"argument {option_string}: {e}")
        if not out:
            parser.error(f"argument {option_string}: needs at least one value")
        earlier = getattr(namespace, self.dest, None)
        if isinstance(earlier, _GivenList):
            out = earlier + out
        if self.unique and len(set(out)) != len(out):
            seen = [x for i, x in enumerate(out) if x in out[:i]]
            parser.error(f"argument {option_string}: repeated value {_fmt(seen[0])}")
        setattr(namespace, self.dest, _GivenList(out))


def add_number(p: argparse.ArgumentParser, flag: str, *, default, lo=None, hi=None, integer: bool = False,
               lo_open: bool = False, help: str = "", unit: str = "", default_text: str | None = None, **kw) -> None:
    """--flag N, range-checked; the range (and unit) appear in --help, with `default_text` in place of the default
    where that is None (filled in later)."""
    rng = range_text(lo, hi, lo_open)
    shown = default if default_text is None else default_text
    text = f"{help} ({'integer ' if integer else ''}{rng}{' ' + unit if unit else ''}; default {shown})".strip()
    p.add_argument(flag, type=number(lo, hi, integer, lo_open), default=default, help=text, **kw)


def add_list(p: argparse.ArgumentParser, flag: str, *, default, item=str, help: str = "", unique: bool = True,
             unordered: bool = False, **kw) -> None:
    """--flag A B or --flag A,B: a list (repeats refused unless unique=False; unordered: a set, whose orders a sweep
    counts as one value)."""
    p.add_argument(flag, nargs="+", action=ListAction, item=item, unique=unique, unordered=unordered, default=default,
                   help=f"{help} (spaces or commas)".strip(), **kw)


def add_numbers(p: argparse.ArgumentParser, flag: str, *, default, lo=None, hi=None, integer: bool = False,
                lo_open: bool = False, help: str = "", unit: str = "", **kw) -> None:
    rng = range_text(lo, hi, lo_open)
    add_list(p, flag, default=default, item=number(lo, hi, integer, lo_open),
             help=f"{help} (each {'an integer ' if integer else ''}{rng}{' ' + unit if unit else ''})", **kw)


def path_kind(action: argparse.Action) -> tuple[str | None, set]:
    """Whether an option reads a file or a folder, from its own definition: its metavar names FILE (`FILE.csv`) or
    DIR. The metavar's other words (`measured|fitted|FILE`) are labels it takes instead of a path. Returns ("file" |
    "folder" | None, labels). (Not type=Path alone: that may be a folder the command writes.)"""
    words = action.metavar.split("|") if isinstance(action.metavar, str) else []
    holders = [w.split(".")[0] for w in words if w.split(".")[0].isupper()]
    labels = {w for w in words if not w.split(".")[0].isupper()}
    if any(h.startswith("FILE") for h in holders):
        return "file", labels
    if any(h.startswith("DIR") for h in holders):
        return "folder", labels
    return None, labels
