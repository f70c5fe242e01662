"""Command-line list options: a list option given twice joins its values (argparse's plain nargs keeps only the last,
which dropped a fit's first --reference in silence)."""
import argparse

import pytest

from wrenorm.cli import build_parser
from wrenorm.options import add_list


def test_list_option_given_twice_joins():
    p = argparse.ArgumentParser()
    add_list(p, "--reference", default=["built-in.npz"])
    assert p.parse_args([]).reference == ["built-in.npz"]
    assert p.parse_args(["--reference", "a.npz"]).reference == ["a.npz"]
    assert p.parse_args(["--reference", "a.npz", "--reference", "b.npz,c.npz"]).reference == ["a.npz", "b.npz", "c.npz"]
    with pytest.raises(SystemExit):  # a repeat across the two uses is still a repeat
        p.parse_args(["--reference", "a.npz", "--reference", "a.npz"])


def test_fit_rope_keeps_every_reference():
    argv = ["fit", "rope", "--reference", "a.npz", "--reference", "b.npz", "--validate", "c.npz", "--validate", "d.npz"]
    args = build_parser(argv).parse_args(argv)
    assert args.reference == ["a.npz", "b.npz"] and args.validate == ["c.npz", "d.npz"]


def test_correct_rope_keeps_every_params_entry():
    argv = ["correct", "rope", "--params", "measured", "--params", "fitted,renormalised"]
    assert build_parser(argv).parse_args(argv).params == ["measured", "fitted", "renormalised"]
