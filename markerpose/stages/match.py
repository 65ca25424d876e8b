"""Match: name the rings and pair them across the two views.

The neural detectors' stage 1 gives each view a handful of candidate ring centres: the
marker's rings, and anything ring-like in the scene. One view can judge a triple of them
only by its 2D shape, which tilt distorts and which a chance arrangement of decoys can
mimic. Two calibrated views measure it (:func:`stereo_triples`, ours): each left/right
pair of candidates close to each other's epipolar lines is triangulated, and three such
points are the marker only if their distances are the marker's (c0-c1, c0-c2, c1-c2, in
mm) and they turn the marker's way. The distances also name the rings, so no ID is
needed from the network. A single view names its triples by the marker's 2D layout
(:func:`view_triples`).

When no matched triple passes, one view may still hold the marker well while the other's
candidates are off (a steeply tilted marker, which the other camera sees steeper still):
triples matched with looser tolerances are refined, and :func:`transfer` carries a view's
refined centres into the other view through the poses that explain them
(:func:`~markerpose.geometry.view_poses`), where they are refined and checked like any
other hypothesis (:func:`transfer_sources` lists what to try).

The classical detector (paper §3.4) names each view's rings by their layout itself; its
views are paired by the epipolar constraint (:func:`pair_triples`).
"""

from __future__ import annotations

import numpy as np

from ..camera import StereoRig
from ..geometry import epipolar_distance, layout_ratios, signed_areas, triangulate, triple_orders
from ..settings import choice, flag, number

PAIRS = ((0, 1), (0, 2), (1, 2))

default_conf = {
    "method": "stereo",  # "stereo": candidates matched by the 3D shape (ours); "layout": one
    #                      triple per view by the 2D layout (ours); "head": by the ID head (paper)
    "epipolar_tol": 20.0,  # stereo: largest epipolar distance of two matched candidates, px
    #                        (stage 1 misplaces steeply tilted rings by 10-20 px)
    "shape_tol": 0.35,  # stereo: relative error allowed in each triangulated ring distance
    "max_triples": 3,  # stereo: matched triples refined and checked, best first
    "min_evidence": 0.1,  # single views: layout triples with less ring evidence are not
    #                       refined, the others are tried by score x evidence; 0: by score
    "view_min_ratio": 0.25,  # single views with evidence: smallest layout ratio (cos 75°;
    #                          the evidence, not the ratio, tells a steep marker's ID order)
    "transfer": True,  # stereo: carry one view's refined rings into the other (below)
    "blur_min_evidence": 0.1,  # a view's blurred-ring fit (the costliest step) only for rings
    #                            with at least this ring evidence (a decoy's triple has less;
    #                            the marker's, blurred 25 px, more); 0: no test
    "mask_min_evidence": 0.05,  # a matched triple whose edges do not fit from the layout's
    #                             seeds in a view goes on to EllipSegNet's masks only with at
    #                             least this ring evidence there; 0: no test
    "transfer_masks": False,  # the transfer's fits (a source, the other view at the predicted
    #                           centres) go on to EllipSegNet's masks where their edges do not
    #                           fit from the layout's seeds (False: they fail there; on an
    #                           inconsistent pair the masks were most of the worst pair's time)
    "transfer_min_evidence": 0.05,  # sources with less ring evidence are not refined (decoy
    #                                 triples on marker-free pairs cost refits); 0: every one.
    #                                 Lower than min_evidence: a source from the steep view
    #                                 is pixels off, and its evidence runs lower
    "max_fits": 3,  # neural: hypotheses refined (a triple fitted in one or both views) per
    #                 cold detection, over both looks; then the pair gives no pose. A valid
    #                 pair needs one or two, an inconsistent one (a view given twice, views
    #                 swapped) would otherwise try every triple and transfer (seconds)
}
METHODS = ("stereo", "layout", "head")
RULES = {
    "method": choice(*METHODS),
    "epipolar_tol": number(0, above=True),
    "shape_tol": number(0, 1, above=True),
    "max_triples": number(1, integer=True),
    "min_evidence": number(0),  # above the largest evidence: refuse all
    "view_min_ratio": number(0, 1),
    "transfer": flag(),
    "blur_min_evidence": number(0),  # above the largest evidence: refuse all
    "mask_min_evidence": number(0),  # above the largest evidence: refuse all
    "transfer_masks": flag(),
    "transfer_min_evidence": number(0),  # above the largest evidence: refuse all
    "max_fits": number(1, integer=True),
}

