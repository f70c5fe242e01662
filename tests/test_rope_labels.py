"""A motion-capture tracker's label exchanges and ghost samples on a rope of identical markers: undone or read as
missing, never a refused file or a silent change of the event (labels.repair_length). Truth: the same recording
without the artefact (newton's flick cut to 12 markers with 0.5 mm noise; MuJoCo's throw from the test data)."""
from pathlib import Path

import numpy as np
import pytest

from wrenorm.errors import InputError
from wrenorm.tasks.rope.reference.events import critical
from wrenorm.tasks.rope.reference.generate import builtin_reference_path, load_reference, reference_arrays

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """newton's flick at 12 markers with 0.5 mm noise: (arrays, the loaded reference, its critical moment)."""
    d = dict(np.load(builtin_reference_path("flick")))
    idx = np.round(np.linspace(0, d["markers"].shape[1] - 1, 12)).astype(int)
    d["markers"] = d["markers"][:, idx] + np.random.default_rng(5).normal(0.0, 5e-4, (len(d["time"]), 12, 3))
    d["marker_arclength"] = d["marker_arclength"][idx]
    f = tmp_path_factory.mktemp("labels") / "clean.npz"
    np.savez(f, **d)
    ref = load_reference(f)
    c = critical(ref)
    assert c.event is not None and c.event.confidence == "high" and not c.warnings
    return d, ref, c


def _load(tmp_path, d, markers, name="edited.npz"):
    f = tmp_path / name
    np.savez(f, **(d | {"markers": markers}))
    ref = load_reference(f)
    return ref, critical(ref)


def _exchanged(markers, k, i, j, back=None):
    m = markers.copy()
    m[k:back, [i, j]] = m[k:back, [j, i]]
    return m


@pytest.mark.parametrize("i, j, offset, back", [
    (4, 9, 0.05, None),  # far apart along the rope, after the contact (a knot forming), kept to the end
    (4, 9, -0.1, None),  # the same before the contact
    (7, 8, -0.05, None),  # neighbours
    (10, 11, -0.1, None),  # the free end's marker and its neighbour: only one interval breaks
    (5, 6, -0.2, 3),  # exchanged for three frames, then back
])
def test_exchanged_labels_are_read_back_in_order(tmp_path, clean, i, j, offset, back):
    """Before stop 48 each of these refused the whole file as "wrong units or wrong length?"."""
    d, ref, c = clean
    k = int(np.searchsorted(d["time"], c.event.time + offset))
    got, gc = _load(tmp_path, d, _exchanged(d["markers"], k, i, j, None if back is None else k + back))
    assert [(t, a, b) for t, a, b in got.label_swaps][:1] == [(pytest.approx(d["time"][k]), i, j)]
    assert len(got.label_swaps) == (1 if back is None else 2)
    assert got.missing is None  # the exchange showed at once: nothing needed guessing
    np.testing.assert_array_equal(got.markers, ref.markers)
    assert gc.event.time == c.event.time and gc.event.confidence == "high"
    assert any(f"markers {i} and {j} exchanged labels at {d['time'][k]:.4f} s" in w for w in gc.warnings)


def test_an_exchange_between_the_touching_pieces_is_said(tmp_path, clean):
    """Labels exchanged where the two pieces touch (markers 5 and 11 are a centimetre apart) show only as they part:
    the frame of the exchange is found from the paths' smoothness and read as missing, so the event is flagged
    (bridged markers bound the contact; the bridged time here 6 ms early, within two frames)."""
    d, ref, c = clean
    k = int(np.searchsorted(d["time"], c.event.time))
    got, gc = _load(tmp_path, d, _exchanged(d["markers"], k, 5, 11))
    assert [(a, b) for _, a, b in got.label_swaps] == [(5, 11)] and got.label_swaps[0][0] == pytest.approx(d["time"][k])
    seen = ~got.missing
    np.testing.assert_array_equal(got.markers[seen], ref.markers[seen])
    assert gc.event.flagged and abs(gc.event.time - c.event.time) < 0.01


@pytest.mark.parametrize("marker, offset, jump", [(7, 0.1, (0.3, 0, 0)), (3, -0.2, (0, 0.2, 0)),
                                                  (11, -0.3, (0, 0, 0.4))])
def test_a_ghost_sample_is_read_as_missing(tmp_path, clean, marker, offset, jump):
    d, ref, c = clean
    k = int(np.searchsorted(d["time"], c.event.time + offset))
    m = d["markers"].copy()
    m[k, marker] += jump
    got, gc = _load(tmp_path, d, m)
    assert got.length_broken == 1 and got.missing.sum() == 1 and got.missing[k, marker]
    assert abs(gc.event.time - c.event.time) < 1e-9 and gc.event.confidence == "high"
    assert any("1 of them farther from their neighbours than the rope between them is long" in w for w in gc.warnings)


@pytest.mark.parametrize("factor", [0.8, 0.85])
def test_a_length_too_short_is_still_refused(tmp_path, clean, factor):
    """What breaks the length in most frames is no tracker's doing: the file is refused, naming how often."""
    d, _, _ = clean
    f = tmp_path / "short.npz"
    np.savez(f, **(d | {"length": d["length"] * factor, "mass": d["mass"] * factor}))
    with pytest.raises(InputError) as e:
        load_reference(f)
    assert e.value.field == "markers" and "wrong units, wrong length" in e.value.problem
    assert "in 100% of the frames" in e.value.problem


def test_an_exchange_on_mujocos_rope(tmp_path):
    """The same on the rope the rule was not developed on (MuJoCo's rod, the test data's throw)."""
    ref = load_reference(DATA / "mujoco_default_flick_fast.npz")
    c = critical(ref)
    data = reference_arrays(ref)
    M = data["markers"].shape[1]
    k = int(np.searchsorted(ref.time, c.event.time - 0.15))
    i, j = M // 3, 2 * M // 3
    got, gc = _load(tmp_path, data, _exchanged(data["markers"], k, i, j))
    assert [(a, b) for _, a, b in got.label_swaps] == [(i, j)]
    np.testing.assert_allclose(got.markers, ref.markers, atol=1e-12)
    assert gc.event.time == pytest.approx(c.event.time, abs=1e-9) and gc.event.confidence == c.event.confidence
