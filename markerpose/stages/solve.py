"""Solve: triangulation, perspective-bias correction and the pose.

The paper triangulates the ellipse centres (DLT) and builds R from the directions
c0→c1 and c0→c2. An ellipse's centre is not the image of the circle's centre under
perspective: with ``bias_correction`` (ours) that offset is predicted from the first
pose in each view, subtracted, and the points triangulated again (two rounds). The pose
is the least-squares rigid fit of the marker's centres (``pose="rigid"``, ours: R in
SO(3)) or the paper's construction (``pose="paper"``, not exactly orthonormal).
"""

from __future__ import annotations

import numpy as np

from ..geometry import POSE_METHODS, nearest_rotation, perspective_bias, pose_from_points, pose_rigid, solve_rigid, triangulate
from ..marker import Marker
from ..results import Detection, Estimate
from ..settings import choice, flag

default_conf = {
    "pose": "rigid",  # "rigid": least-squares SO(3) fit (ours); "paper": R = [x y x×y], t = X0
    "bias_correction": True,  # remove the perspective bias of ellipse centres (False: the paper)
}


RULES = {"pose": choice(*POSE_METHODS), "bias_correction": flag()}
BIAS_ROUNDS = 2  # the bias varies slowly with pose: two rounds converge


def solve(rig, marker: Marker, det_left: Detection, det_right: Detection, conf: dict, source: str = "detected") -> Estimate:
    """The pose from matched centres of both views (ordered by ID).

    With ``bias_correction`` the returned ``centers`` are the corrected ones: estimates of
    where the rings' 3D centres project, rather than the fitted ellipses' centres.
    ``residual_px`` is the RMS distance of the six centres from the marker's centres
    projected under the pose.
    """
    centers = np.stack([det_left.centers, det_right.centers]).astype(np.float64)
    rounds = BIAS_ROUNDS if conf["bias_correction"] else 0
    fast = solve_rigid(rig, centers, marker.points3d, marker.centers2d, marker.outer_radius, rounds) if conf["pose"] == "rigid" else None
    if fast is not None:
        centers, X, T, residual = fast
    else:  # the paper's pose, or a centre where the compiled lens inversion gives up
        X = triangulate(rig, centers[0], centers[1])
        measured = centers.copy()
        for _ in range(rounds):
            T = pose_rigid(X, marker.points3d)
            Ts = (T, rig.T_right_left @ T)
            for i, cam in enumerate(rig.cameras):
                centers[i] = measured[i] - perspective_bias(cam, Ts[i], marker.centers2d, marker.outer_radius)
            X = triangulate(rig, centers[0], centers[1])
        T = pose_from_points(X, marker.points3d, conf["pose"])
        residual = reprojection_rms(rig, marker, T, centers)
    return Estimate(
        T=T,
        points3d=X,
        centers=centers,
        detections=(det_left, det_right),
        residual_px=residual,
        source=source,
        _context=(rig, marker.points3d, conf["pose"]),
    )


def reprojection_rms(rig, marker: Marker, T_left_marker: np.ndarray, centers: np.ndarray) -> float:
    """RMS distance (px) of ``centers`` (2, 3, 2) from the marker's ring centres projected
    into both views under ``T_left_marker`` (its rotation made orthonormal first)."""
    X = marker.points3d @ nearest_rotation(T_left_marker[:3, :3]).T + T_left_marker[:3, 3]
    proj = np.stack(rig.project(X))
    return float(np.sqrt(np.mean(np.sum((proj - centers) ** 2, axis=-1))))


__all__ = ["RULES", "default_conf", "reprojection_rms", "solve"]
