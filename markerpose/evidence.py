"""Ring evidence: how much the image around a triple of ring centres looks like the
printed marker. :func:`ring_evidence` (dark bands on white paper, each judged against
the paper right beside it) is the gate of single-view detection and of the transfer
fallback; :func:`plate_evidence` (dark bands on one evenly lit plate) weighs the stage-1
decoding's triples (``verify``)."""

from __future__ import annotations

import warnings

import numpy as np

from .edges import masked_median, masked_percentile, sorted_stat
from .geometry import layout_affine
from .jit import compiled
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
    inner, band = circle(0.35 * r), np.stack([circle(r + 0.3 * (R - r)), circle(r + 0.7 * (R - r))], 2)  # (3, _ANGLES, 2, 2)
    return {
        "inner": inner,
        "band": band,
        "outside": outside,
        "plate": grid,
        "pairs": (i, j),
        "nearest": to_grid.argmin(2),
        "linked": to_grid.min(2) < 0.8 * R,
        # All of them, as ring_evidence's compiled pass takes them: inner, the band's two
        # circles, outside (3 x _ANGLES each), then the plate.
        "points": np.concatenate([z.reshape(-1, 2) for z in (inner, band[:, :, 0], band[:, :, 1], outside, grid)]),
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
    A, t = _affine(triples, marker)
    out = np.empty(len(A), np.float32)
    i, j = zones["pairs"]
    _ring_evidence_kernel(
        _image(image), A, t, zones["points"], zones["inner"].shape[1], i, j, zones["nearest"], zones["linked"], int(min_pairs), out
    )
    return out


def _affine(triples: np.ndarray, marker: Marker) -> tuple[np.ndarray, np.ndarray]:
    """Per triple of ring centres (T, 3, 2), the affine map from the marker's layout (mm)
    to the image: (A (T, 2, 2), t (T, 2))."""
    P = np.asarray(triples, np.float64).reshape(-1, 3, 2)
    L = marker.centers2d
    A = np.ascontiguousarray(layout_affine(P, L))
    return A, np.ascontiguousarray(P[:, 0] - A @ L[0])


def _image(image: np.ndarray) -> np.ndarray:
    img = np.ascontiguousarray(image, np.float32)
    if img.ndim != 2:
        raise ValueError(f"ring evidence needs a (H, W) gray image, got shape {img.shape}")
    return img


_EPS = 2.0 / 255  # a couple of grey levels: dark images are not divided by ~0


# numpy's nanmedian / nanpercentile over the last axis by compiled selection (numpy's
# NaN-aware statistics were most of the evidence's time); computed in float64, so a
# float32 percentile can differ from numpy's in its last bit.
def _nanmedian(x: np.ndarray) -> np.ndarray:
    return masked_median(x, ~np.isnan(x), empty=np.nan).astype(x.dtype)


def _nanpercentile(x: np.ndarray, q: float) -> np.ndarray:
    return masked_percentile(x, ~np.isnan(x), q, empty=np.nan).astype(x.dtype)


def _sample(img: np.ndarray, A: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples (T, ...) of ``img`` at the marker points ``pts`` (..., 2) mm mapped
    by each triple's affine map (A, t); NaN outside the image."""
    flat = np.ascontiguousarray(pts, np.float64).reshape(-1, 2)
    out = np.empty((len(A), len(flat)), np.float32)
    _affine_samples(img, A, t, flat, out)
    return out.reshape((len(A),) + pts.shape[:-1])


@compiled
def _affine_samples(img, A, t, pts, out):  # pragma: no cover - compiled
    """out[k, p]: ``img`` at the point pts[p] (mm) mapped by triple k's affine map, NaN
    outside the image (:func:`_bilinear`)."""
    h, w = img.shape
    for k in range(A.shape[0]):
        for p in range(pts.shape[0]):
            # numpy's einsum order: the two products summed, then the shift; as float32 coordinates.
            x = np.float32(A[k, 0, 0] * pts[p, 0] + A[k, 0, 1] * pts[p, 1] + t[k, 0])
            y = np.float32(A[k, 1, 0] * pts[p, 0] + A[k, 1, 1] * pts[p, 1] + t[k, 1])
            out[k, p] = _bilinear(img, x, y) if 0 <= x <= w - 1 and 0 <= y <= h - 1 else np.float32(np.nan)


@compiled
def _bilinear(img, x, y):  # pragma: no cover - compiled
    """The bilinear value of ``img`` at (x, y) (float32, inside the image) as OpenCV's remap
    gives it: along x on both rows, then along y, each a fused multiply-add in float32 (the
    product exact in float64, the sum rounded to float32: the fused value but for rare
    double roundings), the last row and column repeated."""
    h, w = img.shape
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    ax, ay = x - np.float32(x0), y - np.float32(y0)
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    p00, p01, p10, p11 = img[y0, x0], img[y0, x1], img[y1, x0], img[y1, x1]
    top = np.float32(np.float64(ax) * np.float64(p01 - p00) + np.float64(p00))
    bottom = np.float32(np.float64(ax) * np.float64(p11 - p10) + np.float64(p10))
    return np.float32(np.float64(ay) * np.float64(bottom - top) + np.float64(top))


_F1, _F2, _F4 = np.float32(1.0), np.float32(2.0), np.float32(4.0)
_EPS32 = np.float32(_EPS)
_NAN32 = np.float32(np.nan)


@compiled
def _step32(a, b):  # pragma: no cover - compiled
    """The relative difference of two paper samples (float32; NaN where either is)."""
    return abs(a - b) / (max(a, b) + _EPS32) if a == a and b == b else _NAN32


@compiled
def _nan_stat32(buf, n, q):  # pragma: no cover - compiled
    """:func:`~markerpose.edges.sorted_stat` of buf[:n] as float32; NaN for none."""
    return np.float32(sorted_stat(buf, n, q)) if n else _NAN32


@compiled
def _unit32(f):  # pragma: no cover - compiled
    """A factor clipped to [0, 1], NaN as 0."""
    return min(max(f, np.float32(0.0)), _F1) if f == f else np.float32(0.0)


@compiled
def _ring_evidence_kernel(img, A, t, pts, n_ang, pi, pj, nearest, linked, min_pairs, out):  # pragma: no cover - compiled
    """:func:`ring_evidence` of each triple (its affine map A[k], t[k]) into ``out``, in
    numpy's float32 arithmetic operation for operation (the medians and the percentile
    in float64). ``pts``: the zones' points, mm, in the order of :func:`_evidence_points`'
    "points"."""
    ring = 3 * n_ang  # points per zone of the rings
    s = np.empty((1, pts.shape[0]), np.float32)
    buf = np.empty(max(n_ang, len(pi)))
    for k in range(A.shape[0]):
        _affine_samples(img, A[k : k + 1], t[k : k + 1], pts, s)
        v = s[0]
        inner, band0, band1, outside, plate = v[:ring], v[ring : 2 * ring], v[2 * ring : 3 * ring], v[3 * ring : 4 * ring], v[4 * ring :]
        # Band contrast along each ray: the brighter band sample against the brighter of core and outside.
        contrast, brighter, off_plate = np.float32(np.inf), np.float32(-np.inf), _NAN32
        for r in range(3):
            n = 0
            for a in range(n_ang):
                i = r * n_ang + a
                b = max(band0[i], band1[i]) if band0[i] == band0[i] and band1[i] == band1[i] else _NAN32
                c = inner[i] if outside[i] != outside[i] else (outside[i] if inner[i] != inner[i] else max(inner[i], outside[i]))
                x = _F1 - b / (c + _EPS32)
                if x == x:
                    buf[n] = x
                    n += 1
            m = _nan_stat32(buf, n, -1.0)
            contrast = _NAN32 if m != m or contrast != contrast else min(contrast, m)  # numpy's min: NaN wins
            # No ring brighter inside than just outside.
            n = 0
            for a in range(n_ang):
                i = r * n_ang + a
                x = (inner[i] - outside[i]) / (outside[i] + _EPS32)
                if x == x:
                    buf[n] = x
                    n += 1
            m = _nan_stat32(buf, n, -1.0)
            m = max(m, np.float32(0.0)) if m == m else m
            brighter = _NAN32 if m != m or brighter != brighter else max(brighter, m)
            # Each ring on the plate: the step from the paper outside it to the nearest plate sample.
            n = 0
            for a in range(n_ang):
                i = r * n_ang + a
                if linked[r, a]:
                    x = _step32(outside[i], plate[nearest[r, a]])
                    if x == x:
                        buf[n] = x
                        n += 1
            m = _nan_stat32(buf, n, -1.0)
            if m == m:
                off_plate = m if off_plate != off_plate else max(off_plate, m)
        # Plate smoothness: the 75th percentile of the steps between neighbouring plate samples.
        n = 0
        for q in range(len(pi)):
            x = _step32(plate[pi[q]], plate[pj[q]])
            if x == x:
                buf[n] = x
                n += 1
        rough = _nan_stat32(buf, n, 75.0) if n >= min_pairs else np.float32(0.0)
        off_plate = off_plate if off_plate == off_plate else np.float32(0.0)  # no link in the image: no test
        f = _unit32(contrast) * _unit32(_F1 - _F4 * rough)
        f = f * _unit32(_F1 - _F2 * brighter)
        out[k] = f * _unit32(_F1 - off_plate)


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
    A, t = _affine(P, marker)
    img = _image(image)

    def sample(pts):  # pts (..., 2) mm → (T, ...) image values, NaN outside the image
        return _sample(img, A, t, pts)

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


def warm_up() -> None:
    """Compile this module's loops (or load them from numba's cache) before a stream's first frame."""
    tri = (_MARKER.centers2d + 20.0)[None]
    ring_evidence(np.zeros((64, 64), np.float32), tri)
    plate_evidence(np.zeros((64, 64), np.float32), tri)


__all__ = ["plate_evidence", "ring_evidence", "warm_up"]
