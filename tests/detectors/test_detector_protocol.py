"""Every registered detector honours the role (detectors/base.py): on a rendered clip it finds each
marker within 1.5 px of its true projection in most frames, reports only known markers at most
once per frame, and after ``reset`` (a missing frame) finds them again."""

from __future__ import annotations

import numpy as np
import pytest

from detectors import create_detector, registry
from detectors.base import Detector
from detectors.blob import MarkerColor
from pipeline.core.clip import Clip
from pipeline.core.errors import StereotrackError
from pipeline.core.frames import StereoFrameSource


def test_registry_holds_the_built_in_detectors():
    assert {"blob", "meanshift", "camshift"} <= set(registry())
    assert all(issubclass(cls, Detector) and cls.name == name for name, cls in registry().items())
    with pytest.raises(StereotrackError, match="unknown detector 'nope'"):
        create_detector("nope", [MarkerColor.from_rgb("red", (230, 30, 30))])


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(registry()))
def test_detector_finds_the_markers(name, png_clip):
    clip = Clip(png_clip)
    truth = clip.truth_table()
    markers = [MarkerColor.from_rgb(m.name, m.rgb) for m in clip.markers]
    det = create_detector(name, markers)
    errs, frames = [], 0
    for fr in StereoFrameSource(png_clip):
        if fr.index == 12:
            det.reset()  # as after a missing frame
        found = det.detect(fr.left)
        names = [d.marker for d in found]
        assert len(names) == len(set(names)) and set(names) <= {m.name for m in markers}
        frames += 1
        for d in found:
            row = (truth["frame"] == fr.index) & (truth["marker"] == d.marker) & (truth["visible_left"] > 0)
            if row.any():
                errs.append(np.hypot(d.u - truth["u_left"][row][0], d.v - truth["v_left"][row][0]))
    visible = int(np.sum(truth["visible_left"] > 0))
    assert len(errs) >= 0.9 * visible, (len(errs), visible)
    assert np.median(errs) < 1.5, np.median(errs)


@pytest.mark.parametrize("name", [n for n, c in sorted(registry().items()) if not c.labels_targets])
def test_point_trackers_refuse_a_one_colour_target(name):
    with pytest.raises(StereotrackError, match="one point per colour"):
        create_detector(name, [MarkerColor.from_rgb("t", (200, 200, 30))], {"t": ["t_1", "t_2", "t_3", "t_4"]})


def test_plugins_register_through_the_entry_point(monkeypatch):
    """A package that names a Detector subclass under the ``stereotrack.detectors`` entry points adds
    it to the registry (as estimators do); an entry point that is no Detector is skipped, warned."""
    import importlib.metadata
    import types

    import detectors
    from detectors.base import _REGISTRY
    from detectors.blob_tracker import BlobTracker

    class Plugged(BlobTracker):
        """A plugin's detector."""

        name = "plugged"

    module = types.ModuleType("plugin_module")
    module.Plugged, module.NotOne = Plugged, object
    monkeypatch.setitem(__import__("sys").modules, "plugin_module", module)
    points = [importlib.metadata.EntryPoint("plugged", "plugin_module:Plugged", detectors.ENTRY_POINT_GROUP),
              importlib.metadata.EntryPoint("broken", "plugin_module:NotOne", detectors.ENTRY_POINT_GROUP)]
    monkeypatch.setattr("pipeline.core.plugins._entry_points", lambda: importlib.metadata.EntryPoints(points))
    monkeypatch.setattr(detectors, "_plugins_loaded", False)
    monkeypatch.setattr(detectors.base, "_REGISTRY", dict(_REGISTRY))
    monkeypatch.setattr(detectors, "_REGISTRY", detectors.base._REGISTRY)
    with pytest.warns(UserWarning, match="detector plugin 'broken'.*is not a detectors.base.Detector"):
        reg = detectors.registry()
    assert reg["plugged"] is Plugged and "broken" not in reg and next(iter(reg)) == "blob"
