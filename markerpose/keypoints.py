"""Stage 1: the SuperPoint-like network that finds the three ring centres and their IDs.

The image is resized to 320x240 (the paper's input), a VGG-style encoder brings it to
H/8 x W/8 cells, and two heads classify every cell:

- the detector head (65 channels): which of the 64 pixels of the 8x8 cell holds a ring
  centre, or channel 64, "no centre here";
- the ID head (4 channels): c0, c1, c2 or background.

Decoding (:func:`decode`) turns the two heads into at most one point per ID: softmax,
depth-to-space score map, non-maximum suppression, a threshold, then the best triple of
candidates whose ID assignment is consistent with the marker (distinct IDs, the right
handedness). Points are scaled back to the full-resolution image.

The network needs torch; the decoding and the training targets are numpy functions.
"""

from __future__ import annotations

import itertools
import warnings
from pathlib import Path

import cv2
import numpy as np

from .geometry import layout_affine
from .marker import Marker
from .nets import fuse_batchnorm

ALIGN_MOVE_RULES = ("spacing", "nearest")  # when align_triple takes an alignment as slid onto a neighbour (see default_conf)
ID_MODES = ("head", "layout")  # how decoding assigns ring IDs (see default_conf["ids"])
INPUT_SIZE = (320, 240)  # (width, height) the paper resizes every image to
CELL = 8
PAPER_WIDTHS = (64, 64, 64, 64, 128, 128, 128, 128)
PAPER_HEAD = 256

default_conf = {
    "width": 1.0,  # multiplier of the paper's layer widths (1.0 = the paper's network)
    "nms_radius": 2,  # px at 320x240 (v0.8: 4): a steeply tilted marker puts two ring centres
    #                   ~6 px apart, and a radius of 4 kept one candidate between them
    "threshold": 0.05,  # minimum location score of a candidate
    "max_candidates": 10,  # best candidates kept after NMS, per image (v0.8: 8)
    "min_id_prob": 0.2,  # an assigned ID must have at least this probability at its point
    "min_score": 0.15,  # geometric mean of the three points' (score x ID probability)
    # How IDs are assigned to a triple of candidates:
    #   "head"   (paper): by the ID head, with the handedness check;
    #   "layout" (ours): by the marker's shape. Of the three orders with the right
    #            handedness, the one whose affine map from the marker's layout is closest
    #            to a foreshortened similarity (largest singular-value ratio), the ID
    #            head's probabilities entering with exponent ``id_weight``. The ID head
    #            sees ~40 px of the 320x240 input, less than the marker spans, so on its
    #            own it often cannot tell the rings apart.
    "ids": "layout",
    "min_ratio": 0.35,  # layout: minimum singular-value ratio (cos 60° = 0.5, less perspective)
    "id_weight": 0.25,  # layout: exponent of the ID head's probabilities in the score
    # Ours: weigh every triple by how much the image around it looks like the printed
    # marker (ring_evidence: dark bands on one white plate, paper-white inside the rings);
    # decoys that merely sit in a marker-like triangle do not. Needs the image.
    "verify": False,
    # Ours: an image in which the first pass finds no marker is looked at again, this many
    # times larger (1: no second look). Rings under ~12 px at 320x240 are found far more
    # often at 2x; the cost is one forward pass zoom² as large, paid by every image
    # without a marker found. The second look keeps a triple only with a score of at
    # least ``look_min_score`` (None: ``min_score``); export tunes it so that both looks
    # together stay within the single-view false-positive budget.
    "second_look": 1.0,
    "look_min_score": None,
    # Ours: the chosen triple is refined by aligning the marker's printed pattern to the
    # image (align_triple: ECC, a homography; the triple gives the start), then scored
    # again. Stage 1's points sit on the network's 8-px cells and are ~1 input px off;
    # aligned, ~0.2 px — a triple whose points are a few pixels off is then still found.
    # Needs the image.
    "align": False,
    # Ours (v0.13), layout IDs: the layout ratio's factor in a triple's score is
    # min(1, ratio / ratio_full) (None: the ratio itself, as up to v0.12). A marker tilted
    # by 60° has a ratio of ~0.5 and was scored down 2x against a frontal decoy; blurred,
    # steeply tilted markers then fell under min_score. Each triple's ID order is still
    # chosen by the ratio itself. Validation (400 views + 3000 marker-free, first look,
    # alignment, <= 0.5 % FP): 94.4 % detected with None, 95.1 % with 0.5.
    "ratio_full": 0.5,
    # Ours (v0.14), with align: the best ``align_top`` triples (each in its best ID order)
    # are aligned and scored again, and the best of them after alignment wins (up to
    # v0.13: the best one alone). Triples enter with a layout ratio of at least
    # ``align_min_ratio`` (None: ``min_ratio``); after alignment they must reach
    # ``min_ratio``. Stage 1's points on a steeply tilted or blurred marker are a few
    # pixels off, enough to put its ratio under ``min_ratio`` or another triple ahead
    # of it until the alignment puts them right.
    "align_top": 3,
    "align_min_ratio": 0.25,
    # Ours (v0.15), with align: each of those triples is aligned in its ``align_orders``
    # best ID orders (of the three with the marker's handedness), and the best after
    # alignment counts. On a steeply tilted marker stage 1's points are a pixel or two
    # off, and that can make a wrong order look the most marker-like (a larger layout
    # ratio, more ring evidence) and the right one show no ring evidence at all, until
    # the alignment puts the points right. Off by default: on the validation set (the
    # v0.14 network, 400 views + 3000 marker-free) aligning all three orders let more
    # marker-free views through, the tuned min_score rose from 0.07 to 0.10 and the
    # first look found 93.4 % instead of 95.4 % (with the second look 97.36 against
    # 97.4 %), for ~1.5x the decoding time.
    "align_orders": 1,
    # Ours (v0.15), with align: an aligned triple's score is multiplied by the alignment's
    # ECC correlation to this power (0: not at all, as up to v0.15.0). A wrong triple
    # that the alignment drags onto ring-like clutter correlates worse than the marker,
    # so the threshold tuned at export can sit lower. Exported with the v0.14 network
    # (validation, 400 views + 3000 marker-free, ≤ 0.5 % false positives): with the
    # second look 97.7 % found against 97.4 % with 0.
    "align_cc_power": 2.0,
    # Ours (v0.18), with align: when an alignment is taken to have slid onto a neighbour's
    # ring, and dropped. "spacing" (up to v0.17): it moves a centre by more than 0.4 of
    # the smallest distance between two stage-1 points. "nearest": some stage-1 point
    # lies nearer another ring's refined centre than its own — what sliding onto a
    # neighbour means, with no fraction to choose. A stage-1 point 2-4 input px off
    # towards its neighbour also shrinks the distance "spacing" measures, and the right
    # alignment of a small or steep marker was dropped: in two of three held-out standard
    # misses of a v0.18 candidate network ECC had put every centre within 0.3 px of the
    # truth (correlation 0.93-0.98), moving one by 2.5 / 4.0 px against limits of
    # 1.8 / 3.6 px (runs/s23/why396.py, ad hoc).
    "align_move_rule": "nearest",
}


