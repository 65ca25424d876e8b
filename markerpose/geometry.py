"""Pure geometry on numpy arrays: triangulation, pose from three points, conics.

No I/O here. Units: mm and radians. Frames: the left camera is the world;
``T_left_marker`` maps marker coordinates to left-camera coordinates.
"""

from __future__ import annotations

import cv2
import numpy as np

from .camera import StereoRig

POSE_METHODS = ("paper", "rigid")


# --- triangulation ------------------------------------------------------------------
def layout_affine(points: np.ndarray, layout: np.ndarray) -> np.ndarray:
    """The linear part A of the affine map taking the marker's layout (3, 2) to three
    image points ((3, 2), or (T, 3, 2) for many at once): ``p_j - p_0 = A (l_j - l_0)``.
    Returns (2, 2) or (T, 2, 2)."""
    P = np.asarray(points, np.float64)
    L = np.asarray(layout, np.float64)
    B = np.column_stack([L[1] - L[0], L[2] - L[0]])
    return np.stack([P[..., 1, :] - P[..., 0, :], P[..., 2, :] - P[..., 0, :]], -1) @ np.linalg.inv(B)


def triangulate(rig: StereoRig, p2d_left: np.ndarray, p2d_right: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of corresponding distorted pixels, as the paper does.

    Points are undistorted to ideal pixels first, then ``cv2.triangulatePoints``
    solves the homogeneous system with ``P1 = K1 [I|0]`` and ``P2 = K2 [R|t]``.

    Args:
        rig: the calibrated stereo rig.
        p2d_left, p2d_right: (N, 2) corresponding pixel coordinates in each view.
    Returns:
        (N, 3) points in the left-camera frame, mm.
    """
    pl = np.asarray(p2d_left, dtype=np.float64).reshape(-1, 2)
    pr = np.asarray(p2d_right, dtype=np.float64).reshape(-1, 2)
    if pl.shape != pr.shape:
        raise ValueError(f"p2d_left and p2d_right differ in shape: {pl.shape} vs {pr.shape}")
    ul = rig.left.undistort_points(pl)
    ur = rig.right.undistort_points(pr)
    X = cv2.triangulatePoints(rig.P1, rig.P2, ul.T.copy(), ur.T.copy())
    return (X[:3] / X[3]).T


def epipolar_distance(rig: StereoRig, p2d_left: np.ndarray, p2d_right: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance (px) between distorted pixel correspondences.

    Args:
        p2d_left: (N, 2), p2d_right: (M, 2) distorted pixels.
    Returns:
        (N, M) mean of the two point-to-epipolar-line distances, ideal pixels.
    """
    ul = rig.left.undistort_points(p2d_left)
    ur = rig.right.undistort_points(p2d_right)
    F = fundamental_matrix(rig)
    hl = np.column_stack([ul, np.ones(len(ul))])
    hr = np.column_stack([ur, np.ones(len(ur))])
    lines_r = hl @ F.T  # (N, 3) epipolar lines in the right image
    lines_l = hr @ F  # (M, 3) epipolar lines in the left image
    d_r = np.abs(lines_r @ hr.T) / np.linalg.norm(lines_r[:, :2], axis=1, keepdims=True)
    d_l = np.abs(hl @ lines_l.T) / np.linalg.norm(lines_l[:, :2], axis=1)[None, :]
    return 0.5 * (d_r + d_l)


def fundamental_matrix(rig: StereoRig) -> np.ndarray:
    """(3, 3) F with ``x_r^T F x_l = 0`` for ideal (undistorted) pixels."""
    t = rig.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ rig.R
    return np.linalg.inv(rig.right.K).T @ E @ np.linalg.inv(rig.left.K)


# --- pose from three points -------------------------------------------------------
def pose_paper(points3d: np.ndarray) -> np.ndarray:
    """The paper's pose from the triangulated centres c0, c1, c2.

    ``t = X0``, ``x̂ = (X1 - X0)/|.|``, ``ŷ = (X2 - X0)/|.|``, ``ẑ = x̂ × ŷ``,
    ``R = [x̂ ŷ ẑ]``. Note: x̂ and ŷ are not exactly orthogonal with noisy points,
    so this R is not exactly orthonormal — kept as published (the reference).

    Args:
        points3d: (3, 3) c0, c1, c2 in the left-camera frame, mm.
    Returns:
        (4, 4) T_left_marker.
    """
    X = np.asarray(points3d, dtype=np.float64).reshape(3, 3)
    x = X[1] - X[0]
    y = X[2] - X[0]
    x = x / np.linalg.norm(x)
    y = y / np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, np.cross(x, y)])
    T[:3, 3] = X[0]
    return T


