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

from .camera import StereoRig, distort_point, undistort_point
from .jit import compiled

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
    if P.ndim == 2:  # one triple (every hypothesis refined asks for one): in floats, no array steps
        (a0, a1), (b0, b1), (c0, c1) = L.tolist()
        u0, u1, v0, v1 = b0 - a0, b1 - a1, c0 - a0, c1 - a1  # B = [[u0, v0], [u1, v1]]
        det = u0 * v1 - v0 * u1
        if det == 0:
            raise np.linalg.LinAlgError("the layout's three points are collinear")
        (p0, p1), (q0, q1), (r0, r1) = P.tolist()
        d00, d01, d10, d11 = q0 - p0, r0 - p0, q1 - p1, r1 - p1  # D = [[d00, d01], [d10, d11]]
        # D B^-1 with B^-1 = [[v1, -v0], [-u1, u0]] / det
        return np.array(
            [[(d00 * v1 - d01 * u1) / det, (d01 * u0 - d00 * v0) / det], [(d10 * v1 - d11 * u1) / det, (d11 * u0 - d10 * v0) / det]]
        )
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

    Points are undistorted to ideal pixels first, then each point's homogeneous system
    with ``P1 = K1 [I|0]`` and ``P2 = K2 [R|t]`` is solved by SVD (as
    ``cv2.triangulatePoints`` does; compiled, for three points at a time).

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
    X = np.empty((len(pl), 3))
    _dlt(rig.P1, rig.P2, ul, ur, X)
    return X


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
    key = (np.asarray(a, np.float64).tobytes() for a in (rig.left.K, rig.right.K, rig.R, rig.t))
    return _fundamental(*key)


@functools.lru_cache(maxsize=16)
def _fundamental(K1: bytes, K2: bytes, R: bytes, t: bytes) -> np.ndarray:
    """:func:`fundamental_matrix` of a rig given as its arrays' bytes (float64), read-only:
    computed once per rig state, however often the checks ask."""
    t = np.frombuffer(t)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ np.frombuffer(R).reshape(3, 3)
    F = np.linalg.inv(np.frombuffer(K2).reshape(3, 3)).T @ E @ np.linalg.inv(np.frombuffer(K1).reshape(3, 3))
    F.flags.writeable = False
    return F


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
    T = np.eye(4)
    _kabsch(np.ascontiguousarray(X), np.ascontiguousarray(M), T)
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


def minor_semi_axis(Q: np.ndarray) -> float:
    """The minor semi-axis of the ellipse (x - c)^T Q (x - c) = 1: one over the square root
    of Q's larger eigenvalue (closed form: this runs for every ring of every pair)."""
    (a, b), (_, d) = np.asarray(Q, np.float64).tolist()
    return 1.0 / math.sqrt(0.5 * (a + d) + math.hypot(0.5 * (a - d), b))


def cq_to_rect(c: np.ndarray, Q: np.ndarray) -> tuple:
    """(centre, Q) → RotatedRect ((cx, cy), (w, h), angle_deg), width = major axis along angle."""
    # The symmetric 2 x 2 eigen-decomposition in closed form (a ring's every fit makes one):
    # the smaller eigenvalue is the major axis', along 0.5 atan2(-2 q, r - p).
    (p, q), (_, r) = np.asarray(Q, np.float64).tolist()
    m, d = 0.5 * (p + r), math.hypot(0.5 * (p - r), q)
    ang = math.degrees(0.5 * math.atan2(-2.0 * q, r - p)) % 180.0
    return ((float(c[0]), float(c[1])), (2.0 / math.sqrt(m - d), 2.0 / math.sqrt(m + d)), ang)


