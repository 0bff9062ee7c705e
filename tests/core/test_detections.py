"""detections.csv's columns as the estimate stage takes them (pipeline.core.detections): a group's
blobs per frame and camera, with the detect stage's ``merged`` flag beside them."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.detections import split_groups
from pipeline.core.errors import StereotrackError


def _cols(merged: list | None) -> dict[str, np.ndarray]:
    cols = {"frame": np.array([0, 0, 0, 1, 1]), "camera": np.array(["left", "left", "right", "left", "right"], dtype=object),
            "marker": np.array(["g", "g", "g", "g", "red"], dtype=object),
            "u": np.array([10.0, 20.0, 11.0, 12.0, 5.0]), "v": np.array([1.0, 2.0, 1.0, 1.0, 5.0]),
            "score": np.ones(5), "area": np.full(5, 30.0)}
    if merged is not None:
        cols["merged"] = np.array(merged, dtype=object if any(isinstance(m, str) for m in merged) else float)
    return cols


def test_merged_flags_sit_beside_each_groups_blobs():
    singles, groups, flags = split_groups(_cols([0, 1, 0, 1, 0]), 2, "detections.csv")
    assert list(groups) == ["g"] and list(singles) == ["red"]
    np.testing.assert_array_equal(groups["g"][0][0], [[10.0, 1.0], [20.0, 2.0]])
    assert flags["g"][0][0].tolist() == [False, True] and flags["g"][0][1].tolist() == [False]
    assert flags["g"][1][0].tolist() == [True] and flags["g"][1][1].tolist() == []


def test_without_the_column_no_blob_is_merged():
    _, groups, flags = split_groups(_cols(None), 2, "detections.csv")
    assert [len(f) for f in flags["g"][0]] == [len(d) for d in groups["g"][0]] == [2, 1]
    assert not any(f.any() for frame in flags["g"] for f in frame)


@pytest.mark.parametrize("bad", [[0, 2, 0, 0, 0], [0, "yes", 0, 0, 0]])
def test_a_merged_value_other_than_0_or_1_names_its_line(bad):
    with pytest.raises(StereotrackError, match=r"detections.csv: line 3: merged must be 0 or 1"):
        split_groups(_cols(bad), 2, "detections.csv")
