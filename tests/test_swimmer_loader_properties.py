"""Property-based: a folder of fishsim-format files with malformed or extreme contents gives
rates or an InputError naming the file — never another exception, never a hang."""
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wrenorm.errors import InputError
from wrenorm.tasks.swimmer.data import load_dir

values = st.floats(allow_nan=True, allow_infinity=True, width=32)


@st.composite
def marker_tables(draw):
    rows = draw(st.integers(0, 140))
    cols = draw(st.sampled_from([18, 18, 18, 17, 2, 0]))
    base = draw(st.sampled_from(["walk", "const", "random"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    if base == "walk":  # plausible pixel tracks
        data = 1000 + np.cumsum(rng.normal(size=(rows, cols)), axis=0) + np.tile(np.arange(cols) * 20.0, (rows, 1))
    elif base == "const":
        data = np.full((rows, cols), draw(values))
    else:
        data = rng.normal(scale=draw(st.sampled_from([1e-6, 1.0, 1e6, 1e30])), size=(rows, cols))
    if rows and cols and draw(st.booleans()):
        data[draw(st.integers(0, rows - 1)), draw(st.integers(0, cols - 1))] = draw(values)
    return data


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(table=marker_tables(), name=st.sampled_from(["markers_f1_00.csv", "rotatedMarkers_f1_00.csv"]))
def test_load_dir_gives_rates_or_input_error(tmp_path, table, name):
    folder = tmp_path / "d"
    folder.mkdir(exist_ok=True)
    for f in folder.iterdir():
        f.unlink()
    np.savetxt(folder / name, table, delimiter=",") if table.size else (folder / name).write_text("")
    try:
        rates = load_dir(folder)
    except InputError as e:
        assert name in str(e) or str(folder) in str(e)
        return
    for r in rates:
        assert np.isfinite(r.speed) and np.isfinite(r.tail_freq)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.binary(max_size=400))
def test_binary_garbage(tmp_path, blob):
    folder = tmp_path / "g"
    folder.mkdir(exist_ok=True)
    (folder / "markers_f0_50.csv").write_bytes(blob)
    try:
        load_dir(folder)
    except InputError as e:
        assert "markers_f0_50.csv" in str(e)
