"""Sub-pixel centres of shaded and flat blobs (detectors.centroid) against the disc's true centre."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from detectors.blob import BlobDetector, MarkerColor
from detectors.centroid import chroma_centre, unmixed_centre

ORANGE, WALL = np.array([20.0, 110.0, 235.0]), np.array([96.0, 124.0, 155.0])  # BGR: skin_wall's ball and wall
SS = 8  # supersampling: each pixel averages SS × SS samples (an anti-aliased edge)


def disc(cx: float, cy: float, r: float, colour: np.ndarray, background: np.ndarray, lit: bool,
         noise: float = 1.0, seed: int = 0, size: int = 80) -> np.ndarray:
    """A ball's image: a disc on a flat background, Lambertian-shaded by a light up and to the left
    when ``lit`` (a dark limb on the lower right), with Gaussian noise."""
    g = (np.arange(size * SS) + 0.5) / SS
    X, Y = np.meshgrid(g, g)
    dx, dy = (X - cx) / r, (Y - cy) / r
    inside = dx**2 + dy**2 < 1
    nz = np.sqrt(np.clip(1 - dx**2 - dy**2, 0, 1))
    light = np.array([-0.5, -0.5, 0.7]) / np.linalg.norm([-0.5, -0.5, 0.7])
    shade = np.clip(dx * light[0] + dy * light[1] + nz * light[2], 0, 1) * 0.75 + 0.25 if lit else np.ones_like(dx)
    img = np.where(inside[..., None], shade[..., None] * colour, background)
    img = img.reshape(size, SS, size, SS, 3).mean((1, 3))
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).round().astype(np.uint8)


def centre_of(img: np.ndarray, shaded: bool) -> tuple[float, float]:
    mk = replace(MarkerColor(name="ball", h_lo=5, h_hi=25, s_min=150, v_min=100), shaded=shaded)
    found = BlobDetector([mk]).detect(img)
    assert found, "the ball was not found"
    return found[0].u, found[0].v


def errors(lit: bool, shaded: bool, background: np.ndarray = WALL) -> np.ndarray:
    rng = np.random.default_rng(7)
    out = []
    for seed in range(20):
        cx, cy = 40 + rng.uniform(-0.5, 0.5), 40 + rng.uniform(-0.5, 0.5)
        u, v = centre_of(disc(cx, cy, 14.0, ORANGE, background, lit, seed=seed), shaded)
        out.append(np.hypot(u - cx + 0.5, v - cy + 0.5))  # OpenCV's pixel centres sit at integers
    return np.array(out)


def test_a_lit_ball_s_centre_is_unmixed_from_the_wall():
    """A lit orange ball (its limb darker, below the range's V floor) on a wall of nearby hue: the
    chroma-weighted centroid leans toward the light; the unmixed centre is within 0.3 px of truth."""
    chroma, unmixed = errors(lit=True, shaded=False), errors(lit=True, shaded=True)
    assert np.median(unmixed) < 0.3 and np.median(chroma) > 2 * np.median(unmixed), (chroma, unmixed)


@pytest.mark.parametrize("shaded", [False, True])
def test_a_flat_ball_is_centred_by_either_model(shaded):
    assert np.max(errors(lit=False, shaded=shaded)) < 0.15


def test_on_a_dark_background_the_unmixing_gives_way_to_chroma():
    """Near-black background: shading and coverage cannot be told apart by colour, so the shaded
    model returns the chroma centre, to the last bit."""
    img = disc(40.2, 39.7, 12.0, ORANGE, np.array([8.0, 8.0, 8.0]), lit=True)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    mk = MarkerColor("ball", 5, 25, 150, 60)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mk.mask(hsv), connectivity=8)
    i = int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) + 1
    box = tuple(int(b) for b in stats[i, :4])
    assert unmixed_centre(labels, i, img, hsv, box, mk) == chroma_centre(labels, i, img, hsv, box, mk)


def _plain_chroma_centre(labels, i, bgr, hsv, box, mk) -> tuple[float, float]:
    """The chroma-weighted centroid written as plainly as numpy allows (the reference the fast
    :func:`chroma_centre` must equal to the bit)."""
    x, y, w, h = box
    H, W = labels.shape
    x0, y0, x1, y1 = max(x - 3, 0), max(y - 3, 0), min(x + w + 3, W), min(y + h + 3, H)
    comp = (labels[y0:y1, x0:x1] == i).astype(np.uint8)
    region = cv2.dilate(comp, np.ones((5, 5), np.uint8)).astype(bool)
    patch = bgr[y0:y1, x0:x1]
    c = patch.max(axis=2).astype(np.float32) - patch.min(axis=2)
    hue = hsv[y0:y1, x0:x1, 0].astype(int)
    lo, hi = (mk.h_lo - 5) % 180, (mk.h_hi + 5) % 180
    hue_ok = (hue >= lo) & (hue <= hi) if lo <= hi else (hue >= lo) | (hue <= hi)
    floor = mk.s_min * mk.v_min / 255.0 * 0.5
    inside = c[comp.astype(bool)]
    full = max(float(np.quantile(inside, 0.2)) - floor, 1.0) if inside.size else 1.0
    wts = np.where(region & hue_ok, np.clip((c - floor) / full, 0.0, 1.0), 0.0)
    s = wts.sum()
    if s <= 0:
        ys, xs = np.nonzero(comp)
        return float(xs.mean() + x0), float(ys.mean() + y0)
    xs, ys = np.arange(x0, x0 + wts.shape[1])[None, :], np.arange(y0, y0 + wts.shape[0])[:, None]
    return float((wts * xs).sum() / s), float((wts * ys).sum() / s)


@pytest.mark.parametrize("seed", range(6))
def test_chroma_centre_is_the_plain_formula_to_the_bit(seed):
    """Noisy discs of random colours, sizes and places (cut by the frame's edge too), each against
    its hue range (red's wrapping one included): the same centre, bit for bit, as the plain formula."""
    rng = np.random.default_rng(seed)
    for _ in range(20):
        rgb = rng.integers(0, 256, 3)
        mk = MarkerColor.from_rgb("m", tuple(int(v) for v in rgb))
        cx, cy, r = rng.uniform(-5, 85), rng.uniform(-5, 85), rng.uniform(2, 15)
        img = disc(cx, cy, r, rgb[::-1].astype(float), rng.uniform(0, 255, 3), lit=bool(seed % 2),
                   noise=float(rng.uniform(0, 25)), seed=seed)
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
        mask = mk.mask(hsv)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        for i in range(1, n):
            box = tuple(int(v) for v in stats[i, :4])
            assert chroma_centre(labels, i, img, hsv, box, mk) == _plain_chroma_centre(labels, i, img, hsv, box, mk)
