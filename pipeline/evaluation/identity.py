"""Identity metrics of a multi-target tracker against the truth, in 3-D: CLEAR MOT (MOTA, MOTP,
identity switches, fragmentations; Bernardin & Stiefelhagen 2008), the identity scores IDF1, IDP
and IDR (Ristani et al. 2016), HOTA with DetA and AssA (Luiten et al. 2021) and GOSPA
(Rahmathullah, García-Fernández & Svensson 2017). Pure functions of two tables of positions:
truth marker → frames × 3 and track → frames × 3, NaN where a marker or a track is absent.

Conventions (stated once, used by every figure): a track and a marker *match* in a frame when their
3-D distance is below ``threshold`` (CLEAR MOT, IDF1); HOTA's similarity is ``max(0, 1 − d/d0)``
(similarity 1 at zero distance, 0 at ``d0`` and beyond) averaged over the localisation thresholds
α = 0.05, 0.10, …, 0.95; GOSPA takes p = 2, α = 2 and a cut-off ``c``, and its switching penalty
counts a track whose matched marker changes between frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    from scipy import optimize
else:  # imported on first use: only clips of identical markers are scored by identity
    optimize = lazy_module("scipy.optimize")

#: HOTA's localisation thresholds (Luiten et al. 2021, §5): 0.05, 0.10, …, 0.95
HOTA_ALPHAS = np.arange(0.05, 0.99, 0.05)


@dataclass
class Frame:
    """One frame: the truth markers and the tracks present (indices into the clip's lists of names)
    and their 3-D distances (markers × tracks)."""

    truth: np.ndarray
    tracks: np.ndarray
    distance: np.ndarray


def frames(truth: dict[str, np.ndarray], tracks: dict[str, np.ndarray]) -> tuple[list[str], list[str], list[Frame]]:
    """(marker names, track names, per-frame :class:`Frame`) over the frames either table covers;
    a marker or track is present in a frame where its position is finite."""
    gt_names, tr_names = list(truth), list(tracks)
    n = max([len(v) for v in (*truth.values(), *tracks.values())], default=0)
    G = _stack(truth, gt_names, n)
    T = _stack(tracks, tr_names, n)
    out = []
    for k in range(n):
        g = np.flatnonzero(np.isfinite(G[:, k]).all(axis=1))
        t = np.flatnonzero(np.isfinite(T[:, k]).all(axis=1))
        d = np.linalg.norm(G[g, k][:, None, :] - T[t, k][None, :, :], axis=2) if len(g) and len(t) \
            else np.zeros((len(g), len(t)))
        out.append(Frame(g, t, d))
    return gt_names, tr_names, out


def _stack(table: dict[str, np.ndarray], names: list[str], n: int) -> np.ndarray:
    out = np.full((len(names), n, 3), np.nan)
    for i, name in enumerate(names):
        v = np.asarray(table[name], dtype=float)
        out[i, : len(v)] = v[:n]
    return out


# -- CLEAR MOT ------------------------------------------------------------------------------------


def clear_mot(seq: list[Frame], threshold: float) -> dict[str, float]:
    """CLEAR MOT (Bernardin & Stiefelhagen 2008, §2.1): each frame keeps every marker's last
    correspondence whose marker and track are both present and closer than ``threshold``, then
    assigns the rest by minimum total distance (Hungarian); a marker matched to another track than
    the last it was matched to is an identity switch, a marker's matched stretch interrupted by
    frames it was present but unmatched a fragmentation. MOTA = 1 − (misses + false positives +
    switches) / truth objects; MOTP = mean distance of the matches (m)."""
    last: dict[int, int] = {}  # marker → the track it was last matched to
    matched_before: dict[int, bool] = {}  # marker → matched in the last frame it was present
    n_gt = misses = fps = switches = frags = 0
    dist_sum, n_match = 0.0, 0
    for f in seq:
        pairs = _clear_pairs(f, last, threshold)
        gt_matched = {g for g, _ in pairs}
        for g, t in pairs:
            if g in last and last[g] != t:
                switches += 1
            if matched_before.get(g) is False:
                frags += 1
            last[g] = t
            dist_sum += f.distance[list(f.truth).index(g), list(f.tracks).index(t)]
        for g in f.truth:
            if g not in gt_matched and g in last:
                matched_before[g] = False
            elif g in gt_matched:
                matched_before[g] = True
        n_gt += len(f.truth)
        n_match += len(pairs)
        misses += len(f.truth) - len(pairs)
        fps += len(f.tracks) - len(pairs)
    return {"mota": 1.0 - (misses + fps + switches) / n_gt if n_gt else float("nan"),
            "motp_m": dist_sum / n_match if n_match else float("nan"), "id_switches": switches,
            "fragmentations": frags, "misses": misses, "false_positives": fps, "matches": n_match, "truth_objects": n_gt}


def _clear_pairs(f: Frame, last: dict[int, int], threshold: float) -> list[tuple[int, int]]:
    """This frame's (marker, track) matches: the last correspondences kept where still valid, the
    rest by Hungarian on the distances below ``threshold``."""
    gi = {int(g): i for i, g in enumerate(f.truth)}
    ti = {int(t): j for j, t in enumerate(f.tracks)}
    pairs: list[tuple[int, int]] = []
    for g in gi:
        t = last.get(g)
        if t is not None and t in ti and not any(t == u for _, u in pairs) and f.distance[gi[g], ti[t]] < threshold:
            pairs.append((g, t))
    used_g, used_t = {g for g, _ in pairs}, {t for _, t in pairs}
    rows = [i for g, i in gi.items() if g not in used_g]
    cols = [j for t, j in ti.items() if t not in used_t]
    if rows and cols:
        D = f.distance[np.ix_(rows, cols)]
        big = 1e9
        cost = np.where(D < threshold, D, big)
        r, c = optimize.linear_sum_assignment(cost)
        pairs += [(int(f.truth[rows[a]]), int(f.tracks[cols[b]])) for a, b in zip(r, c, strict=True) if cost[a, b] < big]
    return pairs


# -- IDF1 -----------------------------------------------------------------------------------------


def identity_scores(seq: list[Frame], n_gt: int, n_tr: int, threshold: float) -> dict[str, float]:
    """IDF1, IDP and IDR (Ristani et al. 2016, §4): one marker ↔ track correspondence for the whole
    clip, chosen to maximise the frames where the pair lies within ``threshold`` (IDTP), by a
    bipartite matching in which a marker or a track may stay unmatched."""
    common = np.zeros((n_gt, n_tr))
    gt_len, tr_len = np.zeros(n_gt), np.zeros(n_tr)
    for f in seq:
        gt_len[f.truth] += 1
        tr_len[f.tracks] += 1
        close = f.distance < threshold
        if close.any():
            i, j = np.nonzero(close)
            np.add.at(common, (f.truth[i], f.tracks[j]), 1)
    # cost of pairing a marker with a track: the frames either has alone (FN + FP of the pair);
    # of leaving each unmatched: all its frames (the usual square formulation with dummies)
    big = np.full((n_gt + n_tr, n_tr + n_gt), 0.0)
    big[:n_gt, :n_tr] = gt_len[:, None] + tr_len[None, :] - 2 * common
    big[:n_gt, n_tr:] = np.where(np.eye(n_gt, dtype=bool), gt_len[:, None], 1e12)
    big[n_gt:, :n_tr] = np.where(np.eye(n_tr, dtype=bool), tr_len[None, :], 1e12)
    r, c = optimize.linear_sum_assignment(big)
    idtp = sum(common[a, b] for a, b in zip(r, c, strict=True) if a < n_gt and b < n_tr)
    total_gt, total_tr = gt_len.sum(), tr_len.sum()
    idp = idtp / total_tr if total_tr else float("nan")
    idr = idtp / total_gt if total_gt else float("nan")
    idf1 = 2 * idtp / (total_gt + total_tr) if total_gt + total_tr else float("nan")
    return {"idf1": float(idf1), "idp": float(idp), "idr": float(idr), "idtp": float(idtp)}


# -- HOTA -----------------------------------------------------------------------------------------


def hota(seq: list[Frame], n_gt: int, n_tr: int, d0: float, alphas: np.ndarray = HOTA_ALPHAS) -> dict[str, float]:
    """HOTA, DetA and AssA (Luiten et al. 2021, eqs. 1–9), each averaged over ``alphas``, with the
    similarity ``max(0, 1 − d/d0)``: per frame, detections are matched by Hungarian on the global
    alignment score times the similarity; at each α a match counts where its similarity is at least
    α; ``AssA`` is the mean over true positives of each pair's association IoU."""
    sims = [np.maximum(0.0, 1.0 - f.distance / d0) for f in seq]
    potential = np.zeros((n_gt, n_tr))
    gt_count, tr_count = np.zeros((n_gt, 1)), np.zeros((1, n_tr))
    for f, s in zip(seq, sims, strict=True):
        denom = s.sum(0)[None, :] + s.sum(1)[:, None] - s
        iou = np.zeros_like(s)
        ok = denom > np.finfo(float).eps
        iou[ok] = s[ok] / denom[ok]
        potential[f.truth[:, None], f.tracks[None, :]] += iou
        gt_count[f.truth] += 1
        tr_count[0, f.tracks] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        align = potential / (gt_count + tr_count - potential)
    tp, fn, fp = np.zeros(len(alphas)), np.zeros(len(alphas)), np.zeros(len(alphas))
    matches = np.zeros((len(alphas), n_gt, n_tr))
    for f, s in zip(seq, sims, strict=True):
        if not len(f.truth) or not len(f.tracks):
            fn += len(f.truth)
            fp += len(f.tracks)
            continue
        r, c = optimize.linear_sum_assignment(-(align[f.truth[:, None], f.tracks[None, :]] * s))
        for a, alpha in enumerate(alphas):
            keep = s[r, c] >= alpha - np.finfo(float).eps
            tp[a] += keep.sum()
            fn[a] += len(f.truth) - keep.sum()
            fp[a] += len(f.tracks) - keep.sum()
            matches[a, f.truth[r[keep]], f.tracks[c[keep]]] += 1
    ass = np.array([np.sum(m * (m / np.maximum(1, gt_count + tr_count - m))) / max(1.0, t)
                    for m, t in zip(matches, tp, strict=True)])
    det = tp / np.maximum(1.0, tp + fn + fp)
    h = np.sqrt(det * ass)
    return {"hota": float(h.mean()), "deta": float(det.mean()), "assa": float(ass.mean()), "d0_m": d0}


# -- GOSPA ----------------------------------------------------------------------------------------


def gospa(seq: list[Frame], c: float, p: float = 2.0, switch: float | None = None) -> dict[str, float]:
    """GOSPA per frame (Rahmathullah, García-Fernández & Svensson 2017, eq. 5, α = 2): the optimal
    assignment of tracks to markers with distances cut off at ``c``, each unassigned marker or track
    costing ``c^p / 2``; ``(Σ min(d, c)^p + c^p/2 · (missed + false))^(1/p)``. Returned: the mean over
    frames, its localisation, missed and false parts (mean of the p-th powers), and with ``switch``
    (default ``c / √2`` per half switch, as in the trajectory metric of Rahmathullah et al. 2016)
    a switching penalty counting, per frame, the tracks whose assigned marker changed."""
    switch = c / np.sqrt(2.0) if switch is None else switch
    total, loc, missed, false, switches = [], 0.0, 0.0, 0.0, 0
    prev: dict[int, int] = {}
    for f in seq:
        cost = np.minimum(f.distance, c) ** p
        r, col = optimize.linear_sum_assignment(cost) if cost.size else (np.array([], int), np.array([], int))
        keep = cost[r, col] < c**p  # a pair at the cut-off is no better than a miss and a false track
        r, col = r[keep], col[keep]
        lo = float(cost[r, col].sum())
        miss, fa = len(f.truth) - len(r), len(f.tracks) - len(r)
        now = {int(f.tracks[b]): int(f.truth[a]) for a, b in zip(r, col, strict=True)}
        switches += sum(1 for t, g in now.items() if t in prev and prev[t] != g)
        prev.update(now)
        loc += lo
        missed += c**p / 2 * miss
        false += c**p / 2 * fa
        total.append((lo + c**p / 2 * (miss + fa)) ** (1 / p))
    n = max(len(seq), 1)
    return {"gospa_m": float(np.mean(total)) if total else float("nan"), "localisation": loc / n, "missed": missed / n,
            "false": false / n, "switches": switches, "switch_cost": switch**p * switches / n, "c_m": c, "p": p}


#: the match threshold the pipeline states (m): CLEAR MOT, IDF1, HOTA's zero-similarity distance and
#: GOSPA's cut-off, and the truth-to-track matching a group's 3-D errors are measured through
MATCH_M = 0.25


def matched_truth(truth: dict[str, np.ndarray], tracks: dict[str, np.ndarray], threshold: float = MATCH_M
                  ) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """Each track's truth: per frame the position of the marker CLEAR MOT matches it to (NaN where
    none), so a track's 3-D error is measured against the marker it follows in that frame and an
    identity switch shows up as an error, not as a silent relabel; and that marker's name per frame
    (``""`` where none)."""
    gt_names, tr_names, seq = frames(truth, tracks)
    n = len(seq)
    out = {t: np.full((n, 3), np.nan) for t in tr_names}
    names = {t: [""] * n for t in tr_names}
    last: dict[int, int] = {}
    for k, f in enumerate(seq):
        for g, t in _clear_pairs(f, last, threshold):
            out[tr_names[t]][k] = truth[gt_names[g]][k]
            names[tr_names[t]][k] = gt_names[g]
            last[g] = t
    return out, names


def switches_of(follows: list[str]) -> list[tuple[int, str, str]]:
    """The frames at which a track starts to follow another marker than the last it followed:
    ``(frame, was, now)`` — its identity switches, frames it follows none left out."""
    out, last = [], ""
    for k, name in enumerate(follows):
        if name and last and name != last:
            out.append((k, last, name))
        last = name or last
    return out


def identity_metrics(truth: dict[str, np.ndarray], tracks: dict[str, np.ndarray], threshold: float,
                     d0: float | None = None, c: float | None = None) -> dict[str, float]:
    """Every identity metric of ``tracks`` against ``truth`` (see the module docstring), with the
    match ``threshold`` (m), HOTA's zero-similarity distance ``d0`` and GOSPA's cut-off ``c``
    (both default to ``threshold``)."""
    gt_names, tr_names, seq = frames(truth, tracks)
    d0, c = d0 or threshold, c or threshold
    out: dict[str, float] = {"threshold_m": threshold}
    out.update(clear_mot(seq, threshold))
    out.update(identity_scores(seq, len(gt_names), len(tr_names), threshold))
    out.update(hota(seq, len(gt_names), len(tr_names), d0))
    out.update(gospa(seq, c))
    return out
