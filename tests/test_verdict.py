"""The held-out verdict (wrenorm.fit._validation): each condition judged against its own tolerance, the one furthest
outside it named, and held-out conditions whose data the system's checks doubt shown but not deciding."""
import numpy as np

from wrenorm.fit import _validation
from wrenorm.params import Parameter, ParameterSpace
from wrenorm.problem import Condition, Problem


class Offsets(Problem):
    """Error of condition j: |value - target_j|; its tolerance and data flags as given."""

    task = "offsets"

    def __init__(self, targets, tolerances=None, flags=None):
        self.space = ParameterSpace([Parameter("x", 0.0, -10.0, 10.0)])
        self.train = [Condition("train", 0.0)]
        self.held_out = [Condition(f"c{j}", t) for j, t in enumerate(targets)]
        self.tolerance, self.resolution = 1.0, {}
        self._tol = dict(tolerances or {})
        self._flags = dict(flags or {})

    def errors(self, values, conditions):
        return np.abs(np.asarray(values)[:, :1] - np.array([c.data for c in conditions])[None, :])

    def tolerance_for(self, condition):
        return self._tol.get(condition.name, self.tolerance)

    def data_flags(self, condition):
        return self._flags.get(condition.name, [])


def _verdict(problem, fitted):
    return _validation(problem, np.array([5.0]), np.array([fitted]))


def test_one_tolerance_gives_the_verdict_it_gave_before():
    v = _verdict(Offsets([0.2, -0.5]), 0.0)
    assert v["verdict"] == "absorbed" and v["worst_fitted_error"] == 0.5 and v["worst_condition"] == "c1"
    v = _verdict(Offsets([0.2, -1.5]), 0.0)
    assert v["verdict"] == "expand" and v["worst_fitted_error"] == 1.5 and "flagged_conditions" not in v


def test_a_condition_with_a_tighter_tolerance_decides_when_it_is_furthest_outside_its_own():
    v = _verdict(Offsets([0.3, -0.9], tolerances={"c0": 0.1}), 0.0)
    assert v["verdict"] == "expand"  # 0.3 against 0.1, though the larger error 0.9 is within 1.0
    assert v["worst_condition"] == "c0" and v["worst_fitted_error"] == 0.3 and v["worst_tolerance"] == 0.1
    assert v["conditions"]["c0"]["within_tolerance"] is False and v["conditions"]["c1"]["within_tolerance"] is True


def test_flagged_conditions_are_shown_but_do_not_decide_and_all_flagged_withholds_the_verdict():
    v = _verdict(Offsets([0.2, 4.0], flags={"c1": ["frame rate?"]}), 0.0)
    assert v["verdict"] == "absorbed" and v["flagged_conditions"] == ["c1"] and "1 of 2" in v["note"]
    assert v["conditions"]["c1"]["data_flags"] == ["frame rate?"] and v["conditions"]["c1"]["fitted_error"] == 4.0
    v = _verdict(Offsets([0.2, 4.0], flags={"c0": ["a"], "c1": ["b"]}), 0.0)
    assert v["verdict"] == "unvalidated" and "worst_fitted_error" not in v and "every held-out" in v["note"]