def cq_to_conic(c: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(3, 3) conic ``x^T C x = 0`` of the ellipse (x - c)^T Q (x - c) = 1."""
    (q00, q01), (q10, q11) = Q.tolist()
    cx, cy = float(c[0]), float(c[1])
    d0, d1 = -(q00 * cx + q01 * cy), -(q10 * cx + q11 * cy)  # -Q c, in floats: a conic per ring per check
    return np.array([[q00, q01, d0], [q10, q11, d1], [d0, d1, -(d0 * cx + d1 * cy) - 1.0]])


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
    c2 = np.ascontiguousarray(centers2d, np.float64).reshape(-1, 2)
    out = np.empty((len(c2), 2))
    _ellipse_centres(camera.K, camera.dist, np.asarray(T_cam_plane, np.float64), c2, float(radius), out, False)
    return out


def perspective_bias(camera, T_cam_plane: np.ndarray, centers2d: np.ndarray, radius: float) -> np.ndarray:
    """(N, 2) imaged-ellipse centre minus projected circle centre, distorted px."""
    c2 = np.ascontiguousarray(centers2d, np.float64).reshape(-1, 2)
    out = np.empty((len(c2), 2))
    _ellipse_centres(camera.K, camera.dist, np.asarray(T_cam_plane, np.float64), c2, float(radius), out, True)
    return out


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
    model = np.ascontiguousarray(model, np.float64)
    xn = camera.undistort_points(np.asarray(centers, np.float64), ideal_pixels=False)
    n, rvecs, tvecs = cv2.solveP3P(model, xn, np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
    if not n:
        return []
    Ts = np.empty((n, 4, 4))
    Ts = Ts[: _rotated_poses(np.reshape(rvecs, (n, 3)).astype(np.float64), np.reshape(tvecs, (n, 3)).astype(np.float64), model, Ts)]
    if not len(Ts):  # degenerate, or behind the camera
        return []
    have = [k for k, e in enumerate(ellipses or []) if e is not None]
    misfit = np.zeros(len(Ts))
    if have:  # every pose's projected circles against the ellipses, in one compiled call
        C = np.stack([ellipse_to_conic(*ellipses[k]) for k in have])
        pts = _circle_points(model[have].tobytes(), len(have), float(radius), 24)
        _plate_misfit(Ts, C, pts, camera.K, camera.dist, misfit)
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


# --- compiled kernels: a few points at a time, where numpy's per-call cost would dominate ---
@compiled
def _dlt(P1, P2, ul, ur, X):  # pragma: no cover - compiled
    """Each row of ``X`` (N, 3): the DLT triangulation of the ideal pixels ``ul[i]``, ``ur[i]``
    (the right singular vector of the smallest singular value, as ``cv2.triangulatePoints``)."""
    A = np.empty((4, 4))
    for i in range(ul.shape[0]):
        for k in range(4):
            A[0, k] = ul[i, 0] * P1[2, k] - P1[0, k]
            A[1, k] = ul[i, 1] * P1[2, k] - P1[1, k]
            A[2, k] = ur[i, 0] * P2[2, k] - P2[0, k]
            A[3, k] = ur[i, 1] * P2[2, k] - P2[1, k]
        h = _least_singular_vector(A)
        for k in range(3):
            X[i, k] = h[k] / h[3]


@compiled
def triangulate_ideal(P1, P2, ul, ur, X):  # pragma: no cover - compiled
    """:func:`triangulate` of ideal pixels ``ul``, ``ur`` (N, 2) into ``X`` (N, 3), the
    projection matrices given (``rig.P1``, ``rig.P2``): callable from other compiled loops."""
    _dlt(P1, P2, ul, ur, X)


@compiled
def _least_singular_vector(A):  # pragma: no cover - compiled
    """The right singular vector of ``A``'s smallest singular value, by one-sided Jacobi
    rotations (as accurate as LAPACK's SVD, without its per-call cost on a 4 x 4)."""
    U = A.copy()
    n = U.shape[1]
    V = np.eye(n)
    for _ in range(60):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                alpha = beta = gamma = 0.0
                for r in range(U.shape[0]):
                    alpha += U[r, p] * U[r, p]
                    beta += U[r, q] * U[r, q]
                    gamma += U[r, p] * U[r, q]
                if abs(gamma) <= 1e-15 * np.sqrt(alpha * beta) or gamma == 0.0:
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = c * t
                for r in range(U.shape[0]):
                    up, uq = U[r, p], U[r, q]
                    U[r, p], U[r, q] = c * up - s * uq, s * up + c * uq
                for r in range(n):
                    vp, vq = V[r, p], V[r, q]
                    V[r, p], V[r, q] = c * vp - s * vq, s * vp + c * vq
        if not rotated:
            break
    best, smallest = 0, np.inf
    for k in range(n):
        norm = 0.0
        for r in range(U.shape[0]):
            norm += U[r, k] * U[r, k]
        if norm < smallest:
            best, smallest = k, norm
    return V[:, best].copy()


@compiled
def _kabsch(X, M, T):  # pragma: no cover - compiled
    """``T`` (4, 4, its last row 0 0 0 1) := the least-squares rigid fit of ``M`` onto ``X``."""
    n = X.shape[0]
    mx, mm = np.zeros(3), np.zeros(3)
    for i in range(n):
        mx += X[i]
        mm += M[i]
    mx /= n
    mm /= n
    H = np.zeros((3, 3))
    for i in range(n):
        H += np.outer(M[i] - mm, X[i] - mx)
    U, _, Vt = np.linalg.svd(H)
    flip = np.linalg.det(U) * np.linalg.det(Vt) < 0  # a reflection: turn the least singular direction
    for r in range(3):
        for c in range(3):
            T[r, c] = Vt[0, r] * U[c, 0] + Vt[1, r] * U[c, 1] + (-1.0 if flip else 1.0) * Vt[2, r] * U[c, 2]
        T[r, 3] = mx[r] - T[r, 0] * mm[0] - T[r, 1] * mm[1] - T[r, 2] * mm[2]


@compiled
def _ellipse_centres(K, dist, T, centres2d, radius, out, bias):  # pragma: no cover - compiled
    """Per circle of the plane z = 0 (centres ``centres2d``, ``radius``) under the pose ``T``:
    its imaged ellipse's centre in distorted pixels, or (``bias``) that minus the projected
    circle centre. An ellipse's centre is the pole of the line at infinity: its dual conic
    applied to (0, 0, 1); the image's dual conic is G C* G^T in normalised coordinates
    (G = [r1 r2 t]), with the circle's C* = m m^T - r^2 diag(1, 1, 0), m = (cx, cy, 1)."""
    for i in range(centres2d.shape[0]):
        cx, cy = centres2d[i, 0], centres2d[i, 1]
        g0, g1, g2 = T[2, 0], T[2, 1], T[2, 3]
        s = cx * g0 + cy * g1 + g2
        v0, v1, v2 = cx * s - radius * radius * g0, cy * s - radius * radius * g1, s
        q = np.empty(3)
        for r in range(3):
            q[r] = T[r, 0] * v0 + T[r, 1] * v1 + T[r, 3] * v2
        u, v = distort_point(q[0] / q[2], q[1] / q[2], K, dist)
        if bias:
            for r in range(3):
                q[r] = T[r, 0] * cx + T[r, 1] * cy + T[r, 3]
            pu, pv = distort_point(q[0] / q[2], q[1] / q[2], K, dist)
            u, v = u - pu, v - pv
        out[i, 0], out[i, 1] = u, v


@compiled
def _undistort_pairs(centers, K1, d1, K2, d2, ul, ur):  # pragma: no cover - compiled
    """Ideal pixels ``ul``, ``ur`` of the (2, N, 2) distorted ``centers``; False where
    Newton's method did not converge for a point (then the caller's fallback)."""
    ok = True
    for i in range(centers.shape[1]):
        x, y, good = undistort_point(centers[0, i, 0], centers[0, i, 1], K1, d1)
        ul[i, 0], ul[i, 1] = K1[0, 0] * x + K1[0, 1] * y + K1[0, 2], K1[1, 1] * y + K1[1, 2]
        ok = ok and good
        x, y, good = undistort_point(centers[1, i, 0], centers[1, i, 1], K2, d2)
        ur[i, 0], ur[i, 1] = K2[0, 0] * x + K2[0, 1] * y + K2[0, 2], K2[1, 1] * y + K2[1, 2]
        ok = ok and good
    return ok


@compiled
def _rigid_solve(measured, K1, d1, K2, d2, P1, P2, T_rl, model, centres2d, radius, rounds, centers, X, T):  # pragma: no cover - compiled
    """:func:`solve_rigid`'s work; returns the RMS reprojection (px), or -1 where an
    undistortion did not converge."""
    n = measured.shape[1]
    ul, ur, bias = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
    centers[:] = measured
    if not _undistort_pairs(centers, K1, d1, K2, d2, ul, ur):
        return -1.0
    _dlt(P1, P2, ul, ur, X)
    for _ in range(rounds):
        _kabsch(X, model, T)
        _ellipse_centres(K1, d1, T, centres2d, radius, bias, True)
        centers[0] = measured[0] - bias
        _ellipse_centres(K2, d2, T_rl @ T, centres2d, radius, bias, True)
        centers[1] = measured[1] - bias
        if not _undistort_pairs(centers, K1, d1, K2, d2, ul, ur):
            return -1.0
        _dlt(P1, P2, ul, ur, X)
    _kabsch(X, model, T)
    sq = 0.0
    Tr = T_rl @ T
    p = np.empty(3)
    for i in range(n):
        for view in range(2):
            A, K, d = (T, K1, d1) if view == 0 else (Tr, K2, d2)
            for r in range(3):
                p[r] = A[r, 0] * model[i, 0] + A[r, 1] * model[i, 1] + A[r, 2] * model[i, 2] + A[r, 3]
            u, v = distort_point(p[0] / p[2], p[1] / p[2], K, d)
            sq += (u - centers[view, i, 0]) ** 2 + (v - centers[view, i, 1]) ** 2
    return np.sqrt(sq / (2 * n))


@compiled
def _rotated_poses(rvecs, tvecs, model, Ts):  # pragma: no cover - compiled
    """P3P's solutions (rotation vectors (n, 3), translations (n, 3)) as poses into ``Ts``,
    those that are finite and put every ``model`` point in front of the camera first;
    returns their number."""
    count = 0
    for k in range(rvecs.shape[0]):
        rx, ry, rz = rvecs[k, 0], rvecs[k, 1], rvecs[k, 2]
        th = np.sqrt(rx * rx + ry * ry + rz * rz)
        R = np.eye(3)
        if th > 0:
            x, y, z = rx / th, ry / th, rz / th
            c, s = np.cos(th), np.sin(th)
            C = 1.0 - c
            R[0, 0], R[0, 1], R[0, 2] = c + x * x * C, x * y * C - z * s, x * z * C + y * s
            R[1, 0], R[1, 1], R[1, 2] = y * x * C + z * s, c + y * y * C, y * z * C - x * s
            R[2, 0], R[2, 1], R[2, 2] = z * x * C - y * s, z * y * C + x * s, c + z * z * C
        good = np.isfinite(th) and np.isfinite(tvecs[k, 0]) and np.isfinite(tvecs[k, 1]) and np.isfinite(tvecs[k, 2])
        for i in range(model.shape[0]):
            if not good:
                break
            good = R[2, 0] * model[i, 0] + R[2, 1] * model[i, 1] + R[2, 2] * model[i, 2] + tvecs[k, 2] > 0
        if not good:
            continue
        Ts[count] = 0.0
        Ts[count, :3, :3] = R
        for r in range(3):
            Ts[count, r, 3] = tvecs[k, r]
        Ts[count, 3, 3] = 1.0
        count += 1
    return count


@compiled
def _plate_misfit(Ts, C, pts, K, dist, misfit):  # pragma: no cover - compiled
    """Per pose ``Ts[p]``: the mean relative radial distance of the rings' projected circle
    points ``pts`` (R * n, 3; n per ring, marker frame) from the fitted ellipses' conics
    ``C`` (R, 3, 3): (x - c)^T A (x - c) = lambda^2, |lambda - 1| averaged."""
    rings = C.shape[0]
    n = pts.shape[0] // rings
    for p in range(Ts.shape[0]):
        T = Ts[p]
        total = 0.0
        for r in range(rings):
            for j in range(n):
                q = pts[r * n + j]
                z = T[2, 0] * q[0] + T[2, 1] * q[1] + T[2, 2] * q[2] + T[2, 3]
                x = (T[0, 0] * q[0] + T[0, 1] * q[1] + T[0, 2] * q[2] + T[0, 3]) / z
                y = (T[1, 0] * q[0] + T[1, 1] * q[1] + T[1, 2] * q[2] + T[1, 3]) / z
                u, v = distort_point(x, y, K, dist)
                h = (u, v, 1.0)
                lam2 = 1.0
                for a in range(3):
                    for b in range(3):
                        lam2 += h[a] * C[r, a, b] * h[b]
                total += abs(np.sqrt(max(lam2, 0.0)) - 1.0)
        misfit[p] = total / (rings * n)


def solve_rigid(rig: StereoRig, centers: np.ndarray, model: np.ndarray, centres2d: np.ndarray, radius: float, rounds: int):
    """The rigid pose from matched centres of both views, each view's perspective bias of
    ellipse centres removed ``rounds`` times (:func:`perspective_bias` under the pose so
    far, then triangulated again), in one compiled call.

    Args:
        centers: (2, N, 2) the views' measured ellipse centres, distorted px.
        model: (N, 3) the marker's centres (mm); ``centres2d`` (N, 2) the same on its plate;
            ``radius`` the rings' outer radius, mm.
    Returns:
        (centers (2, N, 2) corrected, points3d (N, 3), T_left_marker (4, 4), RMS reprojection
        px of the model under T against the corrected centres), or None where a centre lies
        where the lens model's Newton inversion does not converge (the caller's numpy path
        then falls back to OpenCV's iteration).
    """
    measured = np.ascontiguousarray(centers, np.float64)
    out, X, T = np.empty_like(measured), np.empty((measured.shape[1], 3)), np.eye(4)
    L, R = rig.cameras
    args = (L.K, L.dist, R.K, R.dist, rig.P1, rig.P2, rig.T_right_left, np.ascontiguousarray(model, np.float64))
    rms = _rigid_solve(measured, *args, np.ascontiguousarray(centres2d, np.float64), float(radius), int(rounds), out, X, T)
    return None if rms < 0 else (out, X, T, float(rms))


_GEOMETRY_WARM = False


def warm_up() -> None:
    """Compile the geometry kernels (or load them from numba's cache) once per process."""
    global _GEOMETRY_WARM
    if not _GEOMETRY_WARM:
        rig = StereoRig.default()
        model = np.array([[0.0, 0, 0], [25, 0, 0], [0, 40, 0]])
        X = model + [0.0, 0.0, 500.0]
        solve_rigid(rig, np.stack(rig.project(X)), model, model[:, :2], 10.0, 1)
        triangulate(rig, *rig.project(X))
        perspective_bias(rig.left, pose_rigid(X, model), model[:, :2], 10.0)
        imaged_circle_centers(rig.left, pose_rigid(X, model), model[:, :2], 10.0)
        T = np.eye(4)
        T[2, 3] = 500.0
        view_poses(rig.left, rig.project(X)[0], ring_ellipses(rig.left, T, model, 10.0), model, 10.0)
        _GEOMETRY_WARM = True
