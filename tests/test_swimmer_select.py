"""`select swimmer`: the rules that choose features, prior scale and parameter set see the training clips only."""
import numpy as np
import pytest

from wrenorm.tasks.swimmer import data as sd
from wrenorm.tasks.swimmer import select


@pytest.fixture(scope="module")
def study():
    return select.Study(sd.load_builtin(), [1.0, 1.75], generations=2, quiet=True)


def test_the_study_never_holds_a_held_out_clip(study):
    assert [r.label for r in study.rates] == [1.0, 1.75]
    p = study.problem([1.0], "yaw", 0.5)
    assert [c.meta["label"] for c in p.train] == [1.0] and [c.meta["label"] for c in p.held_out] == [1.75]
    # a one-rate fold keeps the noise model of both training clips (the fit's own)
    assert p.noise == study.noise == study.problem([1.0, 1.75], "all", None).noise


def test_information_sees_more_directions_with_each_feature_group(study):
    info = select.information(study)
    speed = info["speed"]
    assert len(speed["singular_values"]) == 2  # two speeds: two directions of five
    assert all(np.isinf(v) for v in speed["data_std_efolds"].values())
    assert len(info["speed+yaw"]["singular_values"]) == 5
    # every group adds information: the all-feature std is below each all-but-one std, coefficient by coefficient
    for g in ("yaw", "sway", "surge2", "surge1"):
        for n, s in info["all"]["data_std_efolds"].items():
            assert s <= info[f"all-{g}"]["data_std_efolds"][n] * (1 + 1e-9)
    # Magnus lift is the coefficient the features see least
    std = info["all"]["data_std_efolds"]
    assert max(std, key=std.get) == "magnus_lift"


def test_choice_takes_the_smallest_error_and_among_near_ties_the_stronger_prior():
    rows = [{"features": f, "prior_scale": p, "error": e} for f, p, e in (
        ("yaw", None, 0.0150), ("yaw", None, -0.0150), ("yaw", 1.0, 0.0130), ("yaw", 1.0, 0.0130),
        ("yaw", 0.5, 0.0138), ("yaw", 0.5, -0.0138), ("speed", 0.5, 0.0300), ("speed", 0.5, 0.0100))]
    got = select.choose(rows)
    assert got["chosen"]["features"] == "yaw" and got["chosen"]["prior_scale"] == 0.5
    assert select.choose(rows, tie=0.0005)["chosen"]["prior_scale"] == 1.0


def test_unreachable_groups_are_not_candidates():
    reach = {"speed": {"reachable": True}, "yaw": {"reachable": True}, "sway": {"reachable": False},
             "surge2": {"reachable": True}, "surge1": {"reachable": False}}
    sets = select.candidate_sets(reach)
    assert set(sets) == {"speed", "yaw", "surge2", "yaw+surge2"}
    assert sets["yaw+surge2"] == ("speed", "yaw_amp", "yaw_phase", "surge2_amp", "surge2_phase")


def test_bad_selection_input_exits_2_before_writing(tmp_path, capsys):
    from wrenorm.cli import main

    out = tmp_path / "sel"
    assert main(["select", "swimmer", "--train", "1.00", "--out", str(out)]) == 2
    assert "--train" in capsys.readouterr().err and not out.exists()
    assert main(["select", "swimmer", "--generations", "0", "--out", str(out)]) == 2
    assert not out.exists()
    # what the selection chooses itself (or does not use) is refused, not accepted and ignored
    for flag, value in (("--features", "all"), ("--prior-scale", "1"), ("--speed-weight", "2"),
                        ("--integrator", "euler")):
        assert main(["select", "swimmer", flag, value, "--out", str(out)]) == 2
        assert flag in capsys.readouterr().err
    assert not out.exists()
