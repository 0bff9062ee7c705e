"""pipeline.core.io's CSV reader across its parsing blocks: a long table reads as a short one does."""

from __future__ import annotations

import numpy as np
import pytest

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
