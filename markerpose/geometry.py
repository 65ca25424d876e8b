"""Pure geometry on numpy arrays: triangulation, pose from three points, conics, the
marker's layout in an image and its plate poses in one view.

No I/O here. Units: mm and radians. Frames: the left camera is the world;
``T_left_marker`` maps marker coordinates to left-camera coordinates.
"""

from __future__ import annotations

import functools
import itertools
import math

import cv2
import numpy as np

from .camera import StereoRig

POSE_METHODS = ("paper", "rigid")
# A pose's rotation part read from a file may depart from a rotation by this much (max of
# |R^T R - I|): the paper's construction R = [x y x×y] is not exactly orthonormal.
POSE_ROTATION_TOL = 0.02


# --- the marker's layout in an image -----------------------------------------------------
def layout_affine(points: np.ndarray, layout: np.ndarray) -> np.ndarray:
    """The linear part A of the affine map taking the marker's layout (3, 2) to three
    image points ((3, 2), or (T, 3, 2) for many at once): ``p_j - p_0 = A (l_j - l_0)``.
    Returns (2, 2) or (T, 2, 2)."""
    P = np.asarray(points, np.float64)
    L = np.asarray(layout, np.float64)
    B = np.column_stack([L[1] - L[0], L[2] - L[0]])
    return np.stack([P[..., 1, :] - P[..., 0, :], P[..., 2, :] - P[..., 0, :]], -1) @ np.linalg.inv(B)


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


_TRIPLES: dict = {}  # n → triple_orders(n)


def triple_orders(n: int) -> np.ndarray:
    """Every triple of ``n`` points in each of its six ID orders, as indices (6 C(n, 3), 3):
    row 6 t + o is triple t (in ``itertools.combinations`` order) in order o (in
    ``itertools.permutations`` order); column j is the point taking ID j."""
    if n not in _TRIPLES:
        trios = np.array(list(itertools.combinations(range(n), 3)), int).reshape(-1, 3)
        _TRIPLES[n] = trios[:, list(itertools.permutations(range(3)))].reshape(-1, 3)
    return _TRIPLES[n]


def ring_diameter(points: np.ndarray, marker) -> float:
    """Apparent outer diameter (px) of the rings at three image points c0, c1, c2 (3, 2),
    judged from their spacing: the larger of |c1 - c0| and |c2 - c0| scaled by the
    marker's diameter over the printed distance."""
    p = np.asarray(points, np.float64)
    return max(np.linalg.norm(p[i] - p[0]) * marker.outer_diameter / np.linalg.norm(marker.centers2d[i]) for i in (1, 2))


# --- triangulation ------------------------------------------------------------------


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


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation nearest ``R`` (3, 3) in the Frobenius norm (SVD; the paper's
    pose is not exactly orthonormal)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


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


def rect_to_cq(rect) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV RotatedRect ((cx, cy), (w, h), angle_deg) → (centre (2,), Q (2, 2)) with
    (x - c)^T Q (x - c) = 1."""
    (cx, cy), (w, h), ang = rect
    a, b = max(w, 1e-6) / 2.0, max(h, 1e-6) / 2.0
    t = math.radians(ang)
    c, s = math.cos(t), math.sin(t)
    ia, ib = 1 / a**2, 1 / b**2  # R diag(ia, ib) R^T, R the rotation by the angle
    q01 = c * s * (ia - ib)
    return np.array([cx, cy], float), np.array([[c * c * ia + s * s * ib, q01], [q01, s * s * ia + c * c * ib]])


def cq_to_rect(c: np.ndarray, Q: np.ndarray) -> tuple:
    """(centre, Q) → RotatedRect ((cx, cy), (w, h), angle_deg), width = major axis along angle."""
    lam, V = np.linalg.eigh(Q)  # ascending: lam[0] ↔ major axis
    a, b = 1 / np.sqrt(lam[0]), 1 / np.sqrt(lam[1])
    ang = np.degrees(np.arctan2(V[1, 0], V[0, 0])) % 180.0
    return ((float(c[0]), float(c[1])), (float(2 * a), float(2 * b)), float(ang))


def cq_to_conic(c: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(3, 3) conic ``x^T C x = 0`` of the ellipse (x - c)^T Q (x - c) = 1."""
    C = np.zeros((3, 3))
    C[:2, :2] = Q
    C[:2, 2] = C[2, :2] = -Q @ c
    C[2, 2] = c @ Q @ c - 1.0
    return C


