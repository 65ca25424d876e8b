"""Cluttered backgrounds with distractors, as reflectance images in [0, 1].

A detector must use the three-ring layout, not just "a dark ring": so the
clutter includes dark disks, single rings with the marker's own inner/outer
ratio, lines, rectangles, low-frequency texture and skin-toned blobs.
"""

from __future__ import annotations

import cv2
import numpy as np


def clutter_background(
    size: tuple[int, int],
    rng: np.random.Generator,
    n_shapes: int | None = None,
    ring_distractors: int | None = None,
    ring_ratio: float = 0.4,
    scale: float | None = None,
) -> np.ndarray:
    """Random cluttered background.

    Args:
        size: (width, height) in pixels.
        rng: the random generator (the only source of randomness).
        n_shapes: number of rectangles/lines/blobs (None → random 10..40).
        ring_distractors: number of single rings and dark disks (None → random 0..6).
        ring_ratio: inner/outer diameter ratio of the ring distractors (the marker's, by default).
        scale: size of the shapes relative to a 1280 px wide frame (None: width / 1280, i.e.
            the image is a whole frame; 1 for a full-resolution crop of a frame).
    Returns:
        (H, W) float32 reflectance in [0, 1].
    """
    w, h = size
    # Low-frequency base: a smooth random field around a random mean grey.
    small = rng.uniform(0, 1, (max(2, h // 128), max(2, w // 128))).astype(np.float32)
    base = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    mean = rng.uniform(0.15, 0.6)
    img = np.clip(mean + 0.25 * (base - 0.5), 0, 1).astype(np.float32)
    n_shapes = int(rng.integers(10, 41)) if n_shapes is None else n_shapes
    scale = w / 1280.0 if scale is None else scale
    for _ in range(n_shapes):
        kind = rng.integers(0, 4)
        g = float(rng.uniform(0.0, 0.95))
        if kind == 0:  # rectangle
            x, y = rng.uniform(0, w), rng.uniform(0, h)
            bw, bh = rng.uniform(20, 300) * scale, rng.uniform(20, 300) * scale
            box = ((x, y), (bw, bh), rng.uniform(0, 180))
            pts = cv2.boxPoints(box).astype(np.int32)
            cv2.fillConvexPoly(img, pts, g, lineType=cv2.LINE_AA)
        elif kind == 1:  # line (cables, edges)
            p0 = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
            p1 = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
            cv2.line(img, p0, p1, g, int(rng.integers(1, 12)), lineType=cv2.LINE_AA)
        elif kind == 2:  # blob (hands-like, skin-toned reflectance)
            c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
            axes = (int(rng.uniform(20, 160) * scale) + 1, int(rng.uniform(10, 80) * scale) + 1)
            cv2.ellipse(img, c, axes, rng.uniform(0, 180), 0, 360, float(rng.uniform(0.3, 0.6)), -1, cv2.LINE_AA)
        else:  # textured patch
            x0, y0 = int(rng.uniform(0, w - 10)), int(rng.uniform(0, h - 10))
            pw, ph = int(rng.uniform(30, 250) * scale) + 2, int(rng.uniform(30, 250) * scale) + 2
            x1, y1 = min(w, x0 + pw), min(h, y0 + ph)
            tex = rng.uniform(0, 1, (y1 - y0, x1 - x0)).astype(np.float32)
            tex = cv2.GaussianBlur(tex, (0, 0), float(rng.uniform(0.7, 3)))
            img[y0:y1, x0:x1] = np.clip(g + 0.8 * (tex - tex.mean()), 0, 1)
    n_rings = int(rng.integers(0, 7)) if ring_distractors is None else ring_distractors
    for _ in range(n_rings):
        c = (float(rng.uniform(0, w)), float(rng.uniform(0, h)))
        r = rng.uniform(20, 80) * scale
        ax = (r, r * rng.uniform(0.5, 1.0))
        ang = rng.uniform(0, 180)
        dark = float(rng.uniform(0.0, 0.1))
        cv2.ellipse(img, (c, (2 * ax[0], 2 * ax[1]), ang), dark, -1, cv2.LINE_AA)
        if rng.uniform() < 0.7:  # a single ring; otherwise a dark disk
            cv2.ellipse(img, (c, (2 * ax[0] * ring_ratio, 2 * ax[1] * ring_ratio), ang), float(rng.uniform(0.7, 0.9)), -1, cv2.LINE_AA)
    return np.clip(img, 0, 1)
