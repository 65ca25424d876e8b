"""How far to trust a pose: its 6 x 6 covariance, propagated from the ring centres' fits.

Each ring centre's 2 x 2 covariance comes from its own fit (the edge fit's residuals,
:func:`markerpose.edges.center_covariances`, or the blurred-ring fit's normal equations):
the image's noise, the edges' contrast and blur and how many edges the ring has all
show in it. It is carried to first order through the triangulation (the pipeline's own,
differentiated numerically) and the rigid fit of the marker's layout (analytically):

    cov = G diag(cov_X0, cov_X1, cov_X2) G^T,   G = (sum A_i^T A_i)^-1 [A_0^T A_1^T A_2^T],

with A_i = [I, -[R m_i]x] the derivative of ring i's 3D centre under a translation and a
small rotation of the marker. The covariance is of (tx, ty, tz) in mm, the marker origin
in the left-camera frame, and (wx, wy, wz) in rad, the rotation error ``R_true @ R_est.T``
as a rotation vector in the left-camera frame.

A fit's residuals show each edge's own noise, not the errors that a ring's edges share:
the plateau levels are planes fitted over all of its rays, the blur's reach is judged per
ring, and an error there moves every edge of the ring together. Each centre's covariance
therefore gets ``MODEL_PX`` squared on its diagonal: the centres' scatter beyond their
fits' covariances on rendered pairs of the standard conditions, as
``markerpose eval uncertainty`` measures it (on pairs of their own, apart from the
held-out ones it checks the covariance on; its report prints the figure). What the
covariance leaves out: the rig's calibration error (common to every pose of a rig) and
the perspective-bias correction's own error (a small fraction of a bias that is itself
small).
"""

from __future__ import annotations

import numpy as np

from .geometry import pose_from_points, triangulate

H_PX = 0.01  # step of the numerical derivative of the triangulation, px
MODEL_PX = 0.005  # the centres' error per axis that their fits do not show, px (see the module's docstring)


def skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) the cross-product matrix of ``v`` (3,): skew(a) @ b = a x b."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def point_covariances(rig, centers: np.ndarray, center_covs: np.ndarray) -> np.ndarray:
    """(N, 3, 3) covariances (mm^2) of the points triangulated from ``centers`` (2, N, 2)
    distorted px, the two views' centres having covariances ``center_covs`` (2, N, 2, 2)
    px^2 (independent between views and points)."""
    centers = np.asarray(centers, np.float64)
    N = centers.shape[1]
    c = np.repeat(centers[:, None], 5, axis=1)  # view, case (none, then each view's x and y moved), point, pixel axis
    for i, (v, a) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        c[v, i + 1, :, a] += H_PX
    X = triangulate(rig, c[0].reshape(-1, 2), c[1].reshape(-1, 2)).reshape(5, N, 3)  # one call: one undistortion per view
    J = ((X[1:] - X[0]) / H_PX).reshape(2, 2, N, 3).transpose(2, 3, 0, 1)  # point, xyz, view, pixel axis
    return np.einsum("nivp,vnpq,njvq->nij", J, np.asarray(center_covs, np.float64), J)


def _rigid_gain(T: np.ndarray, model: np.ndarray) -> np.ndarray:
    """(6, 3 N) the first-order map from the measured points' errors to the rigid fit's
    (translation, rotation vector) error (see the module's docstring)."""
    p = model @ T[:3, :3].T  # the marker's centres about its origin, in the camera frame
    A = np.stack([np.hstack([np.eye(3), -skew(q)]) for q in p])  # (N, 3, 6)
    Nmat = np.einsum("nki,nkj->ij", A, A)
    return np.linalg.solve(Nmat, A.transpose(2, 0, 1).reshape(6, -1))


