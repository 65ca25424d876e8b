"""The classical detector (paper §3.4): binarise, contours, concentric ellipses, layout IDs.

How it works, and why:

1. **Binarisation** (:func:`binarize`): a light Gaussian pre-blur, then a local-mean
   threshold at two window sizes (fractions of the image size, so a ring of any size in
   use has a window larger than its black band). The offset below the local mean is a
   multiple of the image's noise (estimated from the median absolute Laplacian-like
   residual), so the same setting works from full exposure down to a gain of ~0.05,
   where paper and ink differ by ~10 grey levels.
2. **Ring candidates** (:func:`find_rings`): in each binary image, a dark component
   whose outer contour and whose largest hole (the white inner disk) are both ellipses
   (``cv2.fitEllipse``, area/fill check), concentric within a tolerance, with the
   inner/outer size ratio of the :class:`~markerpose.marker.Marker` and a similar shape.
   A hole that is a good ellipse inside a dark region that is *not* one (a ring merged
   with a neighbour by blur, or touched by an occluder) also gives a candidate, its outer
   ellipse predicted from the hole. Every candidate must pass a grey-level check (dark
   band between a brighter hole and brighter surround) and duplicates across windows
   are merged.
3. **Sub-pixel centre** (:func:`refine_ring`): ``subpixel=False`` is the paper's
   choice, the centre of ``cv2.fitEllipse`` on the outer contour. ``subpixel=True``
   (default) samples the grey profile along rays of the coarse ellipse and locates each
   edge by the *area* method: the integral of the normalised profile across the edge
   equals the edge position for any symmetric blur and is exact for area-sampled pixels
   (a bare 50 % crossing with linear interpolation has a pixel-phase error). The plateau
   levels (ink, paper) are planes fitted over the ring from the rays that reach them, so
   lighting gradients do not bias the edges and motion-blurred rays still get the right
   50 % level. Rays spoilt by something next to the ring (a neighbour's blur, an
   occluder) are dropped. A direct least-squares ellipse fit (Halir-Flusser) with robust
   outlier rejection, iterated to convergence, gives the ellipse; with a camera the edge
   points are undistorted first (an imaged circle is an ellipse in ideal pixels only).
   Under motion blur longer than about the black band's width the profiles along the
   motion never reach a plateau and the edge fit errs along the motion (~1 px at 25 px
   of blur): there the marker's three rings are fitted again together, every pixel
   around them against a model of box-blurred rings (:func:`refine_blurred`,
   :mod:`markerpose.blurfit`).
4. **IDs by layout** (:func:`find_triples`): the three outer ellipses give the local
   affine map of the marker plane; undoing it (the symmetric square root of their mean
   quadratic form) rectifies the centres into marker units of one outer radius. A
   rotation+scale (no reflection) fit to the marker's layout then scores every ordered
   triple; the sign of the signed area rejects mirror images outright.
5. **Stereo**: the pipeline pairs the best triples of the two views by the epipolar
   constraint (:func:`markerpose.stages.match.pair_triples`), so a marker-like
   distractor seen in one view only cannot produce a pose.

All tunables live in :data:`default_conf`; pass ``conf={...}`` to override some.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from . import edges
from .camera import Camera
from .geometry import cq_to_conic, cq_to_rect, layout_affine, minor_semi_axis, rect_to_cq, ring_diameter, sqrtm_spd, view_poses
from .images import RESIDUAL_BINS, as_gray
from .jit import compiled
from .marker import Marker
from .results import Detection
from .threads import Worker

default_conf: dict = {
    # --- binarisation -----------------------------------------------------------------
    "blur_sigma": 1.0,  # Gaussian pre-blur before thresholding, px
    "block_sizes": (0.06, 0.2),  # local-mean windows, fractions of min(H, W)
    "min_block": 7,  # smallest window, px
    "offset_noise_k": 3.0,  # threshold offset below the local mean, in noise sigmas (after blur)
    "offset_min": 1.0,  # smallest offset, grey levels
    # --- ring candidates --------------------------------------------------------------
    "min_outer_px": 10.0,  # smallest outer diameter (major axis), px
    "min_inner_px": 4.0,  # smallest inner-disk diameter, px
    "max_outer_frac": 0.6,  # largest outer diameter, fraction of min(H, W)
    "min_axis_ratio": 0.15,  # minor/major of the outer ellipse (a ring seen at <= ~80°)
    "fill_tol": 0.12,  # |contour area / ellipse area - 1|
    "ratio_tol": 0.15,  # |inner/outer diameter ratio - marker's|
    "concentric_tol": 0.08,  # centre distance / outer major axis (plus 1 px)
    "ring_shape_tol": 0.3,  # outer vs inner log-shape distance (plus 1.5 / inner minor axis px)
    "hole_candidates": True,  # rings whose outer contour is merged: outer ellipse from the hole
    "contrast_frac": 0.6,  # fraction of rays where the band is darker than hole and surround
    "nms_frac": 0.3,  # duplicates: centre distance < this * outer minor semi-axis
    "max_candidates": 60,  # keep the best-scored candidates
    # --- sub-pixel edges ----------------------------------------------------------------
    "edge_method": "area",  # "area" (integral of the profile) or "midlevel" (50 % crossing)
    "edge_spacing": 1.5,  # arc length between rays, px
    "min_rays": 24,
    "max_rays": 360,
    "edge_step": 0.5,  # sample step along a ray, px
    "area_window": (0.5, 0.5),  # area method: half-window = a * (10-90 % edge width) + b, px
    "edge_weights": True,  # weigh edge points by (contrast / 10-90 % width)^2 in the fit (ours;
    #                        False: equal weights): under motion blur the edges along the motion
    #                        are smeared and their positions noisy
    "level_samples": 0.2,  # fraction of a profile at each end used for the plateau levels
    "level_smooth": 1 / 16,  # levels are averaged over this fraction of the ellipse (fallback)
    "level_tol": 0.25,  # drop rays whose two ends depart from the ring's levels unequally (x contrast)
    "blur_fit": True,  # refit wide-edged (motion-blurred) rings with a blurred-image model (ours)
    "blur_fit_blocks": True,  # ... its samples (block means) modelled as means (blurfit's block_fit)
    "blur_fit_tangents": True,  # ... its lines smoothed near the rings' tangents (blurfit's
    #                             tangent_smooth; False: bare lines, a cost with cusps)
    "blur_fit_width": 0.4,  # ... when the widest outer edge's 10-90 % width exceeds this
    #                         fraction of the smallest outer minor semi-axis
    "blur_fit_long_width": 0.3,  # ... or this fraction where that width is also at least
    "blur_fit_long_px": 7.5,  # ... this many px (about 10 px of motion blur: from there on the
    #                           edge fit loses to the model whatever the rings' size, while
    #                           shorter blur on foreshortened rings, or a shadow's edge across
    #                           them, is better left to the edge fit; 0: no such rule) ...
    "blur_fit_long_even": 0.6,  # ... and where the edges' widths are uneven around the rings:
    #                             the rings' median of their 25th percentile over their 75th at
    #                             most this (motion widens the edges along it only; defocus and
    #                             resampling widen all of them alike; 1: any edges)
    "blur_fit_unrefined": True,  # ... also when no ring could be edge-fitted (False: only
    #                               refit rings the edge fit found; a tracker's prediction
    #                               that missed the rings then fails fast)
    "blur_fit_max_move": 3.0,  # ... no ring refined if it would move a centre farther, px
    "blur_fit_edge_passes": 3,  # ... and rings whose outer edges are wider than blur_fit_width
    #                             take at most this many edge-fit passes (0: no limit): the
    #                             model fit refits them from wherever these leave them ...
    "blur_fit_motion_passes": 1,  # ... or this many where those edges, or long blur's
    #                               (blur_fit_long_*), are uneven as motion blur's
    #                               (blur_fit_long_even): the model's own case, whose fit
    #                               settles there from a rougher start (0: as wide edges) ...
    "blur_fit_motion_coarse": True,  # ... the first of them the coarse pass (first_pass_*),
    #                                  whose fit other wide edges discard
    "blur_fit_size_tol": 1.5,  # ... and only for three rings whose ellipses are the size their
    #                            spacing implies (area ratio within this factor squared): the
    #                            fit is costly on large decoy ellipses (seconds) and cannot help
    "refine_iters": 10,  # at most this many resample-and-fit passes ...
    "refine_tol": 0.005,  # ... stopping when the ellipse moves less than this, px
    "refine_first_tol": 0.0,  # ... or after the first pass already when it moved the ellipse
    #                           less than this, px (a seed known to be that close: tracking)
    "refine_predict": True,  # ... or when the next move, extrapolated from the last two (the
    #                          passes converge geometrically), is under refine_tol and the
    #                          last one under 10 x refine_tol: saves the pass that only confirms
    "first_pass_spacing": 4.5,  # arc length between rays in the first pass where it may not
    #                             stop the fit (refine_first_tol 0: a seed that may be a pixel
    #                             or more off, which coarse rays move as far), px; 0: edge_spacing
    "first_pass_max_width": 0.2,  # ... its fit discarded where the edges are wider (10-90 %) than
    #                               this fraction of the minor semi-axis (blur: every ray counts)
    "outlier_k": 3.0,  # reject edge points beyond k robust sigmas from the fit
    "outlier_min_px": 0.15,  # ... but never tighter than this, px
    "rescreen_frac": 0.03,  # the next pass screens its points by least median again only after a
    #                         fit that rejected more than this fraction of them (negative: always)
    "close_seed_screen": False,  # a seed known to be close (refine_first_tol > 0) screened from its
    #                              first pass too (False: that pass fits every point, and a screened
    #                              pass follows only where its fit rejected more than rescreen_frac)
    "plate_edge": True,  # drop the outer edges' rays, and the blurred-ring fit's pixels, that what
    #                      lies beyond the plate may reach once blurred (the plate's outline from the
    #                      marker's plate_margin, mapped by the ring centres)
    "min_valid_frac": 0.5,  # fewer valid edge points than this → keep the coarse ellipse
    "min_free_frac": 0.25,  # rays kept after dropping those near neighbours, else keep all
    "refine_inner": False,  # also refine the inner (hole) ellipse (always for "concentric")
    "center": "outer",  # "outer": centre of the outer ellipse (the paper's point);
    #                     "concentric": projected circle centre from outer+inner conics
    # --- layout -----------------------------------------------------------------------
    "prune_tol": 0.5,  # pairwise rectified distance vs the marker's, relative
    "layout_tol": 0.15,  # RMS residual of the similarity fit / RMS spread of the triple
    "scale_tol": 1.6,  # rectified scale within [1/scale_tol, scale_tol] outer radii
    "size_ratio_max": 1.6,  # largest / smallest outer major axis among the three
    "triple_shape_tol": 0.5,  # log-shapes of the three outer ellipses agree within this
    "max_triples": 8,  # triples kept per view (stereo matching considers these)
}


class FitBudget:
    """How many blurred-ring model fits one detection may still run: the costliest
    refinement, which an inconsistent pair would otherwise run on every hypothesis."""

    def __init__(self, fits: int):
        self.left = int(fits)

    def take(self) -> bool:
        """Spend one fit; False when none is left."""
        if self.left <= 0:
            return False
        self.left -= 1
        return True


@dataclass(frozen=True)
class BlurLimits:
    """What may stop a blurred-ring fit that is due, for one call (never settings: they
    live in the caller's frame). Where either stops a fit that is due, no ring of the
    view is refined (:func:`refine_blurred`).

    Attributes:
        budget: the fits one detection may still run, shared by its refinements (None:
            no limit).
        gate: a test ``(gray, centres (3, 2)) -> bool`` the rings must pass first, e.g.
            ring evidence, which a decoy's lack (None: no test).
    """

    budget: FitBudget | None = None
    gate: Callable | None = None


@dataclass
class Ring:
    """One ring candidate in an image.

    Attributes:
        center: (2,) its centre, px (outer-ellipse centre unless conf["center"] says otherwise).
        outer: outer (black) ellipse as an OpenCV RotatedRect ((cx, cy), (w, h), angle_deg).
        inner: inner (white disk) ellipse, RotatedRect.
        score: quality in (0, 1], higher is better.
        refined: True when the ellipses come from sub-pixel edges.
        from_hole: True when the outer ellipse was predicted from the hole (merged contour).
    """

    center: np.ndarray
    outer: tuple
    inner: tuple
    score: float
    refined: bool = False
    from_hole: bool = False
    # Internal: the ellipses as centre + quadratic form, (x - c)^T Q (x - c) = 1.
    _outer_cq: tuple = field(default=None, repr=False)
    _inner_cq: tuple = field(default=None, repr=False)
    _edge_width: float = field(default=0.0, repr=False)  # outer edge's 10-90 % width, px (refined)
    _edge_even: float = field(default=1.0, repr=False)  # those widths' 25th percentile over their 75th (refined)
    _plate_reached: bool = field(default=False, repr=False)  # the plate's blurred edge reached its edge fit's rays
    _blur: float = field(default=0.0, repr=False)  # motion blur length of the blurred-ring fit, px (0: not fitted)
    _rejected: bool = field(default=False, repr=False)  # under heavy blur the edge fit is not trusted: the blurred-ring
    #                                                     fit disagreed with it, or was due and could not run
    _center_cov: np.ndarray | None = field(default=None, repr=False)  # (2, 2) the centre's covariance, px^2 (None: not fitted)


# --- input handling ------------------------------------------------------------------------
def _merge_conf(conf: dict | None) -> dict:
    c = dict(default_conf)
    if conf:
        unknown = set(conf) - set(default_conf)
        if unknown:
            raise ValueError(f"unknown classical-detector settings: {sorted(unknown)}")
        c.update(conf)
    if c["edge_method"] not in ("area", "midlevel"):
        raise ValueError(f"edge_method must be 'area' or 'midlevel', got {c['edge_method']!r}")
    if c["center"] not in ("outer", "concentric"):
        raise ValueError(f"center must be 'outer' or 'concentric', got {c['center']!r}")
    return c


def to_gray(image, name: str = "image") -> np.ndarray:
    """An input image (:func:`markerpose.images.as_gray`; float32 on the 0..255 scale is
    accepted too) as float32 grey levels (H, W)."""
    return np.ascontiguousarray(as_gray(image, name, allow_float=True), dtype=np.float32)


# --- ellipse helpers ------------------------------------------------------------------------
def fit_ellipse(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Direct least-squares ellipse fit (Fitzgibbon; Halir-Flusser's stable form; one
    ellipse of :func:`markerpose.edges.fit_ellipses`).

    Args:
        points: (N, 2) points, N >= 6.
        weights: optional (N,) non-negative weights of the points' algebraic residuals.
    Returns:
        (centre (2,), Q (2, 2)) with (x - c)^T Q (x - c) = 1, or None if degenerate.
    """
    p = np.asarray(points, dtype=np.float64).reshape(1, -1, 2)
    w = None if weights is None else np.asarray(weights, np.float64).reshape(1, -1)
    cen, Q, ok = edges.fit_ellipses(p, np.ones(p.shape[:2], bool), w)
    return (cen[0], Q[0]) if ok[0] else None


def concentric_center(outer_cq, inner_cq) -> np.ndarray | None:
    """Image of the common centre of two concentric circles from their imaged ellipses.

    For concentric circles Q_o = diag(1, 1, -r_o^2), Q_i = diag(1, 1, -r_i^2), the matrix
    Q_o^-1 Q_i has the centre (0, 0, 1) as the eigenvector of its single eigenvalue; under a
    homography H the imaged conics give C_o^-1 C_i = H (Q_o^-1 Q_i) H^-1 up to scale, whose
    matching eigenvector is H (0, 0, 1): the projected centre, free of the perspective bias
    of the ellipse centres. (Exact for a pinhole; lens distortion across one ring is small.)
    """
    Co = cq_to_conic(*outer_cq)
    Ci = cq_to_conic(*inner_cq)
    try:
        w, v = np.linalg.eig(np.linalg.solve(Co, Ci))
    except np.linalg.LinAlgError:
        return None
    w = np.real(w)
    # The single eigenvalue is the one farthest from the other two (a double pair).
    k = int(np.argmax([abs(w[i] - w[(i + 1) % 3]) + abs(w[i] - w[(i + 2) % 3]) for i in range(3)]))
    e = np.real(v[:, k])
    if abs(e[2]) < 1e-12:
        return None
    return e[:2] / e[2]


# --- binarisation ----------------------------------------------------------------------------
@compiled
def _residual_histogram(g, k, hist):  # pragma: no cover - compiled
    """hist[v] += how many pixels of the grid g[1:-1:k, 1:-1:k] have |4 I - (sum of the 4
    neighbours)| = v (uint8 g)."""
    H, W = g.shape
    for y in range(1, H - 1, k):
        for x in range(1, W - 1, k):
            r = 4 * np.int32(g[y, x]) - (np.int32(g[y - 1, x]) + np.int32(g[y + 1, x]) + np.int32(g[y, x - 1]) + np.int32(g[y, x + 1]))
            hist[abs(r)] += 1


def noise_stride(shape: tuple) -> int:
    """The step of :func:`noise_sigma`'s grid of pixels for an image of ``shape`` (H, W):
    about 60k residuals suffice."""
    return max(1, int(np.sqrt(shape[0] * shape[1] / 60_000)))


def noise_from_residuals(hist: np.ndarray) -> float:
    """:func:`noise_sigma` from the histogram of the grid's residuals (``hist[v]``: how many
    have |4 I - (sum of the 4 neighbours)| = v; :data:`~markerpose.images.RESIDUAL_BINS` bins): 4 x the residual
    is an integer, so their exact median (the float computation's) comes from the counts."""
    cum = np.cumsum(hist)
    n = cum[-1]
    mid = np.searchsorted(cum, [(n - 1) // 2 + 1, n // 2 + 1])  # the two middle order statistics
    return _sigma_from_mad(np.float32(0.125 * (mid[0] + mid[1])))


def _sigma_from_mad(med) -> float:
    # var(r) = sigma^2 (1 + 4/16) for white noise; MAD → sigma for a Gaussian.
    return float(1.4826 * med / np.sqrt(1.25))


def noise_sigma(gray: np.ndarray) -> float:
    """Robust estimate of the per-pixel noise sigma (grey levels) of a grey image (float,
    or uint8 as it is).

    Median absolute value of ``I - mean(4-neighbours)`` over a subsampled grid
    (:func:`noise_stride`; edges and texture are a minority of pixels, so the median sees
    the noise).
    """
    k = noise_stride(gray.shape)
    g = gray
    if g.dtype == np.uint8:
        # Counted in one compiled pass over the grid (stage 1's exact quarter-size input
        # counts them in its own pass: keypoints.to_input's ``residuals``).
        hist = np.zeros(RESIDUAL_BINS, np.int64)
        _residual_histogram(g, k, hist)
        return noise_from_residuals(hist)
    r = g[1:-1:k, 1:-1:k] - 0.25 * (g[:-2:k, 1:-1:k] + g[2::k, 1:-1:k] + g[1:-1:k, :-2:k] + g[1:-1:k, 2::k])
    return _sigma_from_mad(np.median(np.abs(r)))


def warm_up() -> None:
    """Compile this module's loop (or load it from numba's cache) before a stream's first
    frame needs it."""
    noise_sigma(np.zeros((8, 8), np.uint8))


def binarize(gray: np.ndarray, conf: dict | None = None, noise: float | None = None) -> list[np.ndarray]:
    """Dark-region masks of a float grey image, one per local-mean window.

    Args:
        gray: (H, W) float32 grey levels.
        noise: the image's noise sigma if known (else :func:`noise_sigma`).
    Returns:
        list of (H, W) uint8 masks, 255 where the (pre-blurred) image is darker than its
        local mean minus an offset.
    """
    c = _merge_conf(conf)
    h, w = gray.shape
    s = c["blur_sigma"]
    blur = cv2.GaussianBlur(gray, (0, 0), s) if s > 0 else gray
    # Noise after a Gaussian of sigma s drops by 1 / (2 s sqrt(pi)) for white noise.
    noise = noise_sigma(gray) if noise is None else noise
    sig = noise * (1.0 / (2 * s * np.sqrt(np.pi)) if s > 0 else 1.0)
    offset = max(c["offset_min"], c["offset_noise_k"] * sig)
    masks = []
    for frac in c["block_sizes"]:
        b = max(int(c["min_block"]), int(round(frac * min(h, w))) | 1)
        mean = cv2.blur(blur, (b, b), borderType=cv2.BORDER_REPLICATE)
        masks.append(((blur < mean - offset).astype(np.uint8)) * 255)
    return masks


# --- ring candidates ---------------------------------------------------------------------------
def _log_shape(Q: np.ndarray) -> np.ndarray:
    """Log of the unit-determinant shape matrix: a scale-free ellipse shape whose Frobenius
    distances treat thin and round ellipses alike (sqrt(2) |log ratio of axis ratios| when aligned)."""
    lam, V = np.linalg.eigh(Q)
    ll = np.log(lam) - 0.5 * np.log(lam).sum()
    return (V * ll) @ V.T


def _inset(rect, d: float) -> np.ndarray:
    """Quadratic form of a RotatedRect whose axes are grown by ``d`` px (negative: shrunk)."""
    (cx, cy), (w, h), ang = rect
    return rect_to_cq(((cx, cy), (max(w + d, 0.5), max(h + d, 0.5)), ang))[1]


def _contrast_check(gray, c, Q, rho, gap, offset, n=32):
    """Fraction of rays where the ring band is darker than the hole and the surround."""
    L = sqrtm_spd(Q, -0.5)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    u = L @ np.stack([np.cos(t), np.sin(t)])  # (2, n) ellipse points relative to c
    lams = np.array([0.5 * rho, 0.5 * (1 + rho), 1 + 0.5 * gap])
    P = c[:, None, None] + u[:, None, :] * lams[None, :, None]  # (2, 3, n)
    v, ok = edges.bilinear(gray, P[0], P[1])
    hole, band, out = v
    good = (band < hole - offset) & (band < out - offset) & ok.all(0)
    contrast = float(np.median(np.minimum(hole, out) - band))
    return float(good.mean()), contrast


def find_rings(
    image: np.ndarray,
    marker: Marker = Marker(),
    conf: dict | None = None,
    subpixel: bool = False,
    camera: Camera | None = None,
) -> list[Ring]:
    """All ring candidates in one image, best first.

    Args:
        image: uint8 gray (H, W) or BGR (H, W, 3).
        marker: the marker (gives the inner/outer ratio and the gap between rings).
        conf: overrides of :data:`default_conf`.
        subpixel: refine every candidate's ellipses with :func:`refine_ring`.
        camera: the camera that took the image (optional; see :func:`refine_ring`).
    Returns:
        list of :class:`Ring`, highest score first (at most conf["max_candidates"]).
    """
    c = _merge_conf(conf)
    gray = to_gray(image)
    noise = noise_sigma(gray)
    rings = _find_rings_gray(gray, marker, c, noise)
    if subpixel:
        rings = [refine_ring(gray, r, marker, c, noise, camera=camera) for r in rings]
    return rings


def _marker_gap(marker: Marker) -> float:
    """Smallest white gap between two rings, in outer radii."""
    p = marker.centers2d
    d = min(np.linalg.norm(p[i] - p[j]) for i, j in ((0, 1), (0, 2), (1, 2)))
    return (d - marker.outer_diameter) / marker.outer_radius


def _find_rings_gray(gray: np.ndarray, marker: Marker, c: dict, noise: float) -> list[Ring]:
    h, w = gray.shape
    rho = marker.inner_diameter / marker.outer_diameter
    gap = min(_marker_gap(marker), 1.0)
    max_outer = c["max_outer_frac"] * min(h, w)
    min_outer_len = 0.8 * np.pi * c["min_outer_px"] / 1.5  # contour points of the smallest ring
    offset = max(c["offset_min"], c["offset_noise_k"] * noise / np.sqrt(3.0))  # ~3-sample averages
    cands: list[Ring] = []
    for mask in binarize(gray, c, noise):
        contours, hier = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        if hier is None:
            continue
        hier = hier[0]
        lens = np.fromiter((len(k) for k in contours), dtype=np.int64, count=len(contours))
        # Top-level dark components with at least one hole, long enough to be a ring.
        tops = np.nonzero((hier[:, 3] < 0) & (hier[:, 2] >= 0) & (lens >= min_outer_len))[0]
        for i in tops:
            holes = []
            j = hier[i, 2]
            while j >= 0:
                if lens[j] >= 6:
                    holes.append(j)
                j = hier[j, 0]
            if not holes:
                continue
            areas = [cv2.contourArea(contours[j]) for j in holes]
            hole = holes[int(np.argmax(areas))]
            inner = _ellipse_of_contour(contours[hole], max(areas), c)
            if inner is None:
                continue
            ci, Qi, inner_rect = inner
            if max(inner_rect[1]) < c["min_inner_px"]:
                continue
            outer = _ellipse_of_contour(contours[i], cv2.contourArea(contours[i]), c)
            ring = None
            if outer is not None:
                ring = _ring_from_pair(outer, inner, rho, max_outer, c)
            if ring is None and c["hole_candidates"]:
                # The dark region is not one ellipse (merged / touched): predict the outer
                # ellipse from the hole, corrected for the contour's half-pixel inset.
                lam, V = np.linalg.eigh(Qi)
                semi = 1 / np.sqrt(lam)  # the hole's semi-axes along V's columns
                Qo = (V / ((semi - 0.5) / rho) ** 2) @ V.T
                rect = cq_to_rect(ci, Qo)
                major = max(rect[1])
                if c["min_outer_px"] <= major <= max_outer and min(rect[1]) / major >= c["min_axis_ratio"]:
                    ring = Ring(ci.copy(), rect, inner_rect, 0.5, from_hole=True, _outer_cq=(ci, Qo), _inner_cq=(ci, Qi))
            if ring is None:
                continue
            frac, _ = _contrast_check(gray, ring._outer_cq[0], ring._outer_cq[1], rho, gap, offset)
            if frac < c["contrast_frac"]:
                continue
            ring.score *= frac
            cands.append(ring)
    return _nms(cands, c)


def _ellipse_of_contour(contour, area, c):
    """cv2.fitEllipse of a contour with a fill check; (centre, Q, rect) or None."""
    if len(contour) < 6:
        return None
    rect = cv2.fitEllipse(contour)
    (cx, cy), (w_, h_), ang = rect
    if not (w_ > 0 and h_ > 0 and np.isfinite(cx) and np.isfinite(cy)):
        return None
    ea = np.pi * w_ * h_ / 4.0
    if abs(abs(area) / ea - 1.0) > c["fill_tol"] + 2.0 / min(w_, h_):
        return None
    cen, Q = rect_to_cq(rect)
    return cen, Q, rect


def _ring_from_pair(outer, inner, rho, max_outer, c) -> Ring | None:
    co, Qo, rect_o = outer
    ci, Qi, rect_i = inner
    major, minor = max(rect_o[1]), min(rect_o[1])
    if not (c["min_outer_px"] <= major <= max_outer) or minor / major < c["min_axis_ratio"]:
        return None
    # Contours run through the boundary pixels of the dark region: the outer one lies
    # ~0.5 px inside the region's edge, the hole's ~0.5 px outside the white disk.
    d_o = np.sqrt(rect_o[1][0] * rect_o[1][1]) + 1.0
    d_i = max(np.sqrt(rect_i[1][0] * rect_i[1][1]) - 1.0, 1e-3)
    ratio = d_i / d_o
    if abs(ratio - rho) > c["ratio_tol"]:
        return None
    dc = np.linalg.norm(co - ci)
    if dc > c["concentric_tol"] * major + 1.0:
        return None
    # Same shape (axis ratio, orientation), after the half-pixel contour insets.
    dshape = np.linalg.norm(_log_shape(_inset(rect_o, 1.0)) - _log_shape(_inset(rect_i, -1.0)))
    shape_tol = c["ring_shape_tol"] + 1.5 / max(min(rect_i[1]), 1.0)
    if dshape > shape_tol:
        return None
    cost = ((ratio - rho) / c["ratio_tol"]) ** 2 + (dc / (c["concentric_tol"] * major + 1.0)) ** 2 + (dshape / shape_tol) ** 2
    return Ring(co.copy(), rect_o, rect_i, float(np.exp(-0.5 * cost)), _outer_cq=(co, Qo), _inner_cq=(ci, Qi))


def _nms(cands: list[Ring], c: dict) -> list[Ring]:
    cands = sorted(cands, key=lambda r: -r.score)
    kept: list[Ring] = []
    for r in cands:
        b = min(r.outer[1]) / 2.0
        a = max(r.outer[1])
        dup = False
        for k in kept:
            if np.linalg.norm(k.center - r.center) < c["nms_frac"] * max(b, min(k.outer[1]) / 2.0):
                if 0.6 < a / max(k.outer[1]) < 1.6:
                    dup = True
                    break
        if not dup:
            kept.append(r)
        if len(kept) >= c["max_candidates"]:
            break
    return kept


# --- sub-pixel refinement ------------------------------------------------------------------
def _ideal_to_pixels(camera: Camera, p: np.ndarray) -> np.ndarray:
    """(N, 2) ideal (undistorted) pixels → distorted pixels of ``camera``."""
    K = camera.K
    p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
    y = (p[:, 1] - K[1, 2]) / K[1, 1]
    x = (p[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return camera.distort(np.column_stack([x, y]))


@functools.lru_cache(maxsize=64)
def _edge_windows(marker: Marker) -> tuple[float, float, float]:
    """(rho, outer half-window, inner half-window) of the edge fits, in units of the
    ellipse: up to the middle of the black band on one side and to the middle of the gap
    between rings (outer) or deep into the hole (inner)."""
    rho = marker.inner_diameter / marker.outer_diameter
    gap = _marker_gap(marker)
    half_band = 0.5 * (1 - rho)  # outer radii
    w_out = 0.9 * min(half_band, 0.5 * gap)
    w_in = 0.9 * min(half_band / rho, 0.8)
    return rho, w_out, w_in


def _inner_starts(rings: list, outer: list, rho: np.ndarray) -> list:
    """Per ring, the inner ellipse's start (centre, Q) where its outer edge fitted: the
    hole's, or the fitted outer one scaled by its marker's rho (K,); None elsewhere."""
    inner_cqs = [None] * len(rings)
    for k, (r, out) in enumerate(zip(rings, outer)):
        if out is not None:
            inner_cqs[k] = r._inner_cq if r._inner_cq is not None and not r.from_hole else (out[0][0], out[0][1] / rho[k] ** 2)
    return inner_cqs


def _refine_inner(grays: list, view: np.ndarray, inner_cqs: list, w_in: np.ndarray, c: dict, floor: np.ndarray, cameras: list) -> list:
    """One batch of edge fits of the inner edges from ``inner_cqs`` (where not None), when
    conf["refine_inner"] or the concentric centre asks for them; None per ring elsewhere."""
    inner: list = [None] * len(inner_cqs)
    todo = [k for k in range(len(inner_cqs)) if inner_cqs[k] is not None]
    if (c["refine_inner"] or c["center"] == "concentric") and todo:
        fits = edges.refine_edges(
            grays,
            view[todo],
            np.array([inner_cqs[k][0] for k in todo]),
            np.array([inner_cqs[k][1] for k in todo]),
            w_in[todo],
            False,
            c,
            floor[todo],
            [[] for _ in todo],
            cameras,
        )
        for k, f in zip(todo, fits):
            inner[k] = f
    return inner


_LOCAL_MAP_STEP = 0.5  # px: the ideal-to-image map's Jacobian at a centre, by differences over this step
_LOCAL_MAP = np.array([[0.0, 0.0], [_LOCAL_MAP_STEP, 0.0], [0.0, _LOCAL_MAP_STEP]])


def _image_centres(outer: list, view: np.ndarray, cameras: list | None) -> dict:
    """Ring k -> (its outer ideal-pixel centre in the image's pixels, the lens's local map
    there (2, 2)) for the rings fitted in ideal pixels: one distortion call per camera."""
    out: dict = {}
    if cameras is None:
        return out
    for g in sorted({int(v) for v in view}):
        ks = [k for k, f in enumerate(outer) if f is not None and f[1] is not None and view[k] == g and cameras[g] is not None]
        if not ks:
            continue
        pts = np.concatenate([outer[k][1][0] + _LOCAL_MAP for k in ks])
        mapped = _ideal_to_pixels(cameras[g], pts).reshape(-1, 3, 2)
        for k, m in zip(ks, mapped):
            out[k] = (m[0], (m[1:] - m[0]).T / _LOCAL_MAP_STEP)
    return out


def _refined_ring(ring: Ring, outer: tuple, inner_cq, inner: tuple | None, camera: Camera | None, mapped: tuple | None, c: dict) -> Ring:
    """``ring`` with its edge fits: ``outer`` and ``inner`` (or None) as
    :func:`markerpose.edges.refine_edges` gives them, ``inner_cq`` the inner fit's start;
    the centre the outer ellipse's (in ideal pixels where there is a camera) or, with
    conf["center"] = "concentric", the two ellipses' concentric centre. ``mapped``: the
    outer ideal centre in the image's pixels and the lens's local map there
    (:func:`_image_centres`), None where the ring was not fitted in ideal pixels."""
    outer_cq, outer_ideal, width, cov, plate_reached, even = outer
    inner_ideal = None
    if inner is not None:
        inner_cq, inner_ideal = inner[:2]
    use_ideal = mapped is not None
    if use_ideal:  # the centre and, through the lens's local map, its covariance in the image's pixels
        center, J = mapped
        cov = J @ cov @ J.T
    else:
        center = outer_cq[0].copy()
    if c["center"] == "concentric" and inner is not None:
        if use_ideal and inner_ideal is not None:
            cc = concentric_center(outer_ideal, inner_ideal)
            cc = None if cc is None else _ideal_to_pixels(camera, cc)[0]
        else:
            cc = concentric_center(outer_cq, inner_cq)
        # Guard against a degenerate eigen-decomposition (the bias is a few % of a radius).
        if cc is not None and np.linalg.norm(cc - center) < 0.1 * max(ring.outer[1]) + 1.0:
            center, cov = cc, np.full((2, 2), np.nan)  # the two ellipses' centre: no covariance from one fit
    return replace(
        ring,
        center=center,
        outer=cq_to_rect(*outer_cq),
        inner=cq_to_rect(*inner_cq) if inner is not None else ring.inner,
        refined=True,
        _outer_cq=outer_cq,
        _inner_cq=inner_cq,
        _edge_width=width,
        _edge_even=even,
        _plate_reached=plate_reached,
        _center_cov=cov,
    )


def _refine_batch(
    grays: list, view: list, rings: list, others: list, marker, c: dict, noises: list, cameras: list, plates: list | None = None
) -> list:
    """:func:`refine_ring` of several rings at once (of one or more images; ring k is in
    ``grays[view[k]]``, seen by ``cameras[view[k]]``, its neighbours ``others[k]``, its
    marker ``marker`` or ``marker[k]``, its plate's sides ``plates[k]`` or None): one batch
    of edge fits (:func:`markerpose.edges.refine_edges`, each ring with its marker's windows)
    for all outer edges, one for all inner ones."""
    if not rings:
        return []
    if isinstance(marker, Marker):
        rho, w_out, w_in = (np.full(len(rings), w) for w in _edge_windows(marker))
    else:
        rho, w_out, w_in = np.array([_edge_windows(mk) for mk in marker], np.float64).T
    view = np.asarray(view, np.intp)
    floor = np.array([max(1.0, 2.0 * n) for n in noises])[view]  # smallest edge contrast, grey levels
    oth = [[o._outer_cq for o in os if o is not r] for r, os in zip(rings, others)]
    if c["blur_fit"] and c["blur_fit_edge_passes"]:
        c = {**c, "wide_edge_passes": c["blur_fit_edge_passes"], "wide_edge_width": c["blur_fit_width"]}
        if c["blur_fit_motion_passes"]:  # motion blur: wide edges, or long blur where that rule is on (_blur_fit_due)
            long_px = c["blur_fit_long_px"] if c["blur_fit_long_px"] > 0 else np.inf
            c["motion_edges"] = (
                c["blur_fit_motion_passes"], c["blur_fit_long_even"], long_px, c["blur_fit_long_width"], c["blur_fit_motion_coarse"]
            )  # fmt: skip
    outer = edges.refine_edges(
        grays,
        view,
        np.array([r._outer_cq[0] for r in rings]),
        np.array([r._outer_cq[1] for r in rings]),
        w_out,
        True,
        c,
        floor,
        oth,
        cameras,
        plates,
    )
    inner_cqs = _inner_starts(rings, outer, rho)
    inner = _refine_inner(grays, view, inner_cqs, w_in, c, floor, cameras)
    result = []
    centres = _image_centres(outer, view, cameras)
    for k, ring in enumerate(rings):
        if outer[k] is None:
            result.append(ring)
            continue
        camera = None if cameras is None else cameras[view[k]]
        result.append(_refined_ring(ring, outer[k], inner_cqs[k], inner[k], camera, centres.get(k), c))
    return result


def refine_ring(
    gray: np.ndarray,
    ring: Ring,
    marker: Marker = Marker(),
    conf: dict | None = None,
    noise: float | None = None,
    others: list[Ring] = (),
    camera: Camera | None = None,
) -> Ring:
    """Sub-pixel ellipses of one ring candidate: the outer one, and the inner one when
    conf["refine_inner"] is set or conf["center"] is "concentric".

    The edges are sampled along rays of the current ellipse and fitted again, until the
    ellipse stops moving (:mod:`markerpose.edges`). :func:`refine_views` does the same for
    several rings at once.

    Args:
        gray: (H, W) float32 grey image (see :func:`to_gray`), not blurred.
        ring: a candidate from :func:`find_rings`.
        marker: the marker geometry (inner/outer ratio, gaps: the sampling windows).
        conf: overrides of :data:`default_conf`.
        noise: the image's noise sigma if known (else :func:`noise_sigma`).
        others: the marker's other rings; outer-edge rays that look toward them are not
            used where a blurred neighbour could bleed into the profile.
        camera: if given, the edge points are undistorted before the ellipse fit, and the
            centre is mapped back to the image's (distorted) pixels. Without it the
            ellipse is fitted in the distorted image, which is off by up to ~0.08 px for
            rings far from the principal point of a 12 mm lens.
    Returns:
        a new :class:`Ring` with refined ellipses and centre (``refined=True``), or the
        input unchanged when too few edge points are found (occlusion, image border).
    """
    c = _merge_conf(conf)
    noise = noise_sigma(gray) if noise is None else noise
    return _refine_batch([gray], [0], [ring], [list(others)], marker, c, [noise], [camera])[0]


def _noises(grays: list, noises: list | None) -> list:
    """Per view, the noise sigma given, or :func:`noise_sigma` where none is."""
    missing = [v for v in range(len(grays)) if noises is None or noises[v] is None]
    found = dict(zip(missing, noise_sigmas([grays[v] for v in missing])))
    return [found[v] if v in found else noises[v] for v in range(len(grays))]


def noise_sigmas(grays: list) -> list[float]:
    """:func:`noise_sigma` of each image, two at a time on two cores (its pass over the image
    runs compiled, outside Python's lock)."""
    return _WORKER.map(noise_sigma, grays)


def refine_views(
    grays: list,
    rings: list,
    marker: Marker | list = Marker(),
    conf: dict | None = None,
    noises: list | None = None,
    cameras: list | None = None,
) -> list:
    """:func:`refine_ring` of every ring of one or more views in one batch, each ring's
    neighbours being the other rings of its view.

    Args:
        grays: per view, a (H, W) float32 grey image (an image may come more than once,
            with another marker's rings).
        rings: per view, a list of :class:`Ring` or None (kept None).
        marker: the marker, or per view the marker whose rings they are (each ring is
            fitted with its marker's edge windows, all in one batch).
        noises: per view, the noise sigma if known (else :func:`noise_sigma`).
        cameras: per view, a :class:`~markerpose.camera.Camera` or None.
    Returns:
        per view, the list of refined rings (see :func:`refine_ring`).
    """
    c = _merge_conf(conf)
    noises = _noises(grays, noises)
    flat = [(v, k, r) for v, rs in enumerate(rings) for k, r in enumerate(rs) if r is not None]
    present = [[r for r in rs if r is not None] for rs in rings]
    markers = [marker] * len(rings) if isinstance(marker, Marker) else list(marker)
    per = marker if isinstance(marker, Marker) else [markers[v] for v, _, _ in flat]
    cams = cameras if cameras is not None else [None] * len(rings)
    sides = [plate_sides(rs, mk, cam) if _plate_near(mk, c) else None for rs, mk, cam in zip(rings, markers, cams)]
    done = _refine_batch(
        grays,
        [v for v, _, _ in flat],
        [r for _, _, r in flat],
        [present[v] for v, _, _ in flat],
        per,
        c,
        noises,
        cameras,
        [sides[v] for v, _, _ in flat],
    )
    out = [list(rs) for rs in rings]
    for (v, k, _), r in zip(flat, done):
        out[v][k] = r
    return out


def plate_sides(rings: list, marker: Marker, camera: Camera | None = None) -> np.ndarray | None:
    """The sides of the marker's plate in the image (:func:`markerpose.edges.plate_lines`:
    (4, 3), distances positive inside, px) where ``rings`` are the marker's rings in ring
    order: through the plate's pose in the view that best explains their centres and
    ellipses (:func:`markerpose.geometry.view_poses`) with a camera, else the affine map
    that takes the marker's ring centres to theirs (which perspective bends by pixels at
    the plate's corners). None unless every ring is there."""
    if len(rings) != 3 or any(r is None for r in rings):
        return None
    P = np.array([r.center for r in rings], np.float64)
    if not np.isfinite(P).all():
        return None
    if camera is not None:
        poses = view_poses(camera, P, [r.outer for r in rings], marker.points3d, marker.outer_radius)
        if not poses:
            return None
        T = poses[0][1]
        corners = camera.project(marker.plate_corners3d @ T[:3, :3].T + T[:3, 3])
    else:
        A = layout_affine(P, marker.centers2d)
        if abs(np.linalg.det(A)) < 1e-9:
            return None
        corners = (marker.plate_corners3d[:, :2] - marker.centers2d[0]) @ A.T + P[0]
    return edges.plate_lines(corners)


def _plate_near(marker: Marker, c: dict) -> bool:
    """Whether the plate's edge can reach an outer edge's rays at all: its margin within
    the rays' window plus the reach of the widest blur the edge fit keeps (blur_fit_width
    of the ring's radius; wider edges go to the blurred-ring fit), with room for a tilt.
    The blurred-ring fit leaves out the plate's reach only then too: from a wider margin
    the plate's edge stays at the edge of its pixels, where its robust weights take it."""
    _, w_out, _ = _edge_windows(marker)
    return c["plate_edge"] and marker.margin < (w_out + 0.65 * c["blur_fit_width"] + 0.25) * marker.outer_radius


def _center_covs(rings: list) -> np.ndarray:
    """(n, 2, 2) the rings' centre covariances, px^2: NaN for a ring missing, not refined
    or rejected."""
    nan = np.full((2, 2), np.nan)
    return np.array(
        [nan if r is None or not r.refined or r._rejected or r._center_cov is None else r._center_cov for r in rings], np.float64
    ).reshape(-1, 2, 2)


def _blur_length(rings: list) -> float:
    """The blur length the blurred-ring fit kept for a view's rings (None for a missing
    one), px; 0 where it did not run or was not kept."""
    return max((r._blur for r in rings if r is not None), default=0.0)


def _sizes_fit_spacing(cqs: list, marker: Marker, tol: float) -> bool:
    """Whether three outer ellipses (centre, Q) c0, c1, c2 have the size their spacing
    implies: the affine map from the marker's layout to the three centres scales a circle's
    area by |det A|, so each ring's area should be about pi R^2 |det A| (perspective and the
    edge fit's error stay well within ``tol`` squared)."""
    A = layout_affine(np.array([cq[0] for cq in cqs], np.float64), marker.centers2d)
    expected = np.pi * marker.outer_radius**2 * abs(np.linalg.det(A))
    areas = np.array([np.pi / np.sqrt(max(np.linalg.det(cq[1]), 1e-30)) for cq in cqs])
    return bool(expected > 0 and np.all(np.abs(np.log(areas / expected)) <= 2 * np.log(tol)))


def _unrefined(rings: list) -> list:
    """The rings of a view, none counted as refined (where the edge fit had refined any)."""
    if not any(r.refined for r in rings):
        return rings
    return [replace(r, refined=False, _rejected=True) for r in rings]


def _blur_fit_due(rings: list, marker: Marker, c: dict) -> bool:
    """Whether :func:`refine_blurred` fits ``rings``: the fit is on, every ring has an
    ellipse, the edges are wide (or no ring was edge-refined, where conf allows that) and,
    for three rings, their sizes fit their spacing."""
    if not c["blur_fit"] or len(rings) < 2 or any(r is None or r._outer_cq is None for r in rings):
        return False
    minor = min(minor_semi_axis(r._outer_cq[1]) for r in rings)
    # Where the plate's blurred edge reached an edge fit's rays, half that blur is enough:
    # the edge fit has lost (or kept) the rays along the motion there, and the model leaves
    # out the pixels the plate's edge reaches.
    half = 0.5 if any(r._plate_reached for r in rings) else 1.0
    wide = max(r._edge_width for r in rings)
    long_blur = (
        c["blur_fit_long_px"] > 0
        and wide >= c["blur_fit_long_px"]
        and wide >= half * c["blur_fit_long_width"] * minor
        and float(np.median([r._edge_even for r in rings])) <= c["blur_fit_long_even"]
    )
    if any(r.refined for r in rings) and wide < half * c["blur_fit_width"] * minor and not long_blur:
        return False
    if not c["blur_fit_unrefined"] and not any(r.refined for r in rings):
        return False
    if len(rings) == 3 and not _sizes_fit_spacing([r._outer_cq for r in rings], marker, c["blur_fit_size_tol"]):
        return False
    return True


def _fit_blurred(gray: np.ndarray, rings: list, marker: Marker, c: dict, noise: float | None, camera: Camera | None = None) -> dict | None:
    """The blurred-ring model fit of ``rings`` (:func:`markerpose.blurfit.fit_blurred_rings`),
    started from their edge-fitted outer ellipses; None where it fails."""
    from . import blurfit

    noise = noise_sigma(gray) if noise is None else noise
    rho = marker.inner_diameter / marker.outer_diameter
    # Seeds where no edge fitted are worth the fit only if the image there is blurred. A
    # fit whose centres wander well beyond the move kept below is given up early.
    fit_conf = {"max_move": 2 * c["blur_fit_max_move"], "block_fit": c["blur_fit_blocks"]}
    if not c["blur_fit_tangents"]:
        fit_conf["tangent_smooth"] = 0.0
    if not any(r.refined for r in rings):
        fit_conf["min_length"] = 10.0
    plate = plate_sides(rings, marker, camera) if _plate_near(marker, c) else None
    # A frame's gray view as it is (uint8): the fit reads only the pixels around the rings.
    pixels = gray if gray.ndim == 2 and gray.dtype == np.uint8 and gray.flags.c_contiguous else to_gray(gray)
    return blurfit.fit_blurred_rings(pixels, [r._outer_cq for r in rings], rho, noise, fit_conf, plate)


def refine_blurred(
    gray: np.ndarray,
    rings: list,
    marker: Marker = Marker(),
    conf: dict | None = None,
    noise: float | None = None,
    limits: BlurLimits | None = None,
    camera: Camera | None = None,
) -> list:
    """The marker's edge-refined rings, fitted again together under a motion-blur model
    when their edges are wide (:mod:`markerpose.blurfit`; conf["blur_fit"]).

    Under linear motion blur longer than the black band the edge fit of
    :func:`refine_ring` is noisy and biased along the motion (pixels off under the
    heaviest blur); the model fit uses every pixel around the three rings. It runs when every
    ring has an ellipse and either the widest edge-refined outer edge (75th percentile
    of its 10-90 % widths) exceeds conf["blur_fit_width"] times the smallest ring's minor
    semi-axis (the blur nears the black band's width), or conf["blur_fit_long_width"] times
    it where it is also conf["blur_fit_long_px"] px wide and the widths are uneven around
    the rings (conf["blur_fit_long_even"]: long motion blur), or no ring could be
    edge-refined;
    a ring the edge fit gave up on (e.g. for a neighbour's blur) is fitted too. When a
    fitted centre lies farther than conf["blur_fit_max_move"] px from the edge fit's
    (of a ring the edge fit refined), the two disagree and no ring is refined: under that
    much blur the edge fit itself can be that far off, and a pose from it would be wrong.
    When only a ring the edge fit gave up on moves that far, the edge fit is kept. Where
    the fit is due (edge-fitted rings with edges that wide) but may not run — the
    ring-evidence gate (``limits.gate``) refuses the three rings or the detection's
    budget of fits (``limits.budget``) is spent — no ring is refined either.
    Three rings whose sizes do not fit their spacing (not the marker) are left alone. With a camera the
    edge fit's distortion correction (the shift from the distorted-image ellipse's
    centre to the undistorted one's) carries over.

    Returns the rings: refitted, unchanged, or unrefined where the two fits disagree.
    """
    c = _merge_conf(conf)
    kept = _blur_kept(gray, rings, marker, c, limits)
    if kept is not None:
        return kept
    return _blur_outcome(rings, _fit_blurred(gray, rings, marker, c, noise, camera), c, camera)


def refine_blurred_views(grays: list, views: list, markers: list, c: dict, noises: list, limits: list, cameras: list) -> list:
    """:func:`refine_blurred` of each view's rings (``views``, with per view its marker,
    noise, :class:`BlurLimits` and camera), the fits that are due two at a time on two
    cores: they run mostly in compiled code and BLAS, outside Python's lock. Whether each
    view's fit runs (its gate, the budget) is decided in the views' order; every other fit
    that is due begins on the worker thread as soon as it is decided, so that the next
    view's gate runs beside it, and the rest run here once all are decided. Each fit's
    outcome (:func:`_blur_outcome`) is taken on the thread that fitted it."""

    def fit(k):
        return _blur_outcome(views[k], _fit_blurred(grays[k], views[k], markers[k], c, noises[k], cameras[k]), c, cameras[k])

    kept, fits, here = [], {}, []
    for k, (g, r, mk, lim) in enumerate(zip(grays, views, markers, limits)):
        kept.append(_blur_kept(g, r, mk, c, lim))
        if kept[-1] is None:
            if (len(fits) + len(here)) % 2 == 0:
                fits[k] = _WORKER.later(fit, k)
            else:
                here.append(k)
    done = {k: fit(k) for k in here}
    done.update({k: f.result() for k, f in fits.items()})
    return [r if r is not None else done[k] for k, r in enumerate(kept)]


_WORKER = Worker()  # the second of two blurred-ring fits at once


def _blur_kept(gray: np.ndarray, rings: list, marker: Marker, c: dict, limits: BlurLimits | None) -> list | None:
    """None where the blurred-ring fit of ``rings`` is to run; else the rings as they stay:
    unchanged where the fit is not due, unrefined where it is due but may not run."""
    if not _blur_fit_due(rings, marker, c):
        return rings
    # Wide edges the model may not check (the ring-evidence gate refuses them, or the
    # detection's budget of fits is spent) are not trusted either: under that much blur the
    # edge fit alone can be pixels off and still pass every check of the pose.
    limits = limits or BlurLimits()
    if limits.gate is not None and not limits.gate(gray, np.array([r.center for r in rings], np.float64)):
        return _unrefined(rings)
    if limits.budget is not None and not limits.budget.take():
        return _unrefined(rings)
    return None


def _blur_outcome(rings: list, fit: dict | None, c: dict, camera: Camera | None = None) -> list:
    """``rings`` after their blurred-ring fit ``fit`` (None: it failed): refitted, unchanged,
    or unrefined where the two fits disagree; ``camera``: the view's, for the centres'
    distortion correction (:func:`_blur_fitted`)."""
    if fit is None:
        return rings
    # A fit that gave up (a centre beyond twice the bound) stopped with that centre far.
    far = [
        not (np.all(np.isfinite(cen)) and np.linalg.norm(cen - r._outer_cq[0]) <= c["blur_fit_max_move"])
        for r, (cen, _) in zip(rings, fit["cqs"])
    ]
    if any(f and r.refined for f, r in zip(far, rings)):
        # The blur model puts a ring far from where its edges were fitted: under such blur
        # the edge fit can be as far off, so neither is trusted.
        return _unrefined(rings)
    if any(far) or fit["gave_up"]:  # a seed the edge fit gave up on went astray: the edge fit stands
        return rings
    return _blur_fitted(rings, fit, camera if c["center"] == "outer" else None)


def _blur_fitted(rings: list, fit: dict, camera: Camera | None = None) -> list:
    """``rings`` with the blurred-ring fit's outer ellipses. Each centre is, with ``camera``,
    that of the ellipse in ideal pixels (:func:`_ideal_centres`) as the edge fit takes it;
    without, moved as the edge fit's own correction moved it (none without a camera; the
    concentric centre's)."""
    ideal = None if camera is None else _ideal_centres(fit["cqs"], camera)
    out = []
    for k, (r, (cen, Q), cov) in enumerate(zip(rings, fit["cqs"], fit["center_covs"])):
        # Under heavy blur the edge fit's points are biased along the motion, and its own
        # correction (fitted to them) with them: the fitted ellipse's is exact.
        shift = r.center - r._outer_cq[0] if ideal is None else ideal[k] - cen
        out.append(
            replace(r, center=cen + shift, outer=cq_to_rect(cen, Q), refined=True, _outer_cq=(cen, Q), _blur=fit["length"], _center_cov=cov)
        )
    return out


_IDEAL_SAMPLES = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)


def _ideal_centres(cqs: list, camera: Camera) -> np.ndarray:
    """(n, 2) the centres, in the image's pixels, of the ellipses (centre, Q) ``cqs`` of
    the distorted image refitted in ideal pixels (points on each, undistorted, fitted,
    the centre mapped back): where a circle's image is an ellipse, as the edge fit takes
    a ring's centre (:func:`_image_centres`). A centre whose refit fails stays."""
    unit = np.stack([np.cos(_IDEAL_SAMPLES), np.sin(_IDEAL_SAMPLES)], 1)
    cen = np.array([cq[0] for cq in cqs], np.float64)
    half = edges._spd2(np.array([cq[1] for cq in cqs], np.float64), -0.5)[0]  # Q^-1/2: the unit circle onto each ellipse
    P = cen[:, None, :] + unit @ half  # Q^-1/2 is symmetric
    ideal = camera.undistort_points(P.reshape(-1, 2)).reshape(P.shape)
    ci, _, ok = edges.fit_ellipses(ideal, np.ones(P.shape[:2], bool))
    mapped = _ideal_to_pixels(camera, ci)
    return np.where(ok[:, None] & np.isfinite(mapped), mapped, cen)


# --- IDs from the layout -------------------------------------------------------------------
def find_triples(rings: list[Ring], marker: Marker = Marker(), conf: dict | None = None) -> list[tuple[float, tuple[int, int, int]]]:
    """Ordered triples of candidates that look like the marker, best first.

    Each candidate's outer ellipse is the affine image of a circle of one outer radius, so
    the symmetric square root W of the triple's mean quadratic form maps the image to the
    marker plane up to a rotation and the residual perspective: ``W (p - p0)`` is in outer
    radii. A rotation+scale fit (no reflection) to the marker's centres (y flipped, as seen
    in a y-down image) scores the triple; its signed area must be negative (mirror images
    never occur physically).

    Args:
        rings: candidates from :func:`find_rings`.
    Returns:
        list of (cost, (i0, i1, i2)) with ``rings[i_k]`` the candidate for ring c_k, lowest
        cost first, at most conf["max_triples"].
    """
    c = _merge_conf(conf)
    n = len(rings)
    if n < 3:
        return []
    ro = marker.outer_radius
    M = marker.centers2d / ro * np.array([1.0, -1.0])  # marker layout as seen (y down), outer radii
    P = np.array([r.center for r in rings])
    Qs = np.array([r._outer_cq[1] for r in rings])
    major = np.array([max(r.outer[1]) for r in rings])
    idx = _spaced_triples(M, P, Qs, major, c)
    out = []
    Mc = M - M.mean(0)
    wm = Mc[:, 0] + 1j * Mc[:, 1]
    for i0, i1, i2 in idx:
        tri = (int(i0), int(i1), int(i2))
        cost = _triple_cost(tri, rings, P, Qs, major, wm, c)
        if cost is not None:
            out.append((float(cost), tri))
    out.sort(key=lambda x: x[0])
    return out[: c["max_triples"]]


def _spaced_triples(M: np.ndarray, P: np.ndarray, Qs: np.ndarray, major: np.ndarray, c: dict) -> np.ndarray:
    """Index triples (T, 3) of distinct candidates whose three pairwise distances, in outer
    radii under each pair's mean ellipse, match the layout ``M``'s (3, 2) within
    conf["prune_tol"], their sizes within conf["size_ratio_max"]; P: (N, 2) centres,
    Qs: (N, 2, 2) outer forms, major: (N,) major axes."""
    dm = {(i, j): np.linalg.norm(M[i] - M[j]) for i, j in ((0, 1), (0, 2), (1, 2))}
    # Pairwise distances in outer radii under the pair's mean ellipse.
    D = P[:, None, :] - P[None, :, :]
    Qp = 0.5 * (Qs[:, None] + Qs[None, :])
    R = np.sqrt(np.einsum("abi,abij,abj->ab", D, Qp, D))
    sz = np.maximum(major[:, None], major[None, :]) / np.minimum(major[:, None], major[None, :])
    okz = sz <= c["size_ratio_max"]
    tol = c["prune_tol"]

    def near(d):
        return okz & (np.abs(R / d - 1) < tol)

    A01, A02, A12 = near(dm[0, 1]), near(dm[0, 2]), near(dm[1, 2])
    idx = np.argwhere(A01[:, :, None] & A02[:, None, :] & A12[None, :, :])
    return idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])]


def _triple_cost(tri: tuple, rings: list, P: np.ndarray, Qs: np.ndarray, major: np.ndarray, wm: np.ndarray, c: dict):
    """The cost of the ordered triple ``tri`` as the marker (layout, scale and shape
    misfits and the candidates' scores), or None where it fails a check (handedness, sizes,
    shapes, layout, scale); wm: (3,) the layout's centred points as complex numbers."""
    p = P[list(tri)]
    v1, v2 = p[1] - p[0], p[2] - p[0]
    if v1[0] * v2[1] - v1[1] * v2[0] >= 0:  # handedness: c0→c1→c2 negative in y-down images
        return None
    if major[list(tri)].max() / major[list(tri)].min() > c["size_ratio_max"]:
        return None
    shp = [_log_shape(Qs[k]) for k in tri]
    dshape = max(np.linalg.norm(shp[a] - shp[b]) for a, b in ((0, 1), (0, 2), (1, 2)))
    if dshape > c["triple_shape_tol"]:
        return None
    W = sqrtm_spd(Qs[list(tri)].mean(0))
    q = (p - p.mean(0)) @ W.T
    z = q[:, 0] + 1j * q[:, 1]
    alpha = np.vdot(wm, z) / np.vdot(wm, wm)
    res = z - alpha * wm
    rel = float(np.sqrt((np.abs(res) ** 2).sum() / (np.abs(z) ** 2).sum()))
    scale = abs(alpha)
    if rel > c["layout_tol"] or not (1 / c["scale_tol"] <= scale <= c["scale_tol"]):
        return None
    return (
        (rel / c["layout_tol"]) ** 2
        + (np.log(scale) / np.log(c["scale_tol"])) ** 2
        + (dshape / c["triple_shape_tol"]) ** 2
        + sum(1.0 - rings[k].score for k in tri)
    )


def view_triples(image: np.ndarray, marker: Marker = Marker(), conf: dict | None = None) -> tuple:
    """One view's ring candidates and its marker-like triples (paper §3.4, steps 1-4).

    Returns:
        (gray (H, W) float32, noise sigma, rings, triples as :func:`find_triples` returns them).
    """
    c = _merge_conf(conf)
    gray = to_gray(image)
    noise = noise_sigma(gray)
    rings = _find_rings_gray(gray, marker, c, noise)
    return gray, noise, rings, find_triples(rings, marker, c)


def refine_triple(gray, rings, tri, cost, marker, subpixel, conf, noise, camera, limits: BlurLimits | None = None) -> Detection:
    """The Detection of the triple ``tri`` of ``rings``: sub-pixel edges (and the blurred-ring
    fit, within ``limits``) with ``subpixel``, else the contour ellipses' centres (the paper)."""
    c = _merge_conf(conf)
    chosen = [rings[k] for k in tri]
    if subpixel:
        chosen = refine_views([gray], [chosen], marker, c, [noise], [camera])[0]
        chosen = refine_blurred(gray, chosen, marker, c, noise, limits, camera)
    centers = np.array([r.center for r in chosen], dtype=np.float64)
    return Detection(
        centers=centers,
        ellipses=[r.outer for r in chosen],
        score=float(np.exp(-0.5 * cost)),
        refined=np.array([not r._rejected for r in chosen]),
        blur_px=_blur_length(chosen),
        center_cov=_center_covs(chosen) if subpixel else None,
    )


def detect(
    image: np.ndarray,
    marker: Marker = Marker(),
    subpixel: bool = True,
    conf: dict | None = None,
    camera: Camera | None = None,
) -> Detection | None:
    """The marker in one view, IDs from the layout.

    Args:
        image: uint8 gray (H, W) or BGR (H, W, 3).
        marker: the marker geometry.
        subpixel: True (default) → sub-pixel edge refinement; False → the paper's centre of
            ``cv2.fitEllipse`` on the outer contour.
        conf: overrides of :data:`default_conf`.
        camera: the camera that took the image, optional: with it the sub-pixel ellipses
            are fitted in undistorted coordinates (see :func:`refine_ring`).
    Returns:
        :class:`~markerpose.results.Detection` (centres (3, 2) by ID, outer ellipses) or
        None when no marker-like triple is found.
    """
    gray, noise, rings, triples = view_triples(image, marker, conf)
    if not triples:
        return None
    cost, tri = triples[0]
    return refine_triple(gray, rings, tri, cost, marker, subpixel, conf, noise, camera)


def _shift_ring(ring: Ring, d: np.ndarray) -> Ring:
    """The same ring in a frame shifted by ``d`` (ROI → full image)."""

    def rect(r):
        return ((r[0][0] + d[0], r[0][1] + d[1]), r[1], r[2])

    def cq(v):
        return None if v is None else (v[0] + d, v[1])

    return replace(
        ring,
        center=ring.center + d,
        outer=rect(ring.outer),
        inner=rect(ring.inner),
        _outer_cq=cq(ring._outer_cq),
        _inner_cq=cq(ring._inner_cq),
    )


def _ring_near(gray: np.ndarray, p: np.ndarray, half: int, r_est: float, marker: Marker, c: dict, noise: float) -> Ring | None:
    """The ring candidate (:func:`find_rings`) of the window of ``half`` px around the
    point ``p`` nearest it, within 0.6 ring radii ``r_est`` + 4 px, in image px; None if none."""
    h, w = gray.shape
    x0, y0 = max(int(p[0]) - half, 0), max(int(p[1]) - half, 0)
    x1, y1 = min(int(p[0]) + half + 1, w), min(int(p[1]) + half + 1, h)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    roi = gray[y0:y1, x0:x1]
    cands = _find_rings_gray(roi, marker, c, noise)
    off = np.array([x0, y0], np.float64)
    best = None
    for r in cands:
        dist = np.linalg.norm(r.center + off - p)
        if dist < 0.6 * r_est + 4 and (best is None or dist < best[0]):
            best = (dist, r)
    return None if best is None else _shift_ring(best[1], off)


def refine_points(
    image: np.ndarray,
    points: np.ndarray,
    marker: Marker = Marker(),
    subpixel: bool = True,
    conf: dict | None = None,
    camera: Camera | None = None,
    detail: bool = False,
    noise: float | None = None,
    limits: BlurLimits | None = None,
) -> tuple:
    """Classical sub-pixel centres of the rings near given rough points (e.g. stage 1's).

    Each point gets a window of about four ring radii (the radius judged from the spacing
    of the three points), the ring candidates of that window (:func:`find_rings`), the
    candidate nearest the point, and its sub-pixel ellipse (:func:`refine_ring`).

    Args:
        image: uint8 gray (H, W) or BGR.
        points: (3, 2) rough centres c0, c1, c2, px.
        marker, subpixel, conf, camera: as in :func:`detect`.
        detail: also return the motion blur and the centres' covariances (as
            :func:`refine_ellipses_views` does).
        noise: the image's noise sigma if known (else :func:`noise_sigma`).
        limits: what may stop the blurred-ring fit (:class:`BlurLimits`; None: nothing).
    Returns:
        (centers (3, 2), found (3,) bool, ellipses): where no ring is found near a point,
        its centre is the input point, ``found`` is False and its ellipse None; with
        ``detail``, the blur length (px) and the centres' covariances (3, 2, 2) as a
        fourth and fifth item.
    """
    c = _merge_conf(conf)
    gray = to_gray(image)
    pts = np.asarray(points, np.float64).reshape(3, 2)
    if not np.isfinite(pts).all():
        raise ValueError(f"points must be finite, got {pts.tolist()}")
    r_est = max(ring_diameter(pts, marker) / 2, 4.0)
    half = int(np.ceil(2.2 * r_est)) + 4
    noise = noise_sigma(gray) if noise is None else float(noise)
    rings: list[Ring | None] = [_ring_near(gray, p, half, r_est, marker, c, noise) for p in pts]
    found = np.array([r is not None for r in rings])
    if subpixel:
        rings = refine_views([gray], [rings], marker, c, [noise], [camera])[0]
        rings = refine_blurred(gray, rings, marker, c, noise, limits, camera)
        rings = [None if r is not None and r._rejected else r for r in rings]  # not trusted (refine_blurred)
        found = np.array([r is not None for r in rings])
    centers = np.array([pts[i] if r is None else r.center for i, r in enumerate(rings)], np.float64)
    out = (centers, found, [None if r is None else r.outer for r in rings])
    return (*out, _blur_length(rings), _center_covs(rings)) if detail else out


def refine_ellipses(
    image: np.ndarray,
    ellipses: list,
    marker: Marker = Marker(),
    conf: dict | None = None,
    camera: Camera | None = None,
    limits: BlurLimits | None = None,
) -> tuple[np.ndarray, np.ndarray, list]:
    """Sub-pixel outer ellipses of rings whose approximate outer ellipses are known (e.g.
    fitted to EllipSegNet's masks): the image's edges are sampled along rays of each
    ellipse and fitted again (:func:`refine_ring`), then the blurred-ring fit where the
    edges are wide (:func:`refine_blurred`).

    Args:
        image: uint8 gray (H, W) or BGR.
        ellipses: per ring, an approximate outer ellipse (RotatedRect) or None.
        marker, conf, camera: as in :func:`detect`.
        limits: what may stop the blurred-ring fit (:class:`BlurLimits`; None: nothing).
    Returns:
        (centers (N, 2), refined (N,) bool, ellipses): where the edges could not be fitted
        (None given, too few edge points) the given ellipse's centre is kept (NaN for
        None) and ``refined`` is False.
    """
    return refine_ellipses_views([image], [ellipses], marker, conf, [camera], limits=limits)[0]


def refine_ellipses_views(
    images: list,
    ellipses: list,
    marker: Marker = Marker(),
    conf: dict | None = None,
    cameras: list | None = None,
    noises: list | None = None,
    detail: bool = False,
    limits: BlurLimits | list | None = None,
    markers: list | None = None,
) -> list:
    """:func:`refine_ellipses` of several views (e.g. both of a stereo pair), their edge
    fits in one batch (each ring with its marker's edge windows, :func:`_edge_windows`).

    Args:
        images: per view, uint8 gray (H, W) or BGR.
        ellipses: per view, a list of approximate outer ellipses (RotatedRect) or None.
        markers: per view, the marker whose rings they are (None: ``marker`` for all); an
            image may come more than once, with another marker's rings.
        cameras: per view, a Camera or None.
        noises: per view, the image's noise sigma if known (else :func:`noise_sigma`).
        detail: also return each view's motion blur and its centres' covariances.
        limits: what may stop the blurred-ring fits (:class:`BlurLimits`, or per view one;
            None: nothing).
    Returns:
        per view, (centers, refined, ellipses) as :func:`refine_ellipses` returns them;
        with ``detail`` (centers, refined, ellipses, blur, covariances): ``blur`` is the motion blur
        length (px) the blurred-ring fit found, 0 where it did not run or was not kept;
        ``covariances`` (n, 2, 2) the centres' covariances, px^2, from their fits' residuals
        (:func:`markerpose.edges.center_covariances`, or the blurred-ring fit's), NaN where
        a centre is not refined.
    """
    c = _merge_conf(conf)
    grays = [as_gray(im, f"view {v}", allow_float=True) for v, im in enumerate(images)]  # 8-bit stays 8-bit: no float copy
    noises = _noises(grays, noises)
    markers = [marker] * len(grays) if markers is None else list(markers)
    views = []
    for rects, mk in zip(ellipses, markers):
        rho = mk.inner_diameter / mk.outer_diameter
        rings = []
        for rect in rects:
            if rect is None:
                rings.append(None)
                continue
            (cx, cy), (w, h), ang = rect
            inner = ((cx, cy), (w * rho, h * rho), ang)
            cq = rect_to_cq(rect)  # the hole's is the same ellipse scaled by rho
            rings.append(Ring(np.array([cx, cy], np.float64), tuple(rect), inner, 1.0, _outer_cq=cq, _inner_cq=(cq[0], cq[1] / rho**2)))
        views.append(rings)
    out = []
    cameras = cameras if cameras is not None else [None] * len(grays)
    fitted = refine_views(grays, views, markers[0] if all(mk is markers[0] for mk in markers) else markers, c, noises, cameras)
    per_view = limits if isinstance(limits, list) else [limits] * len(grays)
    for rings in refine_blurred_views(grays, fitted, markers, c, noises, per_view, cameras):
        centers = np.array([[np.nan, np.nan] if r is None else r.center for r in rings], np.float64).reshape(-1, 2)
        ok = np.array([r is not None and r.refined for r in rings], bool)
        found = (centers, ok, [None if r is None else r.outer for r in rings])
        out.append((*found, _blur_length(rings), _center_covs(rings)) if detail else found)
    return out


__all__ = [
    "BlurLimits",
    "FitBudget",
    "Ring",
    "default_conf",
    "to_gray",
    "noise_sigma",
    "noise_stride",
    "noise_from_residuals",
    "noise_sigmas",
    "binarize",
    "find_rings",
    "refine_ring",
    "fit_ellipse",
    "concentric_center",
    "find_triples",
    "detect",
    "refine_ellipses",
    "refine_ellipses_views",
    "refine_views",
    "refine_points",
    "refine_blurred",
    "refine_triple",
    "view_triples",
]
