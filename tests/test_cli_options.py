"""Command-line list options: a list option given twice joins its values (argparse's plain nargs keeps only the last,
which dropped a fit's first --reference in silence)."""
import argparse

import pytest

from wrenorm.cli import build_parser, main
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


@pytest.mark.parametrize("flag, most", [("--command-step", "6"), ("--fd-step", "6"), ("--noise-size", "0.1"),
                                        ("--marker-noise", "0.1"), ("--time-noise", "1"), ("--snr", "1000")])
def test_sensitivity_rope_refuses_absurd_sizes(tmp_path, capsys, flag, most):
    """1e300 had been answered with a confident count of directions, overflow warnings or an OverflowError traceback
    (review of stop 54)."""
    assert main(["sensitivity", "rope", flag, "1e300", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert f"{flag}: " in err and f"must be <= {most}" in err and err.count("\n") == 1


def test_an_option_of_wrenorm_itself_after_the_command_says_where_it_goes(capsys):
    """`fit pd --verbose` had said "wrenorm: error: wrenorm: unrecognized arguments: --verbose" (a new user's review of
    stop 55): the program named twice, and not where the option goes."""
    assert main(["fit", "pd", "--verbose"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("wrenorm: error: unrecognized arguments: --verbose") and "goes before the command" in err


def test_the_summary_prints_the_std_with_the_misfit_as_noise_beside_the_posterior_one(tmp_path, capsys):
    """The real fish misses its noise-normalised features by chi^2/dof 13: the printed +- (the posterior's) is 3.7x
    narrower than the data allow with the misfit taken as noise, which result.json held and the summary did not print
    (a review of stop 55). A fit within its noise prints the one std."""
    from wrenorm.cli import _print_summary

    def result(chi2):
        return {"task": "swimmer", "resolution": {}, "loss": {"measured": 1.0, "fitted": 0.5},
                "parameters": {"kutta_lift": {"measured": 3.84, "fitted": 1.22, "std": 0.048, "frozen": False}},
                "validation": {"verdict": "expand", "note": ""},
                "uncertainty": {"chi2_per_dof": chi2, "std_inflated_by_misfit": {"kutta_lift": 0.048 * chi2 ** 0.5}}}

    _print_summary(result(13.0), tmp_path)
    assert "fitted 1.22 ± 0.048 (± 0.173 from the data alone, the misfit taken as noise)" in capsys.readouterr().out
    _print_summary(result(0.8), tmp_path)
    assert "± 0.048\n" in capsys.readouterr().out
