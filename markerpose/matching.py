"""Stage-1 candidates of the two views matched by the marker's 3D shape.

Stage 1 gives each view a handful of candidate ring centres: the marker's rings, and
anything ring-like in the scene. One view can judge a triple of them only by its 2D
shape, which tilt distorts and which a chance arrangement of decoys can mimic. Two
calibrated views measure it: each left/right pair of candidates close to each other's
epipolar lines is triangulated, and three such points are the marker only if their
distances are the marker's (c0-c1, c0-c2, c1-c2, in mm) and they turn the marker's way.
The distances also name the rings, so no ID is needed from the network.
"""

from __future__ import annotations

import numpy as np

from .camera import StereoRig
from .geometry import epipolar_distance, triangulate
from .keypoints import signed_area

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


__all__ = ["side_lengths", "stereo_triples"]
