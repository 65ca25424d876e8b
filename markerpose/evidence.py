"""Ring evidence: how much the image around a triple of ring centres looks like the
printed marker (dark bands on one evenly lit white plate). An appearance gate used by
single-view detection, the transfer fallback and the ``verify`` decoding."""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from .geometry import layout_affine
from .marker import Marker

_MARKER = Marker()  # the default marker


def _evidence_points(marker: Marker) -> dict:
    """Where :func:`ring_evidence` looks, in the marker's frame (mm): per ring, circles of
    16 points inside the white centre, across the black band and just outside the ring;
    and a grid on the plate away from every ring (plate white)."""
    R, r = marker.outer_radius, marker.inner_radius
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    unit = np.stack([np.cos(ang), np.sin(ang)], 1)
    c = marker.centers2d

    def circles(*radii):  # (3, 16 * len(radii), 2)
        return np.concatenate([c[:, None, :] + rho * unit[None] for rho in radii], 1)

    x0, y0, x1, y1 = marker.plate
    inset, step = 0.4 * R, 0.4 * R
    gx, gy = np.meshgrid(np.arange(x0 + inset, x1 - inset + 1e-9, step), np.arange(y0 + inset, y1 - inset + 1e-9, step))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    far = np.min(np.linalg.norm(grid[:, None] - c[None], axis=2), axis=1) >= 1.4 * R
    return {
        "inner": np.concatenate([c[:, None, :], circles(0.35 * r)], 1),
        "band": circles(r + 0.3 * (R - r), r + 0.7 * (R - r)),
        "outside": circles(1.3 * R),
        "plate": grid[far],
    }


_EVIDENCE = {}  # marker → its evidence points (computed once per marker geometry)


def ring_evidence(image: np.ndarray, triples: np.ndarray, marker: Marker | None = None) -> np.ndarray:
    """How much the image around each triple of ring centres looks like the printed marker.

    Each triple (c0, c1, c2) fixes the affine map from the marker's layout to the image
    (near enough to the perspective one over a marker), so the image is sampled where the
    marker would be: the plate away from the rings, each ring's black band, its white
    centre and the plate just outside it. The marker shows black bands on one evenly lit
    white plate, and paper of the plate's brightness inside and around every ring; three
    ring-like things that merely lie in a marker-like triangle (decoys, clutter) fail some
    of these. Samples outside the image are left out; the plate's brightness is a plane
    fitted to its samples (:func:`_plate_level`: light falls off smoothly), evaluated at
    each ring. The product of four factors, each in [0, 1]:

    - band contrast: sqrt of the smallest ring's (plate - band) / plate and
      (outside - band) / outside;
    - plate evenness: 1 - (10-90 % spread of the plate's residuals to its plane) / plate;
    - no ring brighter inside than the plate: 1 - 2 max((centre - plate) / plate);
    - the plate's level right outside every ring: 1 - max |outside - plate| / plate.

    Args:
        image: (H, W) float32 in [0, 1] (the network input, or any resolution the
            triples are in).
        triples: (T, 3, 2) ring centres c0, c1, c2 in that image's pixels.
        marker: the marker's geometry (default: the default marker).
    Returns:
        (T,) evidence in [0, 1].
    """
    marker = marker or _MARKER
    key = (tuple(marker.centers2d.ravel()), marker.outer_radius, marker.inner_radius, marker.plate)
    if key not in _EVIDENCE:
        _EVIDENCE[key] = _evidence_points(marker)
    zones = _EVIDENCE[key]
    P = np.asarray(triples, np.float64).reshape(-1, 3, 2)
    L = marker.centers2d
    A = layout_affine(P, L)
    t = P[:, 0] - A @ L[0]
    img = np.ascontiguousarray(image, np.float32)
    h, w = img.shape

    def sample(pts):  # pts (..., 2) mm → (T, ...) image values, NaN outside the image
        q = np.einsum("tij,...j->t...i", A, pts) + t.reshape((-1,) + (1,) * (pts.ndim - 1) + (2,))
        flat = q.reshape(len(P), -1, 2).astype(np.float32)
        v = cv2.remap(img, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inside = (flat[..., 0] >= 0) & (flat[..., 0] <= w - 1) & (flat[..., 1] >= 0) & (flat[..., 1] <= h - 1)
        return np.where(inside, v, np.nan).reshape(q.shape[:-1])

    eps = 2.0 / 255  # a couple of grey levels: dark images are not divided by ~0
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN medians: rings cut by the border
        band = np.nanmedian(sample(zones["band"]), axis=2)  # (T, 3)
        inner = np.nanmedian(sample(zones["inner"]), axis=2)
        outside = np.nanmedian(sample(zones["outside"]), axis=2)
        level, spread = _plate_level(sample(zones["plate"]), zones["plate"], L, np.nanmedian(outside, axis=1), eps)
        contrast = np.minimum((level - band) / (level + eps), (outside - band) / (outside + eps)).min(1)
        factors = [
            np.sqrt(np.clip(contrast, 0, 1)),
            1 - spread,
            1 - 2 * np.clip((inner - level) / (level + eps), 0, None).max(1),
            1 - (np.abs(outside - level) / (level + eps)).max(1),
        ]
    return np.prod([np.clip(np.nan_to_num(f, nan=0.0), 0, 1) for f in factors], axis=0)


def _plate_level(values: np.ndarray, pts: np.ndarray, centers: np.ndarray, fallback: np.ndarray, eps: float, min_points: int = 8):
    """The plate's brightness at each ring and its unevenness, from plate samples.

    Light falls off smoothly across a plate (a gradient, vignetting), so a plane in the
    marker's coordinates is fitted to the samples inside the image (NaN elsewhere):
    its value at each ring centre is that ring's plate level, and the 10-90 % spread of
    the residuals over the plane's value at the samples' centroid (+ ``eps``) is the
    unevenness (clutter is uneven, paper is not). With fewer than ``min_points`` samples in the image the level is ``fallback``
    (e.g. the rings' surroundings) and the unevenness 0.

    Args:
        values: (T, K) samples; pts: (K, 2) where they are, mm; centers: (3, 2) mm;
        fallback: (T,); eps: added to the level divided by.
    Returns:
        (level (T, 3), spread (T,)).
    """
    ok = np.isfinite(values)
    X = np.column_stack([np.ones(len(pts)), pts - pts.mean(0)])  # (K, 3)
    W = ok.astype(np.float64)
    M = np.einsum("tk,ki,kj->tij", W, X, X) + np.diag([1e-9, 1e-3, 1e-3]) * len(pts)  # slopes damped; no samples: solvable
    b = np.einsum("tk,ki,tk->ti", W, X, np.nan_to_num(values))
    coef = np.linalg.solve(M, b[..., None])[..., 0]  # (T, 3)
    level = np.column_stack([np.ones(3), centers - pts.mean(0)]) @ coef.T  # (3, T)
    resid = values - coef @ X.T
    lo, hi = np.nanpercentile(np.where(ok, resid, np.nan), [10, 90], axis=1)
    spread = (hi - lo) / (np.abs(coef[:, 0]) + eps)
    few = ok.sum(1) < min_points
    level = np.where(few[:, None], fallback[:, None], level.T)
    return level, np.where(few, 0.0, spread)



__all__ = ["ring_evidence"]
