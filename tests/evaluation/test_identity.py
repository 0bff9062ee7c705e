"""The identity metrics (pipeline.evaluation.identity) equal independent implementations on shared
fixtures: CLEAR MOT and IDF1 as py-motmetrics computes them, HOTA as TrackEval's reference code
does, GOSPA as a brute force over every assignment; and each metric moves the right way on a
deliberately broken tracker (two ids swapped for a while, a track dropped, a false track)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pipeline.evaluation import identity

THRESHOLD = 0.2  # m: a track within 20 cm of a marker matches it


def fixture(seed: int, n: int = 80, markers: int = 4) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Truth of ``markers`` markers (each present for a stretch) and a tracker's output with noise,
    an identity swap, a fragmented track, a coasting track that drifts, and a false track."""
    rng = np.random.default_rng(seed)
    t = np.arange(n)[:, None] * 0.03
    truth = {}
    for i in range(markers):
        X = np.array([0.3 * i, 0.0, 3.0]) + np.hstack([np.sin(t + i), np.cos(0.7 * t + i), 0.2 * t]) * 0.4
        a, b = sorted(rng.integers(0, n, 2))
        X[: max(0, a - 10)] = np.nan
        X[min(n, b + 40):] = np.nan
        truth[f"m{i}"] = X
    tracks = {f"t{i}": X + rng.normal(0, 0.03, X.shape) for i, X in enumerate(truth.values())}
    s = int(rng.integers(10, n - 20))
    tracks["t0"][s : s + 10], tracks["t1"][s : s + 10] = tracks["t1"][s : s + 10].copy(), tracks["t0"][s : s + 10].copy()
    seen = np.flatnonzero(np.isfinite(truth["m2"]).all(axis=1))
    f = int(seen[len(seen) // 3])  # inside the marker's stretch
    tracks["t2"][f : f + 6] = np.nan  # a fragment
    tracks["t2"][f + 6 : f + 9] += 0.5  # then off by half a metre (a miss and a false positive)
    tracks["false"] = np.full((n, 3), np.nan)
    tracks["false"][5:25] = np.array([2.0, 2.0, 5.0]) + rng.normal(0, 0.05, (20, 3))
    return truth, tracks


def motmetrics_reference(truth: dict, tracks: dict) -> dict[str, float]:
    mm = pytest.importorskip("motmetrics", reason="py-motmetrics comes with the test extra")
    _, _, seq = identity.frames(truth, tracks)
    acc = mm.MOTAccumulator(auto_id=True)
    for f in seq:
        acc.update(f.truth.tolist(), f.tracks.tolist(), np.where(f.distance < THRESHOLD, f.distance, np.nan))
    names = ["mota", "motp", "num_switches", "num_fragmentations", "num_misses", "num_false_positives", "idf1", "idp",
             "idr"]
    row = mm.metrics.create().compute(acc, metrics=names, name="x").iloc[0]
    return {k: float(row[k]) for k in names}


def trackeval_hota(truth: dict, tracks: dict, d0: float) -> dict[str, float]:
    trackeval = pytest.importorskip("trackeval", reason="TrackEval comes with the test extra")
    gt_names, tr_names, seq = identity.frames(truth, tracks)
    data = {"gt_ids": [f.truth for f in seq], "tracker_ids": [f.tracks for f in seq],
            "similarity_scores": [np.maximum(0.0, 1.0 - f.distance / d0) for f in seq],
            "num_gt_dets": sum(len(f.truth) for f in seq), "num_tracker_dets": sum(len(f.tracks) for f in seq),
            "num_gt_ids": len(gt_names), "num_tracker_ids": len(tr_names)}
    res = trackeval.metrics.HOTA().eval_sequence(data)
    return {"hota": float(np.mean(res["HOTA"])), "deta": float(np.mean(res["DetA"])), "assa": float(np.mean(res["AssA"]))}


@pytest.mark.parametrize("seed", range(6))
def test_clear_mot_and_idf1_equal_motmetrics(seed):
    truth, tracks = fixture(seed)
    ours = identity.identity_metrics(truth, tracks, THRESHOLD)
    ref = motmetrics_reference(truth, tracks)
    pairs = {"mota": "mota", "motp_m": "motp", "id_switches": "num_switches", "fragmentations": "num_fragmentations",
             "misses": "num_misses", "false_positives": "num_false_positives", "idf1": "idf1", "idp": "idp", "idr": "idr"}
    for mine, theirs in pairs.items():
        assert ours[mine] == pytest.approx(ref[theirs], abs=1e-9, rel=1e-9), (mine, ours[mine], ref[theirs])
    assert ours["id_switches"] >= 1 and ours["fragmentations"] >= 1 and ours["false_positives"] >= 20


@pytest.mark.parametrize("seed", range(6))
def test_hota_equals_trackeval(seed):
    truth, tracks = fixture(seed)
    ours = identity.identity_metrics(truth, tracks, THRESHOLD, d0=0.15)
    ref = trackeval_hota(truth, tracks, 0.15)
    for k in ("hota", "deta", "assa"):
        assert ours[k] == pytest.approx(ref[k], abs=1e-9), k


def brute_gospa(X: np.ndarray, Y: np.ndarray, c: float, p: float = 2.0) -> float:
    """GOSPA (α = 2) of two small point sets by trying every assignment."""
    best = np.inf
    m, n = len(X), len(Y)
    for k in range(min(m, n) + 1):
        for xs in itertools.combinations(range(m), k):
            for ys in itertools.permutations(range(n), k):
                cost = sum(min(np.linalg.norm(X[a] - Y[b]), c) ** p for a, b in zip(xs, ys, strict=True))
                best = min(best, cost + c**p / 2 * (m + n - 2 * k))
    return best ** (1 / p)


@pytest.mark.parametrize("seed", range(4))
def test_gospa_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    truth = {f"m{i}": rng.normal(0, 0.3, (12, 3)) for i in range(3)}
    tracks = {f"t{i}": rng.normal(0, 0.3, (12, 3)) for i in range(4)}
    for table in (truth, tracks):
        for v in table.values():
            v[rng.random(12) < 0.3] = np.nan
    _, _, seq = identity.frames(truth, tracks)
    want = []
    for k in range(12):
        X = np.array([v[k] for v in truth.values() if np.isfinite(v[k]).all()]).reshape(-1, 3)
        Y = np.array([v[k] for v in tracks.values() if np.isfinite(v[k]).all()]).reshape(-1, 3)
        want.append(brute_gospa(X, Y, 0.4))
    assert identity.gospa(seq, 0.4)["gospa_m"] == pytest.approx(np.mean(want), abs=1e-12)


def test_every_metric_sees_a_broken_tracker():
    """Swapping two ids for 15 frames, then dropping a track, then adding a false one: each step
    makes every metric it concerns worse than the perfect tracker's."""
    truth, _ = fixture(0)
    perfect = {f"t{i}": v.copy() for i, v in enumerate(truth.values())}
    swapped = {k: v.copy() for k, v in perfect.items()}
    swapped["t0"][30:45], swapped["t1"][30:45] = perfect["t1"][30:45], perfect["t0"][30:45]
    dropped = {k: v for k, v in swapped.items() if k != "t3"}
    false = {**dropped, "ghost": np.full_like(perfect["t0"], 4.0)}
    m = [identity.identity_metrics(truth, t, THRESHOLD) for t in (perfect, swapped, dropped, false)]
    assert m[0]["mota"] == 1.0 and m[0]["idf1"] == 1.0 and m[0]["hota"] == pytest.approx(1.0) and m[0]["id_switches"] == 0
    assert m[0]["gospa_m"] == 0.0
    overlap = any(np.isfinite(perfect["t0"][k]).all() and np.isfinite(perfect["t1"][k]).all() for k in range(30, 45))
    if overlap:
        assert m[1]["id_switches"] >= 1 and m[1]["idf1"] < m[0]["idf1"] and m[1]["assa"] < m[0]["assa"]
        assert m[1]["mota"] < 1.0 and m[1]["deta"] == pytest.approx(m[0]["deta"])
    assert m[2]["misses"] > m[1]["misses"] and m[2]["mota"] < m[1]["mota"] and m[2]["deta"] < m[1]["deta"]
    assert m[2]["gospa_m"] > m[1]["gospa_m"]
    assert m[3]["false_positives"] > m[2]["false_positives"] and m[3]["idp"] < m[2]["idp"]
    assert m[3]["hota"] < m[2]["hota"] and m[3]["gospa_m"] > m[2]["gospa_m"]


def test_switch_events_follow_the_matched_marker():
    """A track's identity switches, frame by frame, from the marker it follows: a gap (following
    none) is no switch; taking another marker after it is."""
    assert identity.switches_of(["", "m1", "m1", "", "m1", "m2", "m2", "", "m0"]) == [(5, "m1", "m2"), (8, "m2", "m0")]
    truth, _ = fixture(0)
    tracks = {"t0": truth["m0"].copy()}
    tracks["t0"][60:] = truth["m1"][60:]  # the track jumps to another marker (both are present there)
    _, names = identity.matched_truth(truth, tracks)
    assert names["t0"][45] == "m0" and identity.switches_of(names["t0"]) == [(60, "m0", "m1")]
