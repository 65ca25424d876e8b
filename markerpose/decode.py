"""Stage 1's decoding: the two heads of the network → candidates → the paper's triple.

The detector head's 65 channels become a score map (depth to space), its local maxima
the candidates (:func:`candidates`). The paper names the three rings by the ID head
(:func:`decode` with ``ids="head"``); ours by the marker's layout (``ids="layout"``),
optionally weighed by ring evidence (``verify``) and refined by aligning the printed
pattern to the image (``align``, :func:`align_triple`, used by ``markerpose eval
keypoints``). The default pipeline uses :func:`candidates` only and matches them across
views (:mod:`markerpose.stages.match`). Pure numpy/OpenCV: no torch here.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from .evidence import plate_evidence
from .geometry import layout_ratio, layout_ratios, signed_area, signed_areas, triple_orders
from .jit import compiled
from .marker import Marker

ALIGN_MOVE_RULES = ("spacing", "nearest")  # when align_triple takes an alignment as slid onto a neighbour (see align_triple)
ID_MODES = ("head", "layout")  # how decoding assigns ring IDs (see default_conf["ids"])
CELL = 8  # the network's output cell, input px

_MARKER = Marker()  # the default marker

default_conf = {
    "nms_radius": 2,  # px at 320x240: a steeply tilted marker puts two ring centres a few
    #                   px apart, and a larger radius can keep only one of them
    "threshold": 0.05,  # minimum location score of a candidate
    "max_candidates": 10,  # best candidates kept after NMS, per image
    "min_id_prob": 0.2,  # an assigned ID must have at least this probability at its point
    "min_score": 0.15,  # geometric mean of the three points' (score x ID probability)
    # IDs: "head" (paper) by the ID head; "layout" (ours) by the order whose affine map from
    # the marker's layout is nearest a similarity (the ID head sees less than the marker).
    "ids": "layout",
    "min_ratio": 0.35,  # layout: minimum singular-value ratio (cos 60° = 0.5, less perspective)
    "id_weight": 0.25,  # layout: exponent of the ID head's probabilities in the score
    # Ours: weigh every triple by its ring evidence (evidence.plate_evidence), which decoys
    # in a marker-like triangle lack. Needs the image.
    "verify": False,
    # Ours: zoom of a second look at an image in which the first finds no marker (1: none);
    # small rings are found far more often on the larger input.
    "second_look": 1.0,
    "look_min_score": None,  # the second look's min_score (None: min_score); tuned at export
    # Ours: refine the chosen triple by aligning the marker's printed pattern to the image
    # (align_triple), then score it again. Needs the image.
    "align": False,
    # Layout IDs: a triple's ratio factor is min(1, ratio / ratio_full) (None: the ratio
    # itself), so a steeply tilted marker is not scored down against a frontal decoy.
    "ratio_full": 0.5,
    # With align: the best ``align_top`` triples are aligned and the best after alignment
    # wins; they enter with a layout ratio of at least ``align_min_ratio`` (None:
    # ``min_ratio``) and must reach ``min_ratio`` once aligned.
    "align_top": 3,
    "align_min_ratio": 0.25,
    # With align: how many ID orders of each triple are aligned (more let more marker-free
    # views through at the tuned threshold).
    "align_orders": 1,
    # With align: the score is multiplied by the ECC correlation to this power (0: not at
    # all); a wrong triple dragged onto clutter correlates worse than the marker.
    "align_cc_power": 2.0,
    # With align: when an alignment counts as slid onto a neighbour's ring (dropped), one of
    # ALIGN_MOVE_RULES (see align_triple); "nearest" needs no fraction of the spacing.
    "align_move_rule": "nearest",
}


# --- decoding --------------------------------------------------------------------------
def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def score_map(det_logits: np.ndarray) -> np.ndarray:
    """(65, Hc, Wc) detector logits → (8 Hc, 8 Wc) probability that a pixel is a centre
    (float32)."""
    return score_maps(det_logits[None])[0]


def score_maps(det_logits: np.ndarray) -> np.ndarray:
    """:func:`score_map` of a batch: (B, 65, Hc, Wc) logits → (B, 8 Hc, 8 Wc), float32."""
    # In place and in float32, the precision the network and NMS work in: the exponential
    # of every cell's 65 logits is most of the decoding's time.
    p = np.array(det_logits, np.float32)
    p -= p.max(axis=1, keepdims=True)
    np.exp(p, out=p)
    p /= p.sum(axis=1, keepdims=True)
    p = p[:, :-1]  # drop the "no centre" channel
    b, _, hc, wc = p.shape
    return p.reshape(b, CELL, CELL, hc, wc).transpose(0, 3, 1, 4, 2).reshape(b, hc * CELL, wc * CELL)


@functools.lru_cache(maxsize=8)
def _square(size: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))


def nms(scores: np.ndarray, radius: int, threshold: float, k: int) -> np.ndarray:
    """Local maxima of a score map above a threshold, best first.

    Returns:
        (N, 3) rows (x, y, score), N <= k.
    """
    size = 2 * radius + 1
    scores = np.asarray(scores, np.float32)  # compare like with like: dilate works in float32
    dil = cv2.dilate(scores, _square(size))
    ys, xs = np.nonzero((scores >= dil) & (scores >= threshold))
    return _best_apart(xs, ys, scores[ys, xs], radius, k)


def _best_apart(xs: np.ndarray, ys: np.ndarray, s: np.ndarray, radius: int, k: int) -> np.ndarray:
    """Local maxima (x, y, score), in the map's row-major order, best first without those
    within ``radius`` of a better one (a plateau's twins): (N, 3), N <= k."""
    out = np.empty((k, 3))
    n = _apart(np.asarray(xs, np.float64), np.asarray(ys, np.float64), np.asarray(s, np.float32), float(radius) ** 2, out)
    return out[:n]


@compiled
def _apart(xs, ys, s, r2, out):  # pragma: no cover - compiled
    """:func:`_best_apart` into ``out`` (k, 3); returns the rows kept. Equal scores keep
    their row-major order (a stable sort)."""
    n = 0
    for i in np.argsort(-s, kind="mergesort"):
        far = True
        for m in range(n):
            if (xs[i] - out[m, 0]) ** 2 + (ys[i] - out[m, 1]) ** 2 <= r2:
                far = False
                break
        if far:
            out[n, 0], out[n, 1], out[n, 2] = xs[i], ys[i], s[i]
            n += 1
            if n == len(out):
                break
    return n


def _refine(scores: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Peaks (N, 3) moved to their 3x3 neighbourhood's score-weighted centroid (inside the
    map): a fraction of a pixel better than the peak."""
    out = np.array(cand, np.float64)
    if len(out):
        _centroids(np.asarray(scores, np.float32), 0, out)
    return out


@compiled
def _centroids(scores, pad, cand):  # pragma: no cover - compiled
    """:func:`_refine` in place on ``cand`` (N, 3), whose x, y are pixels of ``scores``
    less ``pad`` on each side (outside the map weighs nothing)."""
    h, w = scores.shape
    for n in range(len(cand)):
        y0, x0 = int(cand[n, 1]) + pad, int(cand[n, 0]) + pad
        total = sx = sy = 0.0
        for y in range(y0 - 1, y0 + 2):
            for x in range(x0 - 1, x0 + 2):
                if 0 <= y < h and 0 <= x < w:
                    v = np.float64(scores[y, x])
                    total += v
                    sx += v * (x - pad)
                    sy += v * (y - pad)
        if total > 0:  # else a zero plateau (a threshold of 0): the peak stays
            cand[n, 0], cand[n, 1] = sx / total, sy / total


@compiled
def _live_near(logits, bound):  # pragma: no cover - compiled
    """(B, Hc, Wc) bool: the cells whose best centre logit less their "no centre" logit
    reaches ``bound`` (float32, as the network's logits), and their 8 neighbours."""
    b, ch, hc, wc = logits.shape
    near = np.zeros((b, hc, wc), np.bool_)
    for j in range(b):
        m = logits[j, 0].copy()
        for c in range(1, ch - 1):  # channel by channel: the logits' own memory order
            for y in range(hc):
                for x in range(wc):
                    m[y, x] = max(m[y, x], logits[j, c, y, x])
        for y in range(hc):
            for x in range(wc):
                if m[y, x] - logits[j, ch - 1, y, x] >= bound:
                    near[j, max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2] = True
    return near


@compiled
def _tops(m, y, x, radius):  # pragma: no cover - compiled
    """Whether no value within ``radius`` (a square) of m[y, x] exceeds it."""
    s = m[y, x]
    for yy in range(y - radius, y + radius + 1):
        for xx in range(x - radius, x + radius + 1):
            if m[yy, xx] > s:
                return False
    return True


@compiled
def _cell_peaks(cells, bi, yi, xi, b, hc, wc, threshold, k, radius):  # pragma: no cover - compiled
    """:func:`_sparse_peaks` from the softmax of the cells (N, 64) at (bi, yi, xi): per
    image (B, k, 3) rows and (B,) how many."""
    pad = max(radius, 1)
    H, W = hc * CELL + 2 * pad, wc * CELL + 2 * pad
    maps = np.zeros((b, H, W), np.float32)
    for n in range(len(bi)):
        for c in range(CELL * CELL):
            maps[bi[n], yi[n] * CELL + c // CELL + pad, xi[n] * CELL + c % CELL + pad] = cells[n, c]
    out = np.empty((b, k, 3))
    counts = np.zeros(b, np.intp)
    cap = len(cells) * CELL * CELL
    at, xs, ys, ss = np.empty(cap, np.intp), np.empty(cap), np.empty(cap), np.empty(cap, np.float32)
    for j in range(b):
        m = maps[j]
        n = 0
        for q in range(len(bi)):  # the maxima of this image's cells ...
            if bi[q] != j:
                continue
            for c in range(CELL * CELL):
                y, x = yi[q] * CELL + c // CELL + pad, xi[q] * CELL + c % CELL + pad
                if m[y, x] >= threshold and _tops(m, y, x, radius):
                    at[n], xs[n], ys[n], ss[n] = y * W + x, x - pad, y - pad, m[y, x]
                    n += 1
        o = np.argsort(at[:n])  # ... in the map's row-major order, as nms's nonzero gives them
        n = _apart(xs[o], ys[o], ss[o], float(radius) ** 2, out[j])
        _centroids(m, pad, out[j, :n])
        counts[j] = n
    return out, counts


def _sparse_peaks(det_logits: np.ndarray, threshold: float, k: int, radius: int) -> list[np.ndarray]:
    """:func:`peaks` without the whole score map. A cell's scores are at most exp(its best
    centre logit - its "no centre" logit), so only the cells where that bound reaches
    ``threshold`` can hold a candidate (a few dozen of a view's thousand). The softmax
    runs on those and their neighbour cells (the windows of the maxima and the peaks' 3x3
    centroids reach into them), in the same order of operations as :func:`score_maps`,
    into a map that is zero elsewhere: every value a candidate is compared with or
    weighted by is the same to the bit, the values under ``threshold`` it leaves out never
    win a comparison, and so the rows are :func:`peaks`' own."""
    logits = np.ascontiguousarray(det_logits, np.float32)
    b, _, hc, wc = logits.shape
    # The bound in float32 against the threshold's log, with a margin for its own rounding.
    bi, yi, xi = np.nonzero(_live_near(logits, np.float32(math.log(threshold) - 1e-3)))
    p = np.ascontiguousarray(logits[bi, :, yi, xi].T)  # (65, N): reduced along axis 0, as score_maps does
    p -= p.max(axis=0, keepdims=True)
    np.exp(p, out=p)
    p /= p.sum(axis=0, keepdims=True)
    cells = np.ascontiguousarray(p[:-1].T)  # (N, 64): channel dy * CELL + dx
    out, counts = _cell_peaks(cells, bi, yi, xi, b, hc, wc, np.float32(threshold), int(k), int(radius))
    return [out[j, : counts[j]].copy() for j in range(b)]


def warm_up() -> None:
    """Compile this module's loops (or load them from numba's cache)."""
    _sparse_peaks(np.zeros((1, CELL * CELL + 1, 2, 2), np.float32), 0.01, 2, 2)
    _refine(np.ones((4, 4), np.float32), np.ones((1, 3)))


def peaks(det_logits: np.ndarray, threshold: float, k: int, nms_radius: int = 4) -> list[np.ndarray]:
    """The location part of :func:`candidates` for a batch of images' detector logits
    (B, 65, Hc, Wc): per image, (N, 3) rows (x, y, score), best first, N <= k."""
    if threshold <= 0:
        return [_refine(s, nms(s, nms_radius, threshold, k)) for s in score_maps(det_logits)]
    return _sparse_peaks(det_logits, threshold, k, nms_radius)


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
    prob = pid[:3, rows, cols].T  # (N, 3): P(ID = j) at candidate n (its peak's cell)
    return _refine(scores, cand), prob


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


def align_triple(
    image: np.ndarray, points: np.ndarray, marker: Marker | None = None, iterations: int = 50, move_rule: str = "spacing"
) -> tuple[np.ndarray, float | None]:
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
            centre than its own (what sliding onto a neighbour means, with no fraction to
            choose: a stage-1 point off towards its neighbour also shrinks the spacing).
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


def decode(
    det_logits: np.ndarray, id_logits: np.ndarray, conf: dict | None = None, marker: Marker | None = None, image: np.ndarray | None = None
):
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
    every allowed (triple, order) is then weighed by :func:`plate_evidence`. With
    ``align`` the ``align_top`` best triples are refined by :func:`align_triple` and
    scored again (layout ratio and evidence of the refined points); the best of them,
    and ``min_score``, decide.
    """
    c = _decode_conf(conf, image)
    marker = marker or _MARKER
    layout = marker.centers2d
    cand, prob = candidates(det_logits, id_logits, c["threshold"], c["max_candidates"], c["nms_radius"])
    if len(cand) < 3:
        return None
    # Every triple of candidates in every ID order at once: idx[m, j] = the candidate taking ID j.
    idx = triple_orders(len(cand))
    p = cand[idx, :2]  # (M, 3, 2)
    s, r, keep = _order_scores(cand, prob, idx, p, layout, c)
    if not keep.any():
        return None
    ev = np.ones(len(p))
    if c["verify"]:
        ev[keep] = plate_evidence(image, p[keep], marker)
    per_triple, rows, value, order = _ranked(s, r, ev, keep, c)
    if not c["align"]:
        best, score = p[rows[order[0]]], float(value[order[0]])
    else:
        best, score = _aligned_best(image, p, s, r, per_triple, rows, value, order, marker, layout, c)
        if best is None:
            return None
    if score < c["min_score"]:
        return None
    return best, score


def _decode_conf(conf: dict | None, image: np.ndarray | None) -> dict:
    """:data:`default_conf` with the overrides ``conf``, checked: a known ID mode, and the
    image where ``verify`` or ``align`` need it."""
    c = {**default_conf, **(conf or {})}
    if c["ids"] not in ID_MODES:
        raise ValueError(f"ids must be one of {ID_MODES}, got {c['ids']!r}")
    for need in ("verify", "align"):
        if c[need] and image is None:
            raise ValueError(f"decoding with {need}=True needs the image")
    return c


def _order_scores(cand: np.ndarray, prob: np.ndarray, idx: np.ndarray, p: np.ndarray, layout: np.ndarray, c: dict) -> tuple:
    """Per triple in each ID order (idx: (M, 3) candidates, p: (M, 3, 2) their points): the
    score (M,) from the location scores and ID probabilities, the layout ratio (M,) (1 with
    ``ids="head"``) and whether the order is allowed (M,) bool (handedness, ID probability
    or layout ratio)."""
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
    return s, r, keep


def _ranked(s: np.ndarray, r: np.ndarray, ev: np.ndarray, keep: np.ndarray, c: dict) -> tuple:
    """The triples ranked: (per triple its orders' values (T, 6), -1 where not allowed; the
    rows of the triples' best orders; their values; their order, best first)."""
    # Each triple in its best ID order (a wrong order puts a ring in the wrong place:
    # a small ratio), then the triples against each other — with the softened ratio, so
    # a steeply tilted marker is not outscored by a flatter decoy (ratio_full; the ID
    # mode "head" has no ratio: r = 1).
    per_triple = np.where(keep, s * r * ev, -1.0).reshape(-1, 6)
    rows = np.arange(len(per_triple)) * 6 + np.argmax(per_triple, axis=1)
    rows = rows[per_triple.max(1) >= 0]
    value = s[rows] * _ratio_weight(r[rows], c["ratio_full"]) * ev[rows]
    order = np.argsort(-value, kind="stable")
    return per_triple, rows, value, order


def _aligned_best(image, p, s, r, per_triple, rows, value, order, marker: Marker, layout: np.ndarray, c: dict) -> tuple:
    """(points (3, 2), score) of the best of the ``align_top`` best triples once aligned
    (``align_orders`` of their ID orders each), or (None, -1.0) when none is."""
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
            got = _aligned_order(image, p, s, r, o, k, value[j], marker, layout, c)
            if got is None:
                continue
            q, found = got
            if found > score:
                best, score = q, found
    return best, score


def _aligned_order(image, p, s, r, o, k, value_k, marker: Marker, layout: np.ndarray, c: dict) -> tuple | None:
    """(points (3, 2), score) of the ID order ``o`` aligned to the image
    (:func:`align_triple`); where the alignment fails or its layout ratio is too small, the
    unrefined triple ``k`` (of value ``value_k``) when ``o`` is it, else None."""
    q, cc = align_triple(image, p[o], marker, move_rule=c["align_move_rule"])
    rq = layout_ratio(q, layout) if c["ids"] == "layout" else 1.0  # "head": r = 1 throughout
    if cc is not None and rq >= c["min_ratio"]:
        found = float(s[o] * _ratio_weight(rq, c["ratio_full"])) * max(cc, 0.0) ** float(c["align_cc_power"])
        if c["verify"]:
            found *= float(plate_evidence(image, q[None], marker)[0])
        return q, found
    if o == k and r[k] >= c["min_ratio"]:  # the unrefined triple stands
        return p[k], float(value_k)
    return None