VIEW_TRIPLES = 4  # single views and the transfer: layout triples tried per view
# The transfer's loose matching: tolerances (px; relative distance error), how many loose
# triples are tried, and how many one-view triples are refined and carried over at most.
TRANSFER_EPIPOLAR_TOL = 60.0
TRANSFER_SHAPE_TOL = 0.6
TRANSFER_ATTEMPTS = 2
TRANSFER_SOURCES = 4
PAIR_EPIPOLAR_TOL = 3.0  # the classical detector: largest epipolar distance of same-ID centres, px


def side_lengths(points3d: np.ndarray) -> np.ndarray:
    """(3,) distances c0-c1, c0-c2, c1-c2 of (3, 3) points."""
    return np.array([np.linalg.norm(points3d[i] - points3d[j]) for i, j in PAIRS])


def stereo_triples(
    rig: StereoRig,
    cand_left: np.ndarray,
    cand_right: np.ndarray,
    model: np.ndarray,
    epipolar_tol: float = 12.0,
    shape_tol: float = 0.15,
    max_triples: int = 3,
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The triples of candidates, matched across views, that have the marker's shape.

    Args:
        rig: the calibrated stereo rig.
        cand_left, cand_right: (N, 3) and (M, 3) candidates (x, y, score), full-resolution
            pixels (:meth:`~markerpose.keypoints.KeypointNet.candidates`).
        model: (3, 3) the marker's ring centres c0, c1, c2 in mm (``Marker.points3d``).
        epipolar_tol: largest symmetric epipolar distance of a matched pair, px.
        shape_tol: largest relative error of each of the three triangulated distances.
        max_triples: how many to return.
    Returns:
        up to ``max_triples`` of (left points (3, 2), right points (3, 2), score), ordered
        c0, c1, c2 and best first. The score is the geometric mean of the six candidates'
        scores times (1 - the largest relative distance error / ``shape_tol``).
    """
    pl, pr, score, _, _ = matched_triples(rig, cand_left, cand_right, model, epipolar_tol, shape_tol)
    return [(pl[n], pr[n], float(score[n])) for n in range(min(len(score), max_triples))]


def matched_triples(
    rig: StereoRig, cand_left: np.ndarray, cand_right: np.ndarray, model: np.ndarray, epipolar_tol: float = 12.0, shape_tol: float = 0.15
) -> tuple:
    """Every triple :func:`stereo_triples` finds, best first (the same order), with the
    candidates it is made of: (left points (M, 3, 2), right points (M, 3, 2), scores (M,),
    left candidates' indices (M, 3), right candidates' indices (M, 3)). A triple's score
    depends on its own six candidates alone, and the order of two triples on their scores
    and candidates' order alone: the triples of a subset of the candidates are those of
    all the candidates that the subset holds, in the same order."""
    cl, cr = np.asarray(cand_left, np.float64).reshape(-1, 3), np.asarray(cand_right, np.float64).reshape(-1, 3)
    none = (np.zeros((0, 3, 2)), np.zeros((0, 3, 2)), np.zeros(0), np.zeros((0, 3), int), np.zeros((0, 3), int))
    if len(cl) < 3 or len(cr) < 3:
        return none
    I, J = np.nonzero(epipolar_distance(rig, cl[:, :2], cr[:, :2]) <= epipolar_tol)
    if len(I) < 3:
        return none
    X = triangulate(rig, cl[I, :2], cr[J, :2])
    front = (X[:, 2] > 0) & (rig.to_right(X)[:, 2] > 0)
    I, J, X = I[front], J[front], X[front]
    L = side_lengths(np.asarray(model, np.float64))
    dist = np.linalg.norm(X[:, None] - X[None], axis=2)
    err = [np.abs(dist - L[k]) / L[k] for k in range(3)]  # relative error as side k
    logs = 0.5 * (np.log(np.maximum(cl[I, 2], 1e-12)) + np.log(np.maximum(cr[J, 2], 1e-12)))
    # (a, b, c) = (c0, c1, c2) with the marker's three side lengths, in (a, b, c) order:
    # the pairs (a, b) with side 0's length, then each one's c with sides 1 and 2.
    A, B = np.nonzero(err[0] <= shape_tol)
    n, C = np.nonzero((err[1][A] <= shape_tol) & (err[2][B] <= shape_tol))
    if not len(n):
        return none
    T = np.column_stack([A[n], B[n], C])
    distinct = (
        (I[T[:, 0]] != I[T[:, 1]])
        & (I[T[:, 0]] != I[T[:, 2]])
        & (I[T[:, 1]] != I[T[:, 2]])
        & (J[T[:, 0]] != J[T[:, 1]])
        & (J[T[:, 0]] != J[T[:, 2]])
        & (J[T[:, 1]] != J[T[:, 2]])
    )
    T = T[distinct]
    pl, pr = cl[I[T], :2], cr[J[T], :2]  # (M, 3, 2)
    front = (signed_areas(pl) < 0) & (signed_areas(pr) < 0)  # not the marker seen from behind
    T, pl, pr = T[front], pl[front], pr[front]
    e = np.maximum(np.maximum(err[0][T[:, 0], T[:, 1]], err[1][T[:, 0], T[:, 2]]), err[2][T[:, 1], T[:, 2]])
    score = np.exp(logs[T].mean(1)) * (1 - e / shape_tol)
    order = np.argsort(-score, kind="stable")
    return pl[order], pr[order], score[order], I[T][order], J[T][order]


def layout_orders(cand: np.ndarray, layout: np.ndarray, min_ratio: float = 0.35, top: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every triple of one view's candidates in every order that could be the marker.

    Args:
        cand: (N, 3) candidates (x, y, score), best first; the ``top`` first are used.
        layout: (3, 2) the marker's ring centres in mm (``Marker.centers2d``).
        min_ratio: smallest singular-value ratio of the affine map from the layout
            (:func:`~markerpose.keypoints.layout_ratio`; cos 60° = 0.5).
    Returns:
        (points (M, 3, 2) ordered c0, c1, c2; scores (M,), the geometric mean of the
        three candidates' scores times the layout ratio; which set of candidates each is
        (M,)): the orders with the marker's handedness and at least ``min_ratio``.
    """
    cand = np.asarray(cand, np.float64).reshape(-1, 3)[:top]
    idx = triple_orders(len(cand))  # every triple in every order; idx[m, j] = the candidate named c_j
    if len(idx) == 0:
        return np.zeros((0, 3, 2)), np.zeros(0), np.zeros(0, int)
    p = cand[idx, :2]
    r = layout_ratios(p, layout)
    ok = (signed_areas(p) < 0) & (r >= min_ratio)  # not a mirror image, not degenerate; the layout's shape
    s = np.prod(cand[idx, 2], axis=1) ** (1 / 3) * r
    return p[ok], s[ok], (np.arange(len(idx)) // 6)[ok]  # triple_orders gives each set's 6 orders in a row


def best_per_set(scores: np.ndarray, sets: np.ndarray) -> np.ndarray:
    """Indices of each set's best-scored entry, best first (ties: the first)."""
    order = np.argsort(-scores, kind="stable")
    _, first = np.unique(sets[order], return_index=True)
    return order[np.sort(first)]


def view_triples(
    cand: np.ndarray, layout: np.ndarray, min_ratio: float = 0.35, max_triples: int | None = 1, top: int = 8
) -> list[tuple[np.ndarray, float]]:
    """Triples of one view's candidates named by the marker's 2D layout, best first: each
    set of candidates in its order of highest score (:func:`layout_orders`).

    Args:
        cand, layout, min_ratio, top: as in :func:`layout_orders`.
        max_triples: how many to return (distinct sets of candidates; None: all).
    Returns:
        up to ``max_triples`` of (points (3, 2) ordered c0, c1, c2, score).
    """
    p, s, sets = layout_orders(cand, layout, min_ratio, top)
    return [(p[k], float(s[k])) for k in best_per_set(s, sets)[:max_triples]]


def transfer(rig: StereoRig, view: int, poses: list, model: np.ndarray, max_poses: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where the marker's rings lie in the other view, from its poses in ``view``.

    Args:
        rig: the calibrated stereo rig.
        view: 0 (left) or 1 (right): the view the poses are in.
        poses: (misfit, T_cam_marker) best first, as :func:`view_poses` returns them.
        model: (3, 3) the marker's ring centres (``Marker.points3d``), mm.
        max_poses: how many poses to use.
    Returns:
        up to ``max_poses`` of (points (3, 2): c0, c1, c2 predicted in the other view,
        T_other_marker (4, 4): the pose there), best first.
    """
    to_left = np.eye(4) if view == 0 else np.linalg.inv(rig.T_right_left)
    to_other = rig.T_right_left if view == 0 else to_left
    out = []
    for _, T in poses:
        Xl = (np.asarray(model, np.float64) @ T[:3, :3].T + T[:3, 3]) @ to_left[:3, :3].T + to_left[:3, 3]
        if np.any(rig.to_right(Xl)[:, 2] <= 0) or np.any(Xl[:, 2] <= 0):
            continue
        pred = rig.project(Xl)[1 - view]
        if np.isfinite(pred).all():
            out.append((pred, to_other @ T))
        if len(out) == max_poses:
            break
    return out


def transfer_sources(loose: list, cand: list, layout: np.ndarray, view_triples_n: int) -> list[tuple[int, np.ndarray, float]]:
    """What the transfer tries to carry over, without repeats: (view, points (3, 2), score)
    for both sides of each loosely matched triple, then each view's best
    ``view_triples_n`` triples by the 2D layout."""
    sources = [(a, p, s) for pl, pr, s in loose for a, p in ((0, pl), (1, pr))]
    for a in (0, 1):
        sources += [(a, p, s) for p, s in view_triples(cand[a], layout, max_triples=view_triples_n)]
    unique: list = []
    for a, pts, s in sources:
        if not any(a == a2 and np.abs(pts - p2).max() < 1e-6 for a2, p2, _ in unique):
            unique.append((a, pts, s))
    return unique


def pair_triples(rig: StereoRig, left: tuple, right: tuple, epipolar_tol: float = 3.0):
    """The classical detector's stereo match (paper §3.4): of each view's marker-like
    triples, the pair whose same-ID centres lie within ``epipolar_tol`` px of each other's
    epipolar lines, at the least cost (the two triples' costs + the squared epipolar
    distances over the tolerance).

    Args:
        left, right: (rings, triples) of each view, as
            :func:`markerpose.classical.view_triples` returns them (rings, [(cost, (i0, i1, i2))]).
    Returns:
        (left triple, right triple, left cost, right cost) or None.
    """
    (rl, tl), (rr, tr) = left, right
    best = None
    for cl, il in tl:
        pl = np.array([rl[k].center for k in il])
        for cr, ir in tr:
            pr = np.array([rr[k].center for k in ir])
            d = np.diag(epipolar_distance(rig, pl, pr))
            if d.max() > epipolar_tol:
                continue
            cost = cl + cr + float((d / epipolar_tol) @ (d / epipolar_tol))
            if best is None or cost < best[0]:
                best = (cost, il, ir, cl, cr)
    return None if best is None else best[1:]


__all__ = [
    "METHODS",
    "PAIR_EPIPOLAR_TOL",
    "RULES",
    "TRANSFER_ATTEMPTS",
    "TRANSFER_EPIPOLAR_TOL",
    "TRANSFER_SHAPE_TOL",
    "TRANSFER_SOURCES",
    "VIEW_TRIPLES",
    "best_per_set",
    "default_conf",
    "layout_orders",
    "matched_triples",
    "pair_triples",
    "side_lengths",
    "stereo_triples",
    "transfer",
    "transfer_sources",
    "view_triples",
]
