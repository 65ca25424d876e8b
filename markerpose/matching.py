"""Stage-1 candidates of the two views matched by the marker's 3D shape.

Stage 1 gives each view a handful of candidate ring centres: the marker's rings, and
anything ring-like in the scene. One view can judge a triple of them only by its 2D
shape, which tilt distorts and which a chance arrangement of decoys can mimic. Two
calibrated views measure it: each left/right pair of candidates close to each other's
epipolar lines is triangulated, and three such points are the marker only if their
distances are the marker's (c0-c1, c0-c2, c1-c2, in mm) and they turn the marker's way.
The distances also name the rings, so no ID is needed from the network.

When no matched triple passes, one view may still hold the marker well while the other's
candidates are off (a steeply tilted marker, which the other camera sees steeper still):
triples matched with looser tolerances are refined, and :func:`transfer` carries a view's
refined centres into the other view through the poses that explain them
(:func:`view_poses`: P3P ranked by the ellipses), where they are refined and checked
like any other hypothesis.
"""

from __future__ import annotations

import cv2
import numpy as np

from .camera import StereoRig
from .geometry import ellipse_to_conic, epipolar_distance, triangulate
from .keypoints import layout_ratios, signed_area, signed_areas, triple_orders

PAIRS = ((0, 1), (0, 2), (1, 2))


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
    cl, cr = np.asarray(cand_left, np.float64).reshape(-1, 3), np.asarray(cand_right, np.float64).reshape(-1, 3)
    if len(cl) < 3 or len(cr) < 3:
        return []
    I, J = np.nonzero(epipolar_distance(rig, cl[:, :2], cr[:, :2]) <= epipolar_tol)
    if len(I) < 3:
        return []
    X = triangulate(rig, cl[I, :2], cr[J, :2])
    front = (X[:, 2] > 0) & (rig.to_right(X)[:, 2] > 0)
    I, J, X = I[front], J[front], X[front]
    L = side_lengths(np.asarray(model, np.float64))
    dist = np.linalg.norm(X[:, None] - X[None], axis=2)
    err = [np.abs(dist - L[k]) / L[k] for k in range(3)]  # relative error as side k
    logs = 0.5 * (np.log(np.maximum(cl[I, 2], 1e-12)) + np.log(np.maximum(cr[J, 2], 1e-12)))
    found = []
    for a in range(len(X)):  # a = c0, b = c1, c = c2
        bs = np.nonzero(err[0][a] <= shape_tol)[0]
        cs = np.nonzero(err[1][a] <= shape_tol)[0]
        for b in bs:
            for c in cs[err[2][b, cs] <= shape_tol]:
                trio = [a, b, c]
                if len(set(I[trio])) < 3 or len(set(J[trio])) < 3:
                    continue
                pl, pr = cl[I[trio], :2], cr[J[trio], :2]
                if signed_area(pl) >= 0 or signed_area(pr) >= 0:  # the marker seen from behind
                    continue
                e = max(err[0][a, b], err[1][a, c], err[2][b, c])
                found.append((pl, pr, float(np.exp(np.mean(logs[trio])) * (1 - e / shape_tol))))
    found.sort(key=lambda f: -f[2])
    return found[:max_triples]


def view_triples(cand: np.ndarray, layout: np.ndarray, min_ratio: float = 0.35, max_triples: int | None = 1, top: int = 8) -> list[tuple[np.ndarray, float]]:
    """Triples of one view's candidates named by the marker's 2D layout, best first.

    Args:
        cand: (N, 3) candidates (x, y, score), best first; the ``top`` first are used.
        layout: (3, 2) the marker's ring centres in mm (``Marker.centers2d``).
        min_ratio: smallest singular-value ratio of the affine map from the layout
            (:func:`~markerpose.keypoints.layout_ratio`; cos 60° = 0.5).
        max_triples: how many to return (distinct sets of candidates; None: all).
    Returns:
        up to ``max_triples`` of (points (3, 2) ordered c0, c1, c2, score); the score is the
        geometric mean of the three candidates' scores times the layout ratio.
    """
    cand = np.asarray(cand, np.float64).reshape(-1, 3)[:top]
    idx = triple_orders(len(cand))  # every triple in every order; idx[m, j] = the candidate named c_j
    if len(idx) == 0:
        return []
    p = cand[idx, :2]
    r = layout_ratios(p, layout)
    ok = (signed_areas(p) < 0) & (r >= min_ratio)  # not a mirror image, not degenerate; the layout's shape
    s = np.where(ok, np.prod(cand[idx, 2], axis=1) ** (1 / 3) * r, -np.inf).reshape(-1, 6)
    order = s.argmax(1)  # each triple's best order
    best = s[np.arange(len(s)), order]
    trios = np.nonzero(np.isfinite(best))[0]
    trios = trios[np.argsort(-best[trios], kind="stable")][:max_triples]
    return [(p[6 * t + order[t]], float(best[t])) for t in trios]


