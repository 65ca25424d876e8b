"""Ring evidence: how much the image around a triple of ring centres looks like the
printed marker. :func:`ring_evidence` (dark bands on white paper, each judged against
the paper right beside it) is the gate of single-view detection and of the transfer
fallback; :func:`plate_evidence` (dark bands on one evenly lit plate) weighs the stage-1
decoding's triples (``verify``)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from .edges import masked_median, masked_percentile
from .geometry import layout_affine
from .marker import Marker

_MARKER = Marker()  # the default marker
_ANGLES = 16  # samples around each circle


def _evidence_points(marker: Marker) -> dict:
    """Where :func:`ring_evidence` looks, in the marker's frame (mm).

    Per ring, circles of :data:`_ANGLES` points at the same angles: inside the white
    centre, twice across the black band and just outside the ring; a grid on the plate
    away from every ring, with its neighbouring pairs; and, for each point outside a
    ring, the nearest grid point when it is close (links from each ring to the plate)."""
    R, r = marker.outer_radius, marker.inner_radius
    ang = np.linspace(0, 2 * np.pi, _ANGLES, endpoint=False)
    unit = np.stack([np.cos(ang), np.sin(ang)], 1)
    c = marker.centers2d

    def circle(rho):  # (3, _ANGLES, 2)
        return c[:, None, :] + rho * unit[None]

    x0, y0, x1, y1 = marker.plate
    inset = step = 0.4 * R
    gx, gy = np.meshgrid(np.arange(x0 + inset, x1 - inset + 1e-9, step), np.arange(y0 + inset, y1 - inset + 1e-9, step))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    grid = grid[np.min(np.linalg.norm(grid[:, None] - c[None], axis=2), axis=1) >= 1.4 * R]
    d = np.linalg.norm(grid[:, None] - grid[None], axis=2)
    i, j = np.nonzero(np.triu((d > 0) & (d < 1.01 * step)))
    outside = circle(1.3 * R)
    to_grid = np.linalg.norm(outside[:, :, None] - grid[None, None], axis=3)  # (3, _ANGLES, G)
    return {
        "inner": circle(0.35 * r),
        "band": np.stack([circle(r + 0.3 * (R - r)), circle(r + 0.7 * (R - r))], 2),  # (3, _ANGLES, 2, 2)
        "outside": outside,
        "plate": grid,
        "pairs": (i, j),
        "nearest": to_grid.argmin(2),
        "linked": to_grid.min(2) < 0.8 * R,
    }


_EVIDENCE = {}  # marker → its evidence points (computed once per marker geometry)


def _zones(marker: Marker) -> dict:
    key = (tuple(marker.centers2d.ravel()), marker.outer_radius, marker.inner_radius, marker.plate)
    if key not in _EVIDENCE:
        _EVIDENCE[key] = _evidence_points(marker)
    return _EVIDENCE[key]


def ring_evidence(image: np.ndarray, triples: np.ndarray, marker: Marker | None = None, min_pairs: int = 8) -> np.ndarray:
    """How much the image around each triple of ring centres looks like the printed marker.

    Each triple (c0, c1, c2) fixes the affine map from the marker's layout to the image
    (near enough to the perspective one over a marker), so the image is sampled where the
    marker would be: each ring's white centre, its black band and the paper just outside
    it, and the plate away from the rings. Light on a real plate is anything but even
    (a hand's shadow, a lamp's gradient, a camera's response curve), so every test
    compares paper with the paper right beside it, never with the plate elsewhere:
    along each ray from a ring's centre the band is judged against the brighter of the
    centre and the outside (a shadow's edge crosses a ray once, so one of them shares
    the band's light), and the plate must be smooth from one sample to the next (a
    shadow's edge spoils only the few neighbours it separates, clutter most). Three
    ring-like things that merely lie in a marker-like triangle (decoys, clutter) fail
    some of these. Samples outside the image are left out (with fewer than ``min_pairs``
    neighbouring plate pairs in the image, the plate is not tested). The product of four factors,
    each in [0, 1], the worst ring deciding:

    - band contrast: median over rays of 1 - band / paper, with the brighter of two
      samples across the band (a triple in a wrong order or at a wrong scale puts one
      of them on paper);
    - plate smoothness: 1 - 4 x the 75th percentile of the relative step between
      neighbouring plate samples;
    - no ring brighter inside than just outside: 1 - 2 x median over rays of
      (centre - outside) / outside;
    - each ring on the plate: 1 - median relative step from the paper outside it to
      the nearest plate sample.

    Args:
        image: (H, W) float32 in [0, 1] (the network input, or any resolution the
            triples are in).
        triples: (T, 3, 2) ring centres c0, c1, c2 in that image's pixels.
        marker: the marker's geometry (default: the default marker).
    Returns:
        (T,) evidence in [0, 1].
    """
    marker = marker or _MARKER
    zones = _zones(marker)
    P = np.asarray(triples, np.float64).reshape(-1, 3, 2)
    L = marker.centers2d
    img = np.ascontiguousarray(image, np.float32)
    A = layout_affine(P, L)
    t = P[:, 0] - A @ L[0]

    def sample(pts):  # pts (..., 2) mm → (T, ...) image values, NaN outside the image
        return _sample(img, np.einsum("tij,...j->t...i", A, pts) + t.reshape((-1,) + (1,) * (pts.ndim - 1) + (2,)))

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN medians: rings cut by the border
        factors = _evidence_factors(sample, zones, min_pairs)
    return np.prod([np.clip(np.nan_to_num(f, nan=0.0), 0, 1) for f in factors], axis=0)


def _step(a, b):
    """The relative difference of two paper samples."""
    return np.abs(a - b) / (np.fmax(a, b) + _EPS)


def _evidence_factors(sample, zones: dict, min_pairs: int) -> list:
    """:func:`ring_evidence`'s four factors (T,) each (band contrast, plate smoothness, no
    ring brighter inside, each ring on the plate), NaN where undecided; ``sample`` maps
    marker points (..., 2) mm to image values (T, ...), NaN outside the image."""
    inner, outside, plate = sample(zones["inner"]), sample(zones["outside"]), sample(zones["plate"])  # (T, 3, A) ×2, (T, G)
    i, j = zones["pairs"]
    steps = _step(plate[:, i], plate[:, j])  # (T, pairs)
    rough = np.where(np.isfinite(steps).sum(1) >= min_pairs, _nanpercentile(steps, 75), 0.0)
    link = np.where(zones["linked"], _step(outside, plate[:, zones["nearest"]]), np.nan)
    off_plate = np.nan_to_num(np.nanmax(_nanmedian(link), axis=1), nan=0.0)  # no link in the image: no test
    return [
        # Band contrast along each ray: the brighter band sample against the brighter of core and outside.
        _nanmedian(1 - sample(zones["band"]).max(-1) / (np.fmax(inner, outside) + _EPS)).min(1),
        1 - 4 * rough,
        1 - 2 * np.clip(_nanmedian((inner - outside) / (outside + _EPS)), 0, None).max(1),
        1 - off_plate,
    ]


_EPS = 2.0 / 255  # a couple of grey levels: dark images are not divided by ~0


# numpy's nanmedian / nanpercentile over the last axis by compiled selection (numpy's
# NaN-aware statistics were most of the evidence's time); computed in float64, so a
# float32 percentile can differ from numpy's in its last bit.
def _nanmedian(x: np.ndarray) -> np.ndarray:
    return masked_median(x, ~np.isnan(x), empty=np.nan).astype(x.dtype)


def _nanpercentile(x: np.ndarray, q: float) -> np.ndarray:
    return masked_percentile(x, ~np.isnan(x), q, empty=np.nan).astype(x.dtype)


def _sample(img: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at image points ``q`` (..., 2); NaN outside the image."""
    h, w = img.shape
    flat = q.reshape(-1, 2).astype(np.float32)
    n, cols = len(flat), 4096  # remap's maps are at most 32767 wide: rows of 4096
    grid = np.pad(flat, ((0, -n % cols), (0, 0))).reshape(-1, cols, 2)
    v = cv2.remap(img, grid[..., 0], grid[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()[:n]
    inside = (flat[:, 0] >= 0) & (flat[:, 0] <= w - 1) & (flat[:, 1] >= 0) & (flat[:, 1] <= h - 1)
    return np.where(inside, v, np.nan).reshape(q.shape[:-1])


def plate_evidence(image: np.ndarray, triples: np.ndarray, marker: Marker | None = None) -> np.ndarray:
    """The stage-1 decoding's ring evidence (``verify``): dark bands on one evenly lit
    white plate, every ring judged against the whole plate's brightness.

    Sampled where :func:`ring_evidence` samples (plus each ring's centre), the plate's
    brightness a plane fitted to its samples (:func:`_plate_level`). The product of four
    factors in [0, 1]: band contrast (sqrt of the smallest ring's (plate - band) / plate
    and (outside - band) / outside), plate evenness (1 - 10-90 % spread of the plate's
    residuals to its plane / plate), no ring brighter inside than the plate, and the
    plate's level right outside every ring. A shadow across the plate fails it, which is
    why the pipeline's gates use :func:`ring_evidence`; the decoding keeps this one, with
    which its thresholds were tuned at export.

    Args and returns: as :func:`ring_evidence`.
    """
    marker = marker or _MARKER
    zones = _zones(marker)
    P = np.asarray(triples, np.float64).reshape(-1, 3, 2)
    L = marker.centers2d
    A = layout_affine(P, L)
    t = P[:, 0] - A @ L[0]
    img = np.ascontiguousarray(image, np.float32)

    def sample(pts):  # pts (..., 2) mm → (T, ...) image values, NaN outside the image
        return _sample(img, np.einsum("tij,...j->t...i", A, pts) + t.reshape((-1,) + (1,) * (pts.ndim - 1) + (2,)))

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN medians: rings cut by the border
        band = _nanmedian(sample(zones["band"]).reshape(len(P), 3, -1))  # (T, 3)
        inner = _nanmedian(sample(np.concatenate([L[:, None, :], zones["inner"]], 1)))
        outside = _nanmedian(sample(zones["outside"]))
        level, spread = _plate_level(sample(zones["plate"]), zones["plate"], L, _nanmedian(outside), _EPS)
        contrast = np.minimum((level - band) / (level + _EPS), (outside - band) / (outside + _EPS)).min(1)
        factors = [
            np.sqrt(np.clip(contrast, 0, 1)),
            1 - spread,
            1 - 2 * np.clip((inner - level) / (level + _EPS), 0, None).max(1),
            1 - (np.abs(outside - level) / (level + _EPS)).max(1),
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
    lo, hi = (_nanpercentile(np.where(ok, resid, np.nan), q) for q in (10, 90))
    spread = (hi - lo) / (np.abs(coef[:, 0]) + eps)
    few = ok.sum(1) < min_points
    level = np.where(few[:, None], fallback[:, None], level.T)
    return level, np.where(few, 0.0, spread)


__all__ = ["plate_evidence", "ring_evidence"]