def _numeric_gain(points3d: np.ndarray, model: np.ndarray, method: str, h: float = 1e-4) -> np.ndarray:
    """(6, 3 N) :func:`_rigid_gain` for any pose construction, by finite differences."""
    import cv2

    T0 = pose_from_points(points3d, model, method)
    G = np.empty((6, points3d.size))
    for j in range(points3d.size):
        X = points3d.copy().reshape(-1)
        X[j] += h
        T = pose_from_points(X.reshape(-1, 3), model, method)
        U, _, Vt = np.linalg.svd(T[:3, :3] @ T0[:3, :3].T)
        G[:3, j] = (T[:3, 3] - T0[:3, 3]) / h
        G[3:, j] = cv2.Rodrigues(U @ Vt)[0].ravel() / h
    return G


def pose_covariance(
    rig,
    model: np.ndarray,
    T: np.ndarray,
    points3d: np.ndarray,
    centers: np.ndarray,
    center_covs,
    method: str = "rigid",
    model_px: float = MODEL_PX,
):
    """(6, 6) covariance of the pose ``T`` (see the module's docstring), or None where a
    centre has no covariance (not edge-fitted: the paper's contour ellipses, a mask's
    centre).

    Args:
        rig: the stereo rig.
        model: (3, 3) the marker's ring centres in its frame, mm.
        T: (4, 4) T_left_marker.
        points3d: (3, 3) the triangulated centres the pose was fitted to, mm.
        centers: (2, 3, 2) the centres they were triangulated from, px.
        center_covs: (2, 3, 2, 2) the centres' covariances, px^2 (or None).
        method: the pose construction ("rigid" or "paper").
        model_px: the fitting method's own error per axis, px (added to each centre's).
    """
    if center_covs is None:
        return None
    covs = np.asarray(center_covs, np.float64)
    if covs.shape != (2, 3, 2, 2) or not np.all(np.isfinite(covs)):
        return None
    cx = point_covariances(rig, centers, covs + model_px**2 * np.eye(2))
    G = _rigid_gain(T, model) if method == "rigid" else _numeric_gain(np.asarray(points3d, np.float64), model, method)
    big = np.zeros((9, 9))
    for i in range(3):
        big[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = cx[i]
    cov = G @ big @ G.T
    return 0.5 * (cov + cov.T)


def point_covariance(cov: np.ndarray, T: np.ndarray, point) -> np.ndarray:
    """(3, 3) covariance (mm^2) of a point fixed to the marker (``point`` (3,) in its frame,
    mm: a tool's tip) in the left-camera frame, from the pose's ``cov``."""
    J = np.hstack([np.eye(3), -skew(T[:3, :3] @ np.asarray(point, np.float64))])
    return J @ cov @ J.T


def relative_covariance(T_ref: np.ndarray, cov_ref: np.ndarray, T_tool: np.ndarray, cov_tool: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of T_reference_tool = inv(T_ref) @ T_tool, in the reference's frame
    (translation of the tool's origin, mm; rotation vector, rad), the two poses' errors
    independent (different rings; the rig's calibration left out as above)."""
    Rt = T_ref[:3, :3].T
    Z = np.zeros((3, 3))
    J_tool = np.block([[Rt, Z], [Z, Rt]])
    J_ref = np.block([[-Rt, Rt @ skew(T_tool[:3, 3] - T_ref[:3, 3])], [Z, -Rt]])
    cov = J_ref @ cov_ref @ J_ref.T + J_tool @ cov_tool @ J_tool.T
    return 0.5 * (cov + cov.T)


def sd_mm(cov: np.ndarray | None, T: np.ndarray, point=None) -> float:
    """The RMS 3D error one standard deviation means, mm: sqrt(trace) of the covariance of
    the marker's origin, or of ``point`` (marker frame, mm); NaN without a covariance."""
    if cov is None:
        return float("nan")
    c = cov[:3, :3] if point is None else point_covariance(cov, T, point)
    return float(np.sqrt(max(np.trace(c), 0.0)))


def sd_deg(cov: np.ndarray | None) -> float:
    """The RMS rotation error one standard deviation means, degrees (NaN without a covariance)."""
    if cov is None:
        return float("nan")
    return float(np.degrees(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))))


__all__ = ["point_covariance", "point_covariances", "pose_covariance", "relative_covariance", "sd_deg", "sd_mm", "skew"]