def pose_rigid(points3d: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Least-squares rigid fit (orthonormal R, no scale) of the model points to the measured ones.

    Minimises ``sum |R m_i + t - X_i|^2`` (Kabsch / Umeyama without scale).

    Args:
        points3d: (N, 3) measured points in the left-camera frame, mm (N >= 3).
        model: (N, 3) the same points in the marker frame, mm.
    Returns:
        (4, 4) T_left_marker with R in SO(3).
    """
    X = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
    M = np.asarray(model, dtype=np.float64).reshape(-1, 3)
    if X.shape != M.shape or len(X) < 3:
        raise ValueError(f"need matching (N>=3, 3) point sets, got {X.shape} and {M.shape}")
    mx, mm = X.mean(0), M.mean(0)
    H = (M - mm).T @ (X - mx)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mx - R @ mm
    return T


def pose_from_points(points3d: np.ndarray, model: np.ndarray, method: str = "paper") -> np.ndarray:
    """Dispatch to :func:`pose_paper` or :func:`pose_rigid` (``method`` in ``POSE_METHODS``)."""
    if method == "paper":
        return pose_paper(points3d)
    if method == "rigid":
        return pose_rigid(points3d, model)
    raise ValueError(f"unknown pose method {method!r}; choose from {POSE_METHODS}")


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (rad) of ``R_a^T R_b`` by the paper's formula ``arccos((tr - 1) / 2)`` (clipped)."""
    c = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (rad) about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    R, _ = cv2.Rodrigues(a * angle)
    return R


# --- conics ---------------------------------------------------------------------------
def circle_conic(center: np.ndarray, radius: float) -> np.ndarray:
    """(3, 3) conic ``x^T C x = 0`` of a circle in the plane (homogeneous 2D coordinates)."""
    cx, cy = center
    return np.array([[1.0, 0, -cx], [0, 1.0, -cy], [-cx, -cy, cx * cx + cy * cy - radius * radius]])


def project_conic(C: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Image of a conic under the homography ``H`` (plane → image): ``H^-T C H^-1``, normalised."""
    Hi = np.linalg.inv(H)
    D = Hi.T @ C @ Hi
    D = 0.5 * (D + D.T)
    return D / np.abs(D).max()


def conic_center(C: np.ndarray) -> np.ndarray:
    """(2,) centre of the ellipse/hyperbola ``C``: ``-A^-1 b``."""
    C = np.asarray(C, dtype=np.float64)
    return -np.linalg.solve(C[:2, :2], C[:2, 2])


def ellipse_to_conic(center, axes, angle_deg) -> np.ndarray:
    """Conic of an ellipse given as OpenCV's RotatedRect ((cx, cy), (w, h), angle in degrees)."""
    cx, cy = center
    a, b = axes[0] / 2.0, axes[1] / 2.0
    th = np.deg2rad(angle_deg)
    c, s = np.cos(th), np.sin(th)
    Rm = np.array([[c, -s], [s, c]])
    A = Rm @ np.diag([1 / a**2, 1 / b**2]) @ Rm.T
    ctr = np.array([cx, cy])
    C = np.zeros((3, 3))
    C[:2, :2] = A
    C[:2, 2] = C[2, :2] = -A @ ctr
    C[2, 2] = ctr @ A @ ctr - 1.0
    return C


def imaged_circle_centers(camera, T_cam_plane: np.ndarray, centers2d: np.ndarray, radius: float) -> np.ndarray:
    """Centres of the ellipses that circles of the plane z = 0 make in the image.

    The ellipse centre is not the image of the circle's centre under perspective
    (the "perspective bias"); this is where an ellipse fit lands. The centre is
    computed in ideal pixels and mapped through the lens distortion.

    Args:
        camera: the :class:`~markerpose.camera.Camera`.
        T_cam_plane: (4, 4) plane → camera.
        centers2d: (N, 2) circle centres in the plane, mm.
        radius: circle radius, mm.
    Returns:
        (N, 2) distorted pixel coordinates of the imaged ellipses' centres.
    """
    H = plane_homography(camera.K, T_cam_plane)
    ideal = np.stack([conic_center(project_conic(circle_conic(c, radius), H)) for c in np.asarray(centers2d)])
    Kinv = np.linalg.inv(camera.K)
    xn = ideal @ Kinv[:2, :2].T + Kinv[:2, 2]
    return camera.distort(xn)


def perspective_bias(camera, T_cam_plane: np.ndarray, centers2d: np.ndarray, radius: float) -> np.ndarray:
    """(N, 2) imaged-ellipse centre minus projected circle centre, distorted px."""
    c3 = np.column_stack([np.asarray(centers2d, dtype=np.float64), np.zeros(len(centers2d))])
    return imaged_circle_centers(camera, T_cam_plane, centers2d, radius) - camera.project(c3 @ T_cam_plane[:3, :3].T + T_cam_plane[:3, 3])


def plane_homography(K: np.ndarray, T_cam_plane: np.ndarray) -> np.ndarray:
    """(3, 3) homography from plane coordinates (x, y, 1) (z = 0) to ideal pixels: ``K [r1 r2 t]``."""
    return K @ np.column_stack([T_cam_plane[:3, 0], T_cam_plane[:3, 1], T_cam_plane[:3, 3]])
