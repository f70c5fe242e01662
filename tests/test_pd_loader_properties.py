"""Property-based: whatever bytes a user hands the PD log loader, it answers with a log or an
InputError naming the file — never another exception, never a hang."""
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wrenorm.errors import InputError
from wrenorm.tasks.pd.problem import LOG_COLUMNS, load_log

finite = st.floats(allow_nan=True, allow_infinity=True, width=64)
cells = st.one_of(finite.map(repr), st.text(max_size=6), st.just(""), st.just("1e400"))


@st.composite
def csv_texts(draw):
    header = draw(st.one_of(st.just(list(LOG_COLUMNS)), st.permutations(list(LOG_COLUMNS)),
                            st.lists(st.sampled_from(["time", "q", "q_d", "qd_d", "x", ""]), max_size=6)))
    n = draw(st.integers(0, 60))
    rows = []
    for i in range(n):
        if draw(st.booleans()):
            rows.append([repr(i * 0.01)] + [repr(draw(st.floats(-10, 10))) for _ in header[1:]])
        else:
            rows.append(draw(st.lists(cells, min_size=0, max_size=len(header) + 1)))
    return "\n".join(",".join(r) for r in [header] + rows)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=csv_texts())
def test_loader_gives_log_or_input_error(tmp_path, text):
    f = tmp_path / "log.csv"
    f.write_text(text)
    try:
        log = load_log(f)
    except InputError as e:
        assert str(f) in str(e)
        return
    assert len(log.time) >= 20 and np.all(np.diff(log.time) > 0)
    assert all(np.all(np.isfinite(a)) for a in (log.q, log.q_d, log.qd_d))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.binary(max_size=300))
def test_loader_survives_binary_garbage(tmp_path, blob):
    f = tmp_path / "log.csv"
    f.write_bytes(blob)
    try:
        load_log(f)
    except InputError as e:
        assert str(f) in str(e)


def test_missing_and_directory(tmp_path):
    for path in (tmp_path / "nope.csv", tmp_path):
        try:
            load_log(path)
        except InputError as e:
            assert "file" in str(e)
        else:
            raise AssertionError("no error")