def layer_widths(width: float = 1.0, stem_width: float | None = None) -> tuple[tuple[int, ...], int]:
    """(encoder widths (8,), head width) for a width multiplier (1.0 = the paper's).

    ``stem_width`` (ours), when given, multiplies the first four convolutions instead —
    those at full and half resolution, which cost most of the compute: the deeper layers
    and the heads run on 16x fewer pixels, so they can be wider for little time."""
    stem = width if stem_width is None else stem_width
    enc = tuple(max(8, int(round(c * (stem if i < 4 else width)))) for i, c in enumerate(PAPER_WIDTHS))
    return enc, max(16, int(round(PAPER_HEAD * width)))


def build_network(width: float = 1.0, stem_width: float | None = None):
    """The SuperPoint-like network (torch ``nn.Module``), paper widths times ``width``
    (the first four convolutions times ``stem_width`` when given; see :func:`layer_widths`).

    Input: (B, 1, H, W) float in [0, 1], H and W multiples of 8.
    Output: (det (B, 65, H/8, W/8), ids (B, 4, H/8, W/8)) logits. Weights channels-last.
    """
    import torch
    from torch import nn

    enc, head = layer_widths(width, stem_width)

    def conv(cin, cout, k=3):
        return [nn.Conv2d(cin, cout, k, padding=k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]

    class SuperPointLike(nn.Module):
        def __init__(self):
            super().__init__()
            layers, cin = [], 1
            for i, c in enumerate(enc):
                layers += conv(cin, c)
                cin = c
                if i % 2 == 1 and i < 7:  # 2x2 max-pool after every two convs, three pools
                    layers.append(nn.MaxPool2d(2, 2))
            self.encoder = nn.Sequential(*layers)
            self.det_head = nn.Sequential(*conv(cin, head), nn.Conv2d(head, CELL * CELL + 1, 1))
            self.id_head = nn.Sequential(*conv(cin, head), nn.Conv2d(head, 4, 1))
            self.width, self.stem_width = width, stem_width

        def forward(self, x: torch.Tensor):
            f = self.encoder(x)
            return self.det_head(f), self.id_head(f)

    # Channels-last: the convolutions run faster on this CPU, in training (297 against
    # 462 ms a step at width 0.25) and inference, with the same outputs to ~1e-6.
    return SuperPointLike().to(memory_format=torch.channels_last)


# --- training targets ------------------------------------------------------------------
def make_targets(points: np.ndarray, labels: np.ndarray, size=INPUT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Cell targets of the two heads from the ring centres of one image.

    Args:
        points: (3, 2) centres c0, c1, c2 in the network input's pixels (x, y).
        labels: (3,) int: 1 = visible (a target), 0 = absent, -1 = ambiguous (ignored
            by the loss: e.g. a ring half occluded or half outside the image).
        size: (W, H) of the network input.
    Returns:
        det: (H/8, W/8) int64 in 0..64 (64 = no centre) or -100 (ignored);
        ids: (H/8, W/8) int64 in 0..3 (3 = background) or -100.
    """
    w, h = size
    det = np.full((h // CELL, w // CELL), CELL * CELL, np.int64)
    ids = np.full((h // CELL, w // CELL), 3, np.int64)
    for i, ((x, y), lab) in enumerate(zip(np.asarray(points, np.float64), labels)):
        if lab == 0 or not (np.isfinite(x) and np.isfinite(y)):
            continue
        px, py = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))  # nearest pixel centre
        if not (0 <= px < w and 0 <= py < h):
            continue
        cy, cx = py // CELL, px // CELL
        if lab < 0:
            det[cy, cx], ids[cy, cx] = -100, -100
        else:
            det[cy, cx] = (py % CELL) * CELL + px % CELL
            ids[cy, cx] = i
    return det, ids


# --- decoding --------------------------------------------------------------------------
def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def score_map(det_logits: np.ndarray) -> np.ndarray:
    """(65, Hc, Wc) detector logits → (8 Hc, 8 Wc) probability that a pixel is a centre."""
    p = _softmax(det_logits.astype(np.float64), 0)[:-1]  # drop the "no centre" channel
    hc, wc = p.shape[1:]
    return p.reshape(CELL, CELL, hc, wc).transpose(2, 0, 3, 1).reshape(hc * CELL, wc * CELL)


def nms(scores: np.ndarray, radius: int, threshold: float, k: int) -> np.ndarray:
    """Local maxima of a score map above a threshold, best first.

    Returns:
        (N, 3) rows (x, y, score), N <= k.
    """
    size = 2 * radius + 1
    scores = scores.astype(np.float32)  # compare like with like: dilate works in float32
    dil = cv2.dilate(scores, cv2.getStructuringElement(cv2.MORPH_RECT, (size, size)))
    ys, xs = np.nonzero((scores >= dil) & (scores >= threshold))
    s = scores[ys, xs]
    order = np.argsort(-s)
    kept: list[tuple[float, float, float]] = []
    for j in order:  # plateaus: drop maxima within the radius of a better one
        if all((xs[j] - x) ** 2 + (ys[j] - y) ** 2 > radius**2 for x, y, _ in kept):
            kept.append((float(xs[j]), float(ys[j]), float(s[j])))
        if len(kept) == k:
            break
    return np.array(kept, np.float64).reshape(-1, 3)


def _refine(scores: np.ndarray, x: float, y: float) -> tuple[float, float]:
    """Score-weighted centroid of the 3x3 neighbourhood: a fraction of a pixel better than the peak."""
    h, w = scores.shape
    x0, y0 = int(x), int(y)
    ys, xs = np.mgrid[max(y0 - 1, 0) : min(y0 + 2, h), max(x0 - 1, 0) : min(x0 + 2, w)]
    s = scores[ys, xs]
    return float((s * xs).sum() / s.sum()), float((s * ys).sum() / s.sum())


def candidates(det_logits: np.ndarray, id_logits: np.ndarray, threshold: float, k: int, nms_radius: int = 4):
    """The best ``k`` local maxima of the location score of one image, above ``threshold``.

    Returns:
        (cand (N, 3) rows (x, y, score), x and y refined to a fraction of a network-input
        pixel; prob (N, 3) the ID head's P(c0), P(c1), P(c2) at each candidate), N <= k.
    """
    scores = score_map(det_logits)
    cand = nms(scores, nms_radius, threshold, k)
    pid = _softmax(id_logits.astype(np.float64), 0)  # (4, Hc, Wc)
    rows = np.clip((cand[:, 1] // CELL).astype(int), 0, pid.shape[1] - 1)
    cols = np.clip((cand[:, 0] // CELL).astype(int), 0, pid.shape[2] - 1)
    prob = pid[:3, rows, cols].T  # (N, 3): P(ID = j) at candidate n
    if len(cand):
        cand[:, :2] = [_refine(scores, x, y) for x, y, _ in cand]
    return cand, prob


def signed_areas(p: np.ndarray) -> np.ndarray:
    """Signed areas of triangles p0 p1 p2 ((..., 3, 2), y down): negative for the real marker."""
    d1, d2 = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    return 0.5 * (d1[..., 0] * d2[..., 1] - d2[..., 0] * d1[..., 1])


def signed_area(p: np.ndarray) -> float:
    """Signed area of the triangle p0 p1 p2 ((3, 2), y down): negative for the real marker."""
    return float(signed_areas(np.asarray(p, np.float64)))


def layout_ratios(p: np.ndarray, layout: np.ndarray) -> np.ndarray:
    """How far image triangles ``p`` (..., 3, 2) are from views of the marker triangle
    ``layout`` (3, 2, mm), in the same ID order: the ratio of the singular values of the
    affine map between the two (1 = a similarity; a plane tilted by θ seen from afar gives
    cos θ; 0 for a degenerate triangle). Orders that put a ring in the wrong place give
    small ratios."""
    sv = np.linalg.svd(layout_affine(p, layout), compute_uv=False)  # (..., 2), largest first
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sv[..., 0] > 0, sv[..., 1] / sv[..., 0], 0.0)


def layout_ratio(p: np.ndarray, layout: np.ndarray) -> float:
    """:func:`layout_ratios` of one triangle (3, 2)."""
    return float(layout_ratios(p, layout))


_MARKER = Marker()  # the default marker
_TRIPLES: dict = {}  # n → triple_orders(n)


def triple_orders(n: int) -> np.ndarray:
    """Every triple of ``n`` points in each of its six ID orders, as indices (6 C(n, 3), 3):
    row 6 t + o is triple t (in ``itertools.combinations`` order) in order o (in
    ``itertools.permutations`` order); column j is the point taking ID j."""
    if n not in _TRIPLES:
        trios = np.array(list(itertools.combinations(range(n), 3)), int).reshape(-1, 3)
        _TRIPLES[n] = trios[:, list(itertools.permutations(range(3)))].reshape(-1, 3)
    return _TRIPLES[n]


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


# --- alignment (ours) -----------------------------------------------------------------
_TEMPLATE_PPM = 2.0  # template pixels per mm
_TEMPLATE_PAD = 3.0  # mm of plate kept around the rings' bounding box (the plate's margin is wider)
_TEMPLATES = {}  # marker → (template, its origin in mm)


def _template(marker: Marker) -> tuple[np.ndarray, np.ndarray]:
    """The printed rings and the plate around them as an image of the marker's frame
    (``_TEMPLATE_PPM`` px per mm, 4x4 supersampled) and the frame point of its pixel (0, 0)."""
    key = (tuple(marker.centers2d.ravel()), marker.outer_radius, marker.inner_radius)
    if key not in _TEMPLATES:
        c = marker.centers2d
        lo = c.min(0) - marker.outer_radius - _TEMPLATE_PAD
        w, h = np.ceil((c.max(0) + marker.outer_radius + _TEMPLATE_PAD - lo) * _TEMPLATE_PPM).astype(int)
        sub = 4
        ys, xs = np.mgrid[0 : h * sub, 0 : w * sub]
        xy = lo + (np.stack([xs, ys], -1) + 0.5) / (sub * _TEMPLATE_PPM)
        refl = np.nan_to_num(marker.reflectance(xy), nan=0.85)  # the pad lies on the plate
        img = refl.reshape(h, sub, w, sub).mean((1, 3)).astype(np.float32)
        _TEMPLATES[key] = (img, lo + 0.5 / _TEMPLATE_PPM)
    return _TEMPLATES[key]


def align_triple(image: np.ndarray, points: np.ndarray, marker: Marker | None = None,
                 iterations: int = 50, move_rule: str = "spacing") -> tuple[np.ndarray, float | None]:
    """Refine three ring centres by aligning the marker's printed pattern to the image.

    The triple fixes the affine map from the marker's frame to the image; from there
    ``cv2.findTransformECC`` (enhanced correlation, insensitive to brightness and
    contrast, so darkness does not matter) fits the homography that takes the printed
    rings onto the image, and the refined centres are the rings' centres mapped by it
    (the projected centres, not the ellipses' centres). Both images are smoothed with
    a Gaussian of ~0.7 image pixels.

    Args:
        image: (H, W) float32 in [0, 1], the image the points are in (e.g. the network input).
        points: (3, 2) centres c0, c1, c2 in that image's pixels.
        marker: the marker's geometry (default: the default marker).
        iterations: ECC's iteration limit.
        move_rule: when the alignment counts as slid onto a neighbour's ring (dropped):
            "spacing", a centre moved by more than 0.4 of the smallest distance between
            two of ``points``; "nearest", a point of ``points`` nearer another refined
            centre than its own (see ``default_conf["align_move_rule"]``).
    Returns:
        (refined (3, 2), correlation coefficient) — or (``points``, None) when the
        alignment fails, flips the marker or slides onto a neighbour's ring (``move_rule``).
    """
    if move_rule not in ALIGN_MOVE_RULES:
        raise ValueError(f"move_rule must be one of {ALIGN_MOVE_RULES}, got {move_rule!r}")
    marker = marker or _MARKER
    pts = np.asarray(points, np.float64)
    tmpl, origin = _template(marker)
    src = ((marker.centers2d - origin) * _TEMPLATE_PPM).astype(np.float32)  # template px
    spacing = _min_spacing(pts)
    if not (np.isfinite(spacing) and spacing > 0):
        return pts, None
    t = cv2.GaussianBlur(tmpl, (0, 0), 0.7 * _min_spacing(src) / spacing)  # ~0.7 image px, in template px
    img = cv2.GaussianBlur(np.ascontiguousarray(image, np.float32), (0, 0), 0.7)
    warp = np.vstack([cv2.getAffineTransform(src, pts.astype(np.float32)), [0, 0, 1]]).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-4)
    try:
        cc, warp = cv2.findTransformECC(t, img, warp, cv2.MOTION_HOMOGRAPHY, criteria, None, 1)
    except cv2.error:  # no convergence, or a degenerate start
        return pts, None
    q = cv2.perspectiveTransform(src[None].astype(np.float64), warp.astype(np.float64))[0]
    if not np.all(np.isfinite(q)) or signed_area(q) >= 0:
        return pts, None
    dist = np.linalg.norm(pts[:, None] - q[None], axis=2)  # [i, j]: stage-1 point i to refined centre j
    if move_rule == "spacing":
        slid = np.diag(dist).max() > 0.4 * spacing
    else:
        slid = np.any(np.argmin(dist, axis=1) != np.arange(3))
    if slid:
        return pts, None
    return q, float(cc)


def _ratio_weight(r, full):
    """The layout ratio's factor in a triple's score: the ratio itself (``full`` None), or
    ``min(1, r / full)``: a marker tilted by up to arccos(full) is not scored down."""
    r = np.asarray(r, np.float64)
    return r if full is None else np.minimum(1.0, r / full)


def _min_spacing(p: np.ndarray) -> float:
    """The smallest distance between two of three points (3, 2)."""
    return float(min(np.linalg.norm(p[a] - p[b]) for a, b in ((0, 1), (0, 2), (1, 2))))


def decode(det_logits: np.ndarray, id_logits: np.ndarray, conf: dict | None = None, marker: Marker | None = None,
           image: np.ndarray | None = None):
    """The three ring centres and their IDs from the two heads of one image.

    Args:
        det_logits: (65, Hc, Wc) detector-head logits.
        id_logits: (4, Hc, Wc) ID-head logits.
        conf: overrides of :data:`default_conf`.
        marker: the marker's geometry, for ``ids="layout"`` and ``verify`` (default: the
            default marker).
        image: (H, W) float32 in [0, 1], the network's input: needed by ``verify``.
    Returns:
        (points (3, 2) in network-input pixels ordered by ID, score) or None when no
        consistent triple is found.

    The ID head gives each candidate a distribution over c0, c1, c2, background; the
    triple and the assignment of IDs maximise the product of (location score x ID
    probability) over the three points, subject to distinct IDs and the marker's
    handedness (c0 → c1 → c2 turns the same way in every real image). A collision (two
    points claiming the same ID) is thereby repaired by the second-best assignment, and
    a triple that no assignment makes consistent is rejected. With ``ids="layout"`` the
    marker's shape chooses the order instead (see :data:`default_conf`), and triples
    compete with the layout ratio softened by ``ratio_full``. With ``verify``
    every allowed (triple, order) is then weighed by :func:`ring_evidence`. With
    ``align`` the ``align_top`` best triples are refined by :func:`align_triple` and
    scored again (layout ratio and evidence of the refined points); the best of them,
    and ``min_score``, decide.
    """
    c = {**default_conf, **(conf or {})}
    if c["ids"] not in ID_MODES:
        raise ValueError(f"ids must be one of {ID_MODES}, got {c['ids']!r}")
    for need in ("verify", "align"):
        if c[need] and image is None:
            raise ValueError(f"decoding with {need}=True needs the image")
    marker = marker or _MARKER
    layout = marker.centers2d
    cand, prob = candidates(det_logits, id_logits, c["threshold"], c["max_candidates"], c["nms_radius"])
    if len(cand) < 3:
        return None
    # Every triple of candidates in every ID order at once: idx[m, j] = the candidate taking ID j.
    idx = triple_orders(len(cand))
    p = cand[idx, :2]  # (M, 3, 2)
    p_id = prob[idx, [0, 1, 2]]  # (M, 3)
    keep = signed_areas(p) < 0  # the marker's handedness; degenerate triples out
    if c["ids"] == "head":
        keep &= p_id.min(1) >= c["min_id_prob"]
        s, r = np.prod(cand[idx, 2] * p_id, axis=1) ** (1 / 3), np.ones(len(idx))
    else:
        r = layout_ratios(p, layout)
        loose = c["align"] and c["align_min_ratio"] is not None
        keep &= r >= (c["align_min_ratio"] if loose else c["min_ratio"])
        s = np.prod(cand[idx, 2], axis=1) ** (1 / 3) * np.prod(p_id, axis=1) ** (c["id_weight"] / 3)
    if not keep.any():
        return None
    ev = np.ones(len(p))
    if c["verify"]:
        ev[keep] = ring_evidence(image, p[keep], marker)
    # Each triple in its best ID order (a wrong order puts a ring in the wrong place:
    # a small ratio), then the triples against each other — with the softened ratio, so
    # a steeply tilted marker is not outscored by a flatter decoy (ratio_full; the ID
    # mode "head" has no ratio: r = 1).
    per_triple = np.where(keep, s * r * ev, -1.0).reshape(-1, 6)
    rows = np.arange(len(per_triple)) * 6 + np.argmax(per_triple, axis=1)
    rows = rows[per_triple.max(1) >= 0]
    value = s[rows] * _ratio_weight(r[rows], c["ratio_full"]) * ev[rows]
    order = np.argsort(-value, kind="stable")
    if not c["align"]:
        best, score = p[rows[order[0]]], float(value[order[0]])
    else:
        best, score = None, -1.0
        for j in order[: max(1, int(c["align_top"]))]:
            k = rows[j]
            t = k // 6  # the triple; its handedness-consistent orders, best first
            tried = 6 * t + np.argsort(-per_triple[t], kind="stable")[: max(1, int(c["align_orders"]))]
            for o in tried[per_triple[t, tried % 6] >= 0]:
                if s[o] < c["min_score"]:
                    # Every factor below is at most 1, so this order cannot reach min_score:
                    # its alignment (the costly part) could not change the result.
                    continue
                q, cc = align_triple(image, p[o], marker, move_rule=c["align_move_rule"])
                rq = layout_ratio(q, layout) if c["ids"] == "layout" else 1.0  # "head": r = 1 throughout
                if cc is not None and rq >= c["min_ratio"]:
                    found = float(s[o] * _ratio_weight(rq, c["ratio_full"])) * max(cc, 0.0) ** float(c["align_cc_power"])
                    if c["verify"]:
                        found *= float(ring_evidence(image, q[None], marker)[0])
                elif o == k and r[k] >= c["min_ratio"]:  # the unrefined triple stands
                    q, found = p[k], float(value[j])
                else:
                    continue
                if found > score:
                    best, score = q, found
        if best is None:
            return None
    if score < c["min_score"]:
        return None
    return best, score


def to_input(gray: np.ndarray, size=INPUT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """A full-resolution gray image → the network's input and the scale back.

    Returns:
        (image (H, W) float32 in [0, 1] at ``size``, scale (2,) = full / input, per axis).
    """
    w, h = size
    small = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA)
    return small.astype(np.float32) / 255.0, np.array([gray.shape[1] / w, gray.shape[0] / h])


def to_full(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Network-input pixels → full-resolution pixels (pixel centres at integers in both)."""
    return (np.asarray(points, np.float64) + 0.5) * scale - 0.5


WEIGHTS_DIR = Path(__file__).parent / "weights"


def look_conf(conf: dict) -> dict:
    """The decoding settings of the second look: ``min_score`` from ``look_min_score``."""
    ms = conf.get("look_min_score")
    return conf if ms is None else {**conf, "min_score": ms}


def check_second_look(value) -> float:
    """``second_look`` as a float; ValueError unless it is a zoom factor >= 1 (1: none)."""
    if not float(value) >= 1:
        raise ValueError(f"second_look is a zoom factor >= 1 (1: none), got {value!r}")
    return float(value)


def look_size(zoom: float = 1.0) -> tuple[int, int]:
    """The network input's (width, height) for a look ``zoom`` times the paper's 320x240."""
    return round(INPUT_SIZE[0] * zoom), round(INPUT_SIZE[1] * zoom)


def tuned_key(ids: str, verify: bool = False, stereo: bool = False, align: bool = False) -> str:
    """Name of a set of decoding thresholds tuned at export: the ID mode, ``_verify``,
    ``_align`` and ``_stereo`` (the operating point for views of a stereo pair). The
    second look's threshold is stored under this name + ``_look``."""
    return ids + ("_verify" if verify else "") + ("_align" if align else "") + ("_stereo" if stereo else "")


class KeypointNet:
    """Stage 1 with its weights: full-resolution images → ring centres by ID.

    Args:
        weights: a checkpoint path (``.pt``) or None for the shipped default.
        conf: decoding overrides of :data:`default_conf`; ``width`` and ``stem_width``
            come from the checkpoint.
        device: torch device ("cpu" by default; "cuda" when wanted and present).
        marker: the marker's geometry, for ``ids="layout"`` and ``verify`` (default: the
            default marker).
        stereo: use the thresholds tuned for views of a stereo pair (a looser
            false-positive budget, as the pair's epipolar and shape checks reject false
            triples) when the checkpoint has them; else those for single images.
    """

    default_weights = WEIGHTS_DIR / "keypoints.pt"

    def __init__(self, weights: str | Path | None = None, conf: dict | None = None, device: str = "cpu", marker: Marker | None = None, stereo: bool = False):
        import torch

        path = Path(weights) if weights is not None else self.default_weights
        if not path.is_file():
            raise ValueError(
                f"keypoint weights not found: {path} (train them with `markerpose train keypoints`)"
            )
        ckpt = torch.load(path, map_location=device, weights_only=True)
        for key in ("state_dict", "width"):
            if key not in ckpt:
                raise ValueError(f"{path} is not a markerpose keypoint checkpoint: no {key!r}")
        # Decoding thresholds: the defaults, those tuned for this ID mode and operating
        # point when the weights were exported (keyed by tuned_key), then the caller's.
        self.tuned = ckpt.get("decode", {})
        if not any(k in self.tuned for k in ID_MODES):  # older checkpoints: tuned for "head"
            self.tuned = {"head": self.tuned}
        self.conf = self.decode_conf(conf, stereo)
        self.conf["width"] = float(ckpt["width"])
        self.conf["stem_width"] = ckpt.get("stem_width")
        self.net = build_network(self.conf["width"], self.conf["stem_width"]).to(device).eval()
        self.net.load_state_dict(ckpt["state_dict"])  # strict: every weight must match
        fuse_batchnorm(self.net)
        self.device = device
        self.path = path
        self.marker = marker or _MARKER

    def decode_conf(self, conf: dict | None = None, stereo: bool = False) -> dict:
        """Decoding settings: the defaults, the thresholds tuned at export for the ID mode
        (``conf["ids"]``), ``verify`` and operating point (stereo or single view), then
        ``conf``."""
        mode = (conf or {}).get("ids", default_conf["ids"])
        if mode not in ID_MODES:
            raise ValueError(f"ids must be one of {ID_MODES}, got {mode!r}")
        verify = bool((conf or {}).get("verify", default_conf["verify"]))
        align = bool((conf or {}).get("align", default_conf["align"]))
        single = self.tuned.get(tuned_key(mode, verify, align=align), {})
        chosen = self.tuned.get(tuned_key(mode, verify, True, align), single) if stereo else single
        if mode == "layout" and chosen and "ratio_full" not in chosen:
            chosen = {**chosen, "ratio_full": None}  # tuned before v0.13, with the ratio itself
        if chosen.get("align") and "align_top" not in chosen:
            chosen = {**chosen, "align_top": 1, "align_min_ratio": None}  # tuned before v0.14: the best triple aligned
        if chosen.get("align") and "align_orders" not in chosen:
            chosen = {**chosen, "align_orders": 1}  # tuned before v0.15: each triple's best order only
        if chosen.get("align") and "align_cc_power" not in chosen:
            chosen = {**chosen, "align_cc_power": 0.0}  # tuned before v0.15: the score without the correlation
        if chosen.get("align") and "align_move_rule" not in chosen:
            chosen = {**chosen, "align_move_rule": "spacing"}  # tuned before v0.18
        if float((conf or {}).get("second_look", default_conf["second_look"])) > 1:
            chosen = {**chosen, **self.tuned.get(tuned_key(mode, verify, stereo, align) + "_look", {})}
        out = {**default_conf, **chosen, **(conf or {})}
        check_second_look(out["second_look"])
        return out

    def logits(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, H, W) float32 inputs → (det (B, 65, Hc, Wc), ids (B, 4, Hc, Wc)) logits."""
        import torch

        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(batch, np.float32))[:, None].to(self.device)
            det, ids = self.net(x)
        return det.float().cpu().numpy(), ids.float().cpu().numpy()

    def _forward(self, images: list[np.ndarray], zoom: float = 1.0):
        """Full-resolution gray images → (det logits, ID logits, per-image scales back, inputs),
        looked at ``zoom`` times the paper's input size."""
        inputs, scales = zip(*(to_input(g, look_size(zoom)) for g in images))
        return (*self.logits(np.stack(inputs)), scales, inputs)

    def candidates(self, images: list[np.ndarray], threshold: float = 0.01, k: int = 16, zoom: float = 1.0,
                   nms_radius: int | None = None) -> list[np.ndarray]:
        """Every view's ``k`` best centre candidates, whatever their ID (one forward pass at
        ``zoom`` times 320x240; NMS radius in input px, None: ``conf["nms_radius"]``): per
        image, (N, 3) rows (x, y, score) in full-resolution pixels, best first."""
        det, ids, scales, _ = self._forward(images, zoom)
        r = self.conf["nms_radius"] if nms_radius is None else nms_radius
        out = []
        for k_, s in enumerate(scales):
            cand, _ = candidates(det[k_], ids[k_], threshold, k, r)
            cand[:, :2] = to_full(cand[:, :2], s)
            out.append(cand)
        return out

    def evidence(self, image: np.ndarray, triples: np.ndarray, zoom: float = 1.0) -> np.ndarray:
        """:func:`ring_evidence` of (T, 3, 2) triples in a full-resolution uint8 gray image's
        pixels, looked at in the network's input of the look that found them: (T,)."""
        small, scale = to_input(image, look_size(zoom))
        return ring_evidence(small, (np.asarray(triples, np.float64) + 0.5) / scale - 0.5, self.marker)

    def __call__(self, images: list[np.ndarray]) -> list[tuple[np.ndarray, float] | None]:
        """Centres in full-resolution pixels for a batch of uint8 gray images (one forward pass).

        Returns:
            per image, (centers (3, 2) by ID, score) or None.
        """
        det, ids, scales, inputs = self._forward(images)
        out = []
        for k, s in enumerate(scales):
            found = decode(det[k], ids[k], self.conf, self.marker, inputs[k])
            out.append(None if found is None else (to_full(found[0], s), found[1]))
        zoom = float(self.conf["second_look"])
        again = [k for k, o in enumerate(out) if o is None]
        if zoom > 1 and again:
            # The second look resizes the full-resolution image, so it sees finer detail.
            det, ids, scales, inputs = self._forward([images[k] for k in again], zoom)
            conf = look_conf(self.conf)
            for j, k in enumerate(again):
                found = decode(det[j], ids[j], conf, self.marker, inputs[j])
                out[k] = None if found is None else (to_full(found[0], scales[j]), found[1])
        return out


__all__ = [
    "ALIGN_MOVE_RULES",
    "ID_MODES",
    "INPUT_SIZE",
    "align_triple",
    "KeypointNet",
    "build_network",
    "candidates",
    "check_second_look",
    "decode",
    "default_conf",
    "layout_ratio",
    "layout_ratios",
    "layer_widths",
    "look_size",
    "make_targets",
    "nms",
    "ring_evidence",
    "score_map",
    "signed_area",
    "signed_areas",
    "to_full",
    "to_input",
    "triple_orders",
    "tuned_key",
]