def ellipse_to_conic(center, axes, angle_deg) -> np.ndarray:
    """Conic of an ellipse given as OpenCV's RotatedRect ((cx, cy), (w, h), angle in degrees)."""
    return cq_to_conic(*rect_to_cq((center, axes, angle_deg)))


def sqrtm_spd(Q: np.ndarray, power: float = 0.5) -> np.ndarray:
    """``Q`` (symmetric positive definite, (2, 2) or a stack (..., n, n)) to a real
    ``power`` (0.5: its square root)."""
    lam, V = np.linalg.eigh(Q)
    return (V * lam[..., None, :] ** power) @ np.swapaxes(V, -1, -2)


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
    # An ellipse's centre is the pole of the line at infinity: its dual conic applied to
    # (0, 0, 1). The image's dual conic is H C* H^T, with the circle's dual conic
    # C* = m m^T - r^2 diag(1, 1, 0), m = (cx, cy, 1): all circles at once.
    m = np.column_stack([np.asarray(centers2d, np.float64).reshape(-1, 2), np.ones(len(centers2d))])
    h = H[2]
    pole = (m * (m @ h)[:, None] - radius**2 * np.array([h[0], h[1], 0.0])) @ H.T
    ideal = pole[:, :2] / pole[:, 2:]
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


# --- the marker's plate in one view ----------------------------------------------------
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
    Ts = []
    for rv, tv in zip(rvecs[:n], tvecs[:n]):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rv)[0], np.ravel(tv)
        if not np.isfinite(T).all() or np.any(model @ T[2, :3] + T[2, 3] <= 0):
            continue  # degenerate, or behind the camera
        Ts.append(T)
    if not Ts:
        return []
    have = [k for k, e in enumerate(ellipses or []) if e is not None]
    misfit = np.zeros(len(Ts))
    if have:  # every pose's projected circles against the ellipses, in one batch
        C = np.stack([ellipse_to_conic(*ellipses[k]) for k in have])
        edges = ring_edges(camera, np.stack(Ts), model[have], radius)  # (P, R, n, 2)
        h = np.concatenate([edges, np.ones(edges.shape[:-1] + (1,))], axis=-1)
        lam2 = np.einsum("prni,rij,prnj->prn", h, C, h) + 1.0  # (p - c)^T A (p - c) = lambda^2
        misfit = np.abs(np.sqrt(np.maximum(lam2, 0)) - 1).mean(2).mean(1)
    poses = [(float(m), T) for m, T in zip(misfit, Ts) if np.isfinite(m)]
    poses.sort(key=lambda p: p[0])
    return poses


def ring_edges(camera, T_cam_marker: np.ndarray, model: np.ndarray, radius: float, n: int = 24) -> np.ndarray:
    """(3, n, 2) distorted pixels of ``n`` points on each ring's outer circle in a view
    where the marker has pose ``T_cam_marker`` (``model``: the ring centres, mm); for a
    stack of P poses (P, 4, 4), (P, 3, n, 2)."""
    T = np.asarray(T_cam_marker, np.float64)
    model = np.asarray(model, np.float64)
    pts = _circle_points(model.tobytes(), len(model), float(radius), int(n))
    cam = np.einsum("...ij,mj->...mi", T[..., :3, :3], pts) + T[..., None, :3, 3]
    return camera.project(cam.reshape(-1, 3)).reshape(T.shape[:-2] + (len(model), n, 2))


@functools.lru_cache(maxsize=16)
def _circle_points(model: bytes, count: int, radius: float, n: int) -> np.ndarray:
    """(count * n, 3) points of the rings' circles (centres ``model``, (count, 3) float64
    as bytes) in the marker frame, read-only (computed once per marker)."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    circle = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)]) * radius
    pts = (np.frombuffer(model).reshape(count, 3)[:, None, :] + circle[None]).reshape(-1, 3)
    pts.flags.writeable = False
    return pts


def ring_ellipses(camera, T_cam_marker: np.ndarray, model: np.ndarray, radius: float) -> list:
    """The rings' outer ellipses (OpenCV RotatedRects) in a view where the marker has pose
    ``T_cam_marker``: ellipses fitted to the projected circles (lens distortion included)."""
    return [cv2.fitEllipseDirect(e.astype(np.float32)) for e in ring_edges(camera, T_cam_marker, model, radius, 36)]
