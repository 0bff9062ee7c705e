"""Scenarios: built-ins validate, truth is deterministic, bad values get errors naming field and file."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.errors import ScenarioError
from renderers.motion import simulate_truth
from renderers.scenario import builtin_scenarios, load_scenario, parse_scenario
from renderers.truth import project_truth

REQUIRED = {"receding", "maneuvering", "accelerating", "sine", "four_point", "multi_marker"}


def test_builtins_present_and_valid():
    names = set(builtin_scenarios())
    assert names >= REQUIRED
    multi = load_scenario("multi_marker")
    colors = set(multi.marker_colors().values())
    assert len(multi.marker_names()) >= 3 and len(colors) >= 3


@pytest.mark.parametrize("name", sorted(REQUIRED))
def test_builtin_markers_visible(name):
    s = load_scenario(name)
    truth = simulate_truth(s)
    proj = project_truth(s.rig.build(), s, truth)
    # every marker is visible in both cameras for most of the clip
    assert proj.visible.mean(axis=0).min() > 0.8


def test_same_seed_same_truth_bit_for_bit():
    s = load_scenario("maneuvering")
    a, b = simulate_truth(s), simulate_truth(s)
    assert a.positions.tobytes() == b.positions.tobytes()
    assert a.velocities.tobytes() == b.velocities.tobytes()
    c = simulate_truth(s.with_overrides(seed=s.seed + 1))
    assert not np.array_equal(a.positions, c.positions)


def test_motion_models_match_their_equations():
    s = load_scenario("accelerating")
    tr = simulate_truth(s)
    m = s.objects[0].motion
    t = tr.t[-1]
    expected = np.array(m.start) + np.array(m.velocity) * t + 0.5 * np.array(m.acceleration) * t * t
    np.testing.assert_allclose(tr.positions[-1, 0], expected)
    # velocities are the derivative of positions (central differences)
    sine = simulate_truth(load_scenario("sine"))
    dp = (sine.positions[2:, 0] - sine.positions[:-2, 0]) / (2 * load_scenario("sine").dt)
    np.testing.assert_allclose(dp, sine.velocities[1:-1, 0], atol=5e-3)


def test_four_point_target_geometry():
    s = load_scenario("four_point")
    tr = simulate_truth(s)
    tgt = tr.targets[0]
    p = tr.positions[:, :4]
    R = s.objects[0].motion.radius
    # 1–3 and 2–4 are 2R apart, centred on the plate centre
    np.testing.assert_allclose(np.linalg.norm(p[:, 0] - p[:, 2], axis=1), 2 * R)
    np.testing.assert_allclose(np.linalg.norm(p[:, 1] - p[:, 3], axis=1), 2 * R)
    np.testing.assert_allclose((p[:, 0] + p[:, 2]) / 2, tgt.center, atol=1e-12)
    # point 1 recedes by R sin(alpha): the SPEC's y1 = f R cos a / (z + R sin a)
    np.testing.assert_allclose(p[:, 0, 2], tgt.distance + R * np.sin(tgt.alpha))
    # alpha follows the closed loop of the paper: it decays towards 0
    assert abs(tgt.alpha[-1]) < abs(tgt.alpha[0]) / 2


def _base(**over) -> dict:
    d = {
        "objects": [{"name": "m", "motion": {"type": "constant_velocity", "start": [0, 0, 2], "velocity": [0, 0, 0]}}]
    }
    d.update(over)
    return d


@pytest.mark.parametrize(
    ("data", "field"),
    [
        (_base(frames=0), "frames"),
        (_base(frames=-5), "frames"),
        ({"objects": [{"name": "m", "radius": -0.1, "motion": {"type": "constant_velocity", "start": [0, 0, 2],
                                                                 "velocity": [0, 0, 0]}}]}, "objects.0.radius"),
        ({"objects": [{"name": "m", "motion": {"type": "teleport"}}]}, "objects.0.motion"),
        ({"objects": [{"name": "t", "motion": {"type": "four_point_target", "radius": -1}}]}, "radius"),
        (_base(rig={"focal": -3}), "rig.focal"),
        (_base(fps=0), "fps"),
        (_base(bogus=1), "bogus"),
    ],
)
def test_bad_values_name_field_and_file(tmp_path, data, field):
    import yaml

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert str(path) in msg and field in msg


def test_not_yaml_and_missing_file(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("objects: [unclosed\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(path)
    with pytest.raises(ScenarioError, match="no such scenario"):
        load_scenario(tmp_path / "missing.yaml")


def test_marker_never_in_view_warns_not_fatal(tmp_path):
    from renderers.render import render_clip

    data = _base(frames=3)
    data["objects"].append(
        {"name": "behind", "color": [30, 200, 40],
         "motion": {"type": "constant_velocity", "start": [0, 0, -3], "velocity": [0, 0, 0]}}
    )
    with pytest.warns(UserWarning, match="'behind' is never visible"):
        res = render_clip(parse_scenario(data), tmp_path / "clip", fmt="png", workers=1)
    assert res.warnings and (tmp_path / "clip" / "truth.csv").is_file()


def test_clip_description_written_and_derived_alike(tmp_path):
    """A rendered clip's clip.json says what its scenario.yaml says (fps, markers and colours, the
    target); without clip.json the clip is footage like any other (its markers must be given)."""
    import json
    import shutil

    from pipeline.core.clip import Clip
    from renderers.scenario import clip_description, load_scenario
    from tests.conftest import REPO

    for name in ("sample_small", "four_point_small"):
        clip = tmp_path / name
        shutil.copytree(REPO / "data" / "clips" / name, clip)
        written = Clip(clip).info
        derived = json.loads(json.dumps(clip_description(load_scenario(clip / "scenario.yaml"))))
        assert written == derived and written["markers"]
        (clip / "clip.json").unlink()
        assert Clip(clip).info == {}
        (clip / "clip.json").write_text(json.dumps(written))
    assert Clip(tmp_path / "four_point_small").info["target"]["radius"] > 0


def test_groups_of_identical_markers():
    """Markers of one colour form a group named after it; a `group:` names it; a group whose
    markers differ in colour, or named like a marker, is one error naming the file."""
    from pipeline.core.errors import StereotrackError
    from renderers.scenario import clip_description

    def obj(name, color, group=None):
        o = {"name": name, "color": color, "motion": {"type": "constant_velocity", "start": [0, 0, 2], "velocity": [0, 0, 0]}}
        return {**o, "group": group} if group else o

    base = {"frames": 10, "rig": {"width": 640, "height": 480, "focal": 600, "baseline": 0.3}}
    same = parse_scenario({**base, "objects": [obj("a", [240, 150, 20]), obj("b", [240, 150, 20]), obj("c", [20, 150, 240])]})
    groups = {m["name"]: m["group"] for m in clip_description(same)["markers"]}
    assert groups == {"a": "rgb_f09614", "b": "rgb_f09614", "c": None}
    named = parse_scenario({**base, "objects": [obj("a", [240, 150, 20], "balls"), obj("b", [240, 150, 20], "balls")]})
    assert {m["group"] for m in clip_description(named)["markers"]} == {"balls"}
    with pytest.raises(StereotrackError, match=r"x.yaml: .*group 'g' have different colours"):
        parse_scenario({**base, "objects": [obj("a", [240, 150, 20], "g"), obj("b", [20, 150, 240], "g")]}, "x.yaml")
    with pytest.raises(StereotrackError, match=r"group 'a' is also a marker's name"):
        parse_scenario({**base, "objects": [obj("a", [240, 150, 20], "a")]}, "x.yaml")
