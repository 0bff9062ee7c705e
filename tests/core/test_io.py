"""pipeline.core.io's CSV reader across its parsing blocks: a long table reads as a short one does."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.core import io
from pipeline.core.errors import StereotrackError


def test_csv_blocks_read_as_one_table(tmp_path, monkeypatch):
    """Numbers, a column that turns out to be text only in a later block (kept as text from its
    first row, as written), blank lines, and an error's line number counted across blocks."""
    monkeypatch.setattr(io, "CSV_BLOCK", 7)
    path = tmp_path / "t.csv"
    lines = [f"{k},m{k % 3},{k / 4:g},0{k}" for k in range(30)]
    lines[20] = "20,m2,5,note"
    path.write_text("frame,marker,x,ref\n" + "\n".join(lines[:10]) + "\n\n" + "\n".join(lines[10:]) + "\n")
    cols = io.read_csv(path)
    np.testing.assert_array_equal(cols["frame"], np.arange(30.0))
    np.testing.assert_array_equal(cols["x"], np.arange(30) / 4)
    assert list(cols["ref"][:3]) == ["00", "01", "02"] and cols["ref"][20] == "note"
    assert cols["marker"].dtype == object and cols["marker"][29] == "m2"
    with pytest.raises(StereotrackError, match="line 23: column 'ref' is not a number"):  # the blank line counts
        io.read_csv(path, numeric=["ref"])
    with pytest.raises(StereotrackError, match=r"line 13: column 'x' is empty"):
        path.write_text("frame,x\n" + "".join(f"{k},{k}\n" for k in range(11)) + "11,\n")
        io.read_csv(path, finite=["x"])


def test_an_attempt_s_folder_names_its_final_one(tmp_path):
    from pipeline.core.outputs import final_folder, partial_folder

    final = tmp_path / "out" / "clip.v2"
    attempt = partial_folder(final, "0123456789ab")
    assert attempt.name == ".clip.v2.partial-0123456789ab" and final_folder(attempt) == final
    assert final_folder(final) == final and final_folder(tmp_path / ".hidden") == tmp_path / ".hidden"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.integers(0, 6), floats=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=18, max_size=18),
       ints=st.lists(st.integers(-10**12, 10**12), min_size=6, max_size=6),
       names=st.lists(st.text(max_size=6), min_size=6, max_size=6))
def test_a_table_written_by_columns_is_the_one_written_by_rows(tmp_path, rows, floats, ints, names):
    """``write_csv_columns`` (the estimates' writer) gives ``write_csv``'s bytes: floats to 10
    digits with NaN, ±inf and −0, integers and booleans as integers, names quoted as CSV needs."""
    f = np.array(floats[: 3 * rows], dtype=float).reshape(3, rows) if rows else np.zeros((3, 0))
    i = np.array(ints[:rows], dtype=np.int64)
    b = np.arange(rows) % 2 == 0
    n = names[:rows]
    io.write_csv(tmp_path / "rows.csv", ["a", "b", "c", "i", "flag", "name"],
                 [(*f[:, k], i[k], b[k], n[k]) for k in range(rows)])
    io.write_csv_columns(tmp_path / "cols.csv", ["a", "b", "c", "i", "flag", "name"], [*f, i, b, n])
    assert (tmp_path / "cols.csv").read_bytes() == (tmp_path / "rows.csv").read_bytes()


_CELLS = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-10**6, 10**6).map(str),
                   st.sampled_from(["", " 2.5 ", "nan", "-0", "1e-320", "x", "0", "7", "a b", "1,2", '"q"']),
                   st.text(alphabet="ab 1.-", max_size=4))


def _plain_read(path, text_columns) -> dict[str, np.ndarray]:
    """The reader as first written, cell by cell: what ``read_csv`` must still return."""
    import csv

    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh)]
    header, body = [h.strip() for h in rows[0]], [r for r in rows[1:] if r]
    out = {}
    for i, name in enumerate(header):
        values = [r[i].strip() if i < len(r) else "" for r in body]
        try:
            out[name] = (np.array(values, dtype=object) if name in text_columns
                         else np.array([float(v) if v != "" else np.nan for v in values], dtype=float))
        except ValueError:
            out[name] = np.array(values, dtype=object)
    return out


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.lists(_CELLS, min_size=0, max_size=6), max_size=12), block=st.integers(1, 5))
def test_the_reader_reads_any_table_as_cell_by_cell_parsing_does(tmp_path, monkeypatch, rows, block):
    """Short rows (missing cells empty), long rows (extra cells ignored), blank rows, spaces around
    values, empty cells, text in a later block, names that look like numbers in a name column (the
    group of identical markers ``0`` stays ``"0"``, as its marker does): every column as the plain
    cell-by-cell reading gives it, bit for bit, across parsing blocks."""
    import csv

    monkeypatch.setattr(io, "CSV_BLOCK", block)
    path = tmp_path / "t.csv"
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([[" frame", "marker", "group", "x", "y"], *rows])
    got, want = io.read_csv(path), _plain_read(path, io.TEXT_COLUMNS)
    assert got.keys() == want.keys()
    for name, w in want.items():
        g = got[name]
        assert g.dtype == w.dtype, name
        if w.dtype == object:
            assert list(g) == list(w), name
        else:
            assert g.tobytes() == w.tobytes(), name  # NaN and −0 included
    if rows and any(len(r) > 2 for r in rows):
        assert got["group"].dtype == object