def view_poses(camera, centers: np.ndarray, ellipses: list | None, model: np.ndarray, radius: float) -> list[tuple[float, np.ndarray]]:
    """The marker's poses in one view from three ring centres, best explained first.

    P3P gives up to four poses that put the marker's centres on the three centres' rays;
    each is scored by how well its projected outer circles fit the rings' fitted ellipses
    (the ellipses' shapes tell the plate's tilt, which three points leave ambiguous). The
    score tells the marker from three ring-like things that merely lie in a
    marker-like triangle: their ellipses do not fit one plate.

    Args:
        camera: the view's :class:`~markerpose.camera.Camera`.
        centers: (3, 2) ring centres c0, c1, c2 in its (distorted) pixels.
        ellipses: the rings' outer ellipses (OpenCV RotatedRects, None for a missing one),
            or None: every pose then scores 0, in P3P's order.
        model: (3, 3) the marker's ring centres (``Marker.points3d``), mm.
        radius: the rings' outer radius, mm.
    Returns:
        list of (misfit, T_cam_marker (4, 4)), smallest misfit first; the misfit is the mean
        relative radial distance of the projected circles from the ellipses (0 = exact).
    """
    model = np.asarray(model, np.float64)
    xn = camera.undistort_points(np.asarray(centers, np.float64), ideal_pixels=False)
    n, rvecs, tvecs = cv2.solveP3P(model, xn, np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
    conics = [None if e is None else ellipse_to_conic(*e) for e in (ellipses or [])]
    poses = []
    for rv, tv in zip(rvecs[:n], tvecs[:n]):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rv)[0], np.ravel(tv)
        if not np.isfinite(T).all() or np.any(model @ T[2, :3] + T[2, 3] <= 0):
            continue  # degenerate, or behind the camera
        misfit = []
        edges = ring_edges(camera, T, model, radius) if conics else []
        for C, edge in zip(conics, edges):
            if C is None:
                continue
            h = np.column_stack([edge, np.ones(len(edge))])
            lam2 = np.einsum("ni,ij,nj->n", h, C, h) + 1.0  # (p - c)^T A (p - c) = lambda^2
            misfit.append(np.mean(np.abs(np.sqrt(np.maximum(lam2, 0)) - 1)))
        m = float(np.mean(misfit)) if misfit else 0.0
        if np.isfinite(m):
            poses.append((m, T))
    poses.sort(key=lambda p: p[0])
    return poses


def ring_edges(camera, T_cam_marker: np.ndarray, model: np.ndarray, radius: float, n: int = 24) -> np.ndarray:
    """(3, n, 2) distorted pixels of ``n`` points on each ring's outer circle in a view
    where the marker has pose ``T_cam_marker`` (``model``: the ring centres, mm)."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    circle = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)]) * radius
    T = np.asarray(T_cam_marker, np.float64)
    pts = (np.asarray(model, np.float64)[:, None, :] + circle[None]).reshape(-1, 3)
    return camera.project(pts @ T[:3, :3].T + T[:3, 3]).reshape(len(model), n, 2)


def ring_ellipses(camera, T_cam_marker: np.ndarray, model: np.ndarray, radius: float) -> list:
    """The rings' outer ellipses (OpenCV RotatedRects) in a view where the marker has pose
    ``T_cam_marker``: ellipses fitted to the projected circles (lens distortion included)."""
    return [cv2.fitEllipse(e.astype(np.float32)) for e in ring_edges(camera, T_cam_marker, model, radius, 36)]


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


__all__ = ["ring_edges", "ring_ellipses", "side_lengths", "stereo_triples", "transfer", "view_poses", "view_triples"]
