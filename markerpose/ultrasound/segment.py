"""Semi-automatic segmentation of a tube's outer wall through a sweep, and of a wire target.

"Semi": the user gives one seed, a point inside the tube on the first frame. Each frame is
searched along rays from the current centre; the centre then follows the tube from frame
to frame. Only rays near the beam axis are used (above and below the centre): there a
smooth surface returns a specular echo whose peak marks the interface; at the sides the
echo drops out and the wall's speckle would bias the boundary inward.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RingSearch:
    """Settings of :func:`ring_points`.

    Attributes:
        min_radius_mm, max_radius_mm: search range from the centre.
        sector_deg: half-width of the sectors around straight up and straight down.
        n_rays: rays per frame (split between the two sectors).
        smooth_px: Gaussian smoothing of the image before the search, px. Kept small: an
            echo lies between dark water and the brighter speckle of the wall, and
            smoothing pulls its peak toward the wall (inward).
        level: an echo counts when it rises this fraction of the way from the frame's
            background (median) to its brightest 0.1 %.
        max_shift_mm: a frame whose fitted centre moves more than this from the previous
            one is not trusted to move the centre (it keeps the previous one).
    """

    min_radius_mm: float = 2.0
    max_radius_mm: float = 12.0
    sector_deg: float = 40.0
    n_rays: int = 60
    smooth_px: float = 0.5
    level: float = 0.5
    max_shift_mm: float = 3.0


def _fit_circle(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Algebraic least-squares circle through (N, 2) points: (centre, radius)."""
    if len(p) < 3:
        return None
    A = np.column_stack([2 * p, np.ones(len(p))])
    b = (p**2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:2]
    r2 = sol[2] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return c, float(np.sqrt(r2))


def _outer_peaks(prof: np.ndarray, thr: float) -> np.ndarray:
    """Per row of ``prof`` (rays × radius samples): the radius (in samples) of the outermost
    local maximum above ``thr``, refined by a quadratic over ±3 samples; NaN if none."""
    n, m = prof.shape
    out = np.full(n, np.nan)
    core = prof[:, 1:-1]
    is_max = (core >= prof[:, :-2]) & (core > prof[:, 2:]) & (core >= thr)
    for i in range(n):
        ks = np.flatnonzero(is_max[i]) + 1
        if not len(ks):
            continue
        k = ks[-1]
        if k < 3 or k > m - 4:
            continue
        x = np.arange(-3, 4)
        a, b, _ = np.polyfit(x, prof[i, k - 3 : k + 4], 2)
        off = -b / (2 * a) if a < 0 else 0.0
        out[i] = k + float(np.clip(off, -1.5, 1.5))
    return out


def ring_points(image: np.ndarray, center_px, spacing, search: RingSearch | None = None):
    """Points on the outer surface of a tube in one B-mode frame.

    Args:
        image: uint8 (H, W) B-mode frame.
        center_px: (u, v) a point inside the tube (pixels).
        spacing: (sx, sy) mm per pixel.
        search: settings.
    Returns:
        (points, center): (N, 2) sub-pixel points (u, v) on the outer echo, and the
        centre of the circle through them (pixels; the input centre if too few points).
    """
    s = search or RingSearch()
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"expected a gray (H, W) image, got shape {img.shape}")
    g = cv2.GaussianBlur(img.astype(np.float32), (0, 0), s.smooth_px)
    sx, sy = float(spacing[0]), float(spacing[1])
    c = np.asarray(center_px, dtype=np.float64)
    step_mm = min(sx, sy) / 4
    r = np.arange(s.min_radius_mm, s.max_radius_mm, step_mm)
    half = s.n_rays // 2
    sec = np.deg2rad(s.sector_deg)
    phis = np.concatenate(
        [np.linspace(np.pi / 2 - sec, np.pi / 2 + sec, half), np.linspace(-np.pi / 2 - sec, -np.pi / 2 + sec, s.n_rays - half)]
    )
    mx = (c[0] + np.cos(phis)[:, None] * r[None, :] / sx).astype(np.float32)
    my = (c[1] + np.sin(phis)[:, None] * r[None, :] / sy).astype(np.float32)
    prof = cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    bg = float(np.median(g))
    top = float(np.percentile(g, 99.9))
    thr = bg + s.level * (top - bg)
    k = _outer_peaks(prof, thr)
    ok = np.isfinite(k)
    rr = s.min_radius_mm + k[ok] * step_mm
    pts = np.column_stack([c[0] + np.cos(phis[ok]) * rr / sx, c[1] + np.sin(phis[ok]) * rr / sy])
    fit = _fit_circle(pts * [sx, sy])
    if fit is None:
        return pts, c
    cc, rad = fit
    resid = np.abs(np.linalg.norm(pts * [sx, sy] - cc, axis=1) - rad)
    keep = resid < max(3 * 1.4826 * np.median(resid), 0.2)
    pts = pts[keep]
    fit = _fit_circle(pts * [sx, sy])
    if fit is None:
        return pts, c
    new_c = fit[0] / [sx, sy]
    if np.hypot(*((new_c - c) * [sx, sy])) > s.max_shift_mm:
        return pts, c
    return pts, new_c


def sweep_points(images, seed_px, spacing, search: RingSearch | None = None, progress: bool = False):
    """:func:`ring_points` through a sweep, the centre carried from frame to frame.

    Returns a list of (N_i, 2) point arrays, one per frame (empty where none was found).
    """
    c = np.asarray(seed_px, dtype=np.float64)
    out = []
    it = images
    if progress:
        from tqdm import tqdm

        it = tqdm(images, desc="segment", unit="frame", leave=False)
    for im in it:
        pts, c = ring_points(im, c, spacing, search)
        out.append(pts)
    return out


def point_target(image: np.ndarray, smooth_px: float = 1.0, dynamic_range_db: float = 55.0, max_size_px: int = 40) -> np.ndarray | None:
    """Sub-pixel position (u, v) of the brightest compact echo (a wire crossing): the
    amplitude-weighted centroid of the connected bright region around the maximum, the
    8-bit log image mapped back to amplitude with ``dynamic_range_db``. None when nothing
    stands out from the background, or when the brightest echo is not compact (wider or
    taller than ``max_size_px``: a surface, not a wire)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"expected a gray (H, W) image, got shape {img.shape}")
    g = cv2.GaussianBlur(img.astype(np.float32), (0, 0), smooth_px)
    bg = float(np.median(g))
    _, peak, _, (u, v) = cv2.minMaxLoc(g)
    if peak - bg < 0.25 * (255 - bg):
        return None
    thr = bg + 0.6 * (peak - bg)
    _, lab = cv2.connectedComponents((g >= thr).astype(np.uint8))
    m = lab == lab[v, u]
    ys, xs = np.nonzero(m)
    if np.ptp(xs) >= max_size_px or np.ptp(ys) >= max_size_px:
        return None
    # The image is log-compressed: weight by amplitude above the threshold, not by dB.
    w = 10 ** ((g[ys, xs] - thr) * dynamic_range_db / (255.0 * 20.0)) - 1 + 1e-9
    return np.array([np.sum(w * xs) / w.sum(), np.sum(w * ys) / w.sum()])


__all__ = ["RingSearch", "point_target", "ring_points", "sweep_points"]
