"""Probe calibration with a point (cross-wire) phantom.

The wire crossing is a fixed point P in the tracker frame. Imaged from many probe poses
at pixel (u_i, v_i), it satisfies, for every image i,

    T_left_marker_i · T_marker_image · (u_i sx, v_i sy, 0, 1) = P.

A linear solve (the rotation's first two columns free) gives the start; a nonlinear
least-squares over the rotation vector, translation and P gives the calibration. Its
quality figure is the RMS distance of the reconstructed crossings from P.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..geometry import nearest_rotation
from .probe import ProbeCalibration, rigid


def calibrate_probe(poses: list, points_px, spacing, size=None) -> tuple[ProbeCalibration, np.ndarray, np.ndarray]:
    """Solve the image → marker transform from images of one fixed point.

    Args:
        poses: per image, (4, 4) ``T_left_marker`` or None (image skipped).
        points_px: per image, (u, v) of the point in the image, or None (skipped).
        spacing: (sx, sy) mm per pixel (as reported by the scanner for its depth setting).
        size: (width, height) of the images, stored in the result.
    Returns:
        (calibration, P, errors): the calibration (``rms_mm`` set), the point in the
        tracker frame (3,), and each used image's reconstruction error (mm).
    """
    sx, sy = float(spacing[0]), float(spacing[1])
    use = [(np.asarray(T, float), np.asarray(p, float)) for T, p in zip(poses, points_px) if T is not None and p is not None]
    if len(use) < 6:
        raise ValueError(f"probe calibration needs at least 6 images with a pose and a point, got {len(use)}")
    xy = np.array([[p[0] * sx, p[1] * sy] for _, p in use])
    # Linear: R_i (x r1 + y r2 + t) - P = -t_i, unknowns r1, r2, t, P (12).
    A = np.zeros((3 * len(use), 12))
    b = np.zeros(3 * len(use))
    for i, ((T, _), (x, y)) in enumerate(zip(use, xy)):
        Ri = T[:3, :3]
        A[3 * i : 3 * i + 3, 0:3] = x * Ri
        A[3 * i : 3 * i + 3, 3:6] = y * Ri
        A[3 * i : 3 * i + 3, 6:9] = Ri
        A[3 * i : 3 * i + 3, 9:12] = -np.eye(3)
        b[3 * i : 3 * i + 3] = -T[:3, 3]
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    r1, r2 = sol[0:3], sol[3:6]
    R0 = nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    x0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), sol[6:9], sol[9:12]])
    Rs = np.array([T[:3, :3] for T, _ in use])
    ts = np.array([T[:3, 3] for T, _ in use])
    pl = np.column_stack([xy, np.zeros(len(xy))])

    def points(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        pm = pl @ R.T + x[3:6]
        return np.einsum("nij,nj->ni", Rs, pm) + ts

    fit = least_squares(lambda x: (points(x) - x[6:9]).ravel(), x0)
    x = fit.x
    err = np.linalg.norm(points(x) - x[6:9], axis=1)
    T_mi = rigid(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])
    calib = ProbeCalibration(T_mi, (sx, sy), size, float(np.sqrt(np.mean(err**2))))
    return calib, x[6:9], err


__all__ = ["calibrate_probe"]
