"""Tests for markerpose.geometry: triangulation, epipolar distance, pose from three points, conics."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from markerpose import Marker
from markerpose import geometry as g

SIGMA_PX = 0.05  # pixel noise of the synthetic "detections"


@pytest.fixture(scope="module")
def model() -> np.ndarray:
    return Marker().points3d


def _working_volume(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) points 350..800 mm deep, within 40 mm of the left optical axis (seen by both views)."""
    return np.column_stack([rng.uniform(-40, 40, (n, 2)), rng.uniform(350, 800, n)])


def _random_pose(rng: np.random.Generator, max_tilt_deg: float = 60.0) -> np.ndarray:
    """T_left_marker: the marker faces the left camera (z toward it), tilted up to ``max_tilt_deg``."""
    face = np.diag([1.0, -1.0, -1.0])  # marker z = -camera z: the printed face looks at the camera
    tilt = g.rotation_about_axis(np.append(rng.normal(size=2), 0.0), np.deg2rad(rng.uniform(0, max_tilt_deg)))
    spin = g.rotation_about_axis([0, 0, 1], rng.uniform(-np.pi, np.pi))
    T = np.eye(4)
    T[:3, :3] = tilt @ face @ spin
    T[:3, 3] = _working_volume(rng, 1)[0] - T[:3, :3] @ [12.5, 20.0, 0.0]  # marker centre in the volume
    return T


def _apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X @ T[:3, :3].T + T[:3, 3]


def _triangulated_centres(rig, T, model, rng=None, sigma=0.0):
    uv = rig.project(_apply(T, model))
    if rng is not None:
        uv = uv + rng.normal(0.0, sigma, uv.shape)
    return g.triangulate(rig, uv[0], uv[1])


# --- triangulation ---------------------------------------------------------------------
class TestTriangulate:
    def test_shapes(self, rig):
        P = _working_volume(np.random.default_rng(0), 5)
        uv = rig.project(P)
        assert g.triangulate(rig, uv[0], uv[1]).shape == (5, 3)
        assert g.triangulate(rig, uv[0, 0], uv[1, 0]).shape == (1, 3)

    def test_exact_projections(self, rig):
        P = _working_volume(np.random.default_rng(1), 500)
        uv = rig.project(P)
        X = g.triangulate(rig, uv[0], uv[1])
        assert np.abs(X - P).max() <= 1e-6

    def test_noise_matches_first_order_prediction(self, rig):
        """0.05 px noise: RMS 3D error agrees with the propagated covariance (~0.06 mm here)."""
        rng = np.random.default_rng(2)
        P = _working_volume(rng, 1500)
        uv = rig.project(P)
        X = g.triangulate(rig, *(uv + rng.normal(0.0, SIGMA_PX, uv.shape)))
        rms = np.sqrt(np.mean(np.sum((X - P) ** 2, axis=1)))
        # Predicted: sigma^2 tr((J^T J)^-1), J = d(both projections)/dX by central differences.
        h = 1e-3
        J = np.stack([(rig.project(P + d) - rig.project(P - d)) / (2 * h) for d in np.eye(3) * h], axis=-1)
        J = J.transpose(1, 0, 2, 3).reshape(len(P), 4, 3)
        pred = np.sqrt(np.mean(SIGMA_PX**2 * np.trace(np.linalg.inv(J.transpose(0, 2, 1) @ J), axis1=1, axis2=2)))
        assert 0.02 < rms < 0.1
        assert rms == pytest.approx(pred, rel=0.1)

    def test_depth_error_dominates_and_grows_with_distance(self, rig):
        rng = np.random.default_rng(3)
        err = {}
        for z in (400.0, 750.0):
            P = np.column_stack([rng.uniform(-20, 20, (800, 2)), np.full(800, z)])
            uv = rig.project(P)
            X = g.triangulate(rig, *(uv + rng.normal(0.0, SIGMA_PX, uv.shape)))
            err[z] = np.sqrt(np.mean((X - P) ** 2, axis=0))  # per-axis RMS
        for z in err:
            assert err[z][2] > err[z][0] and err[z][2] > err[z][1]
        # Depth error scales roughly like z^2: (750/400)^2 = 3.5.
        assert 2.5 < err[750.0][2] / err[400.0][2] < 5.0

    def test_mismatched_shapes(self, rig):
        with pytest.raises(ValueError, match="differ in shape"):
            g.triangulate(rig, np.zeros((3, 2)), np.zeros((2, 2)))


class TestEpipolarDistance:
    def test_shape(self, rig):
        uv = rig.project(_working_volume(np.random.default_rng(4), 6))
        assert g.epipolar_distance(rig, uv[0], uv[1, :4]).shape == (6, 4)

    def test_true_and_wrong_correspondences(self, rig):
        P = _working_volume(np.random.default_rng(5), 40)
        uv = rig.project(P)
        D = g.epipolar_distance(rig, uv[0], uv[1])
        assert np.abs(np.diag(D)).max() < 1e-6
        off = D[~np.eye(len(P), dtype=bool)]
        assert np.median(off) > 20.0

    def test_perpendicular_offset_is_measured(self, rig):
        # Moving the right point off its epipolar line by d px gives a distance of order d;
        # moving it along the line is invisible (the depth ambiguity the matcher must live with).
        P = np.array([[5.0, -10.0, 500.0]])
        uv = rig.project(P)
        uv_far = rig.project(P * 1.2)  # same ray from the left camera
        along = g.epipolar_distance(rig, uv[0], uv_far[1])
        assert along[0, 0] < 1e-6
        direction = (uv_far[1] - uv[1])[0]
        normal = np.array([-direction[1], direction[0]]) / np.linalg.norm(direction)
        d = g.epipolar_distance(rig, uv[0], uv[1] + 3.0 * normal)[0, 0]
        assert 2.0 < d < 4.0

    def test_fundamental_matrix(self, rig):
        P = _working_volume(np.random.default_rng(6), 30)
        xl = P @ rig.left.K.T
        xr = rig.to_right(P) @ rig.right.K.T
        F = g.fundamental_matrix(rig)
        assert F.shape == (3, 3)
        xl, xr = xl / xl[:, 2:], xr / xr[:, 2:]
        res = np.einsum("ni,ij,nj->n", xr, F / np.linalg.norm(F), xl)
        # Relative to the size of the terms (|x| ~ 1e3 px): zero to rounding.
        assert np.abs(res / (np.linalg.norm(xr, axis=1) * np.linalg.norm(xl, axis=1))).max() < 1e-13
        assert abs(np.linalg.det(F)) < 1e-12 * np.linalg.norm(F) ** 3


# --- pose from three points ----------------------------------------------------------------
class TestPose:
    @pytest.mark.parametrize("seed", range(5))
    def test_paper_exact(self, rig, model, seed):
        """Exact centres: the paper's R = [x̂ ŷ x̂×ŷ], t = X0 is the true pose."""
        T = _random_pose(np.random.default_rng(seed))
        Tp = g.pose_paper(_triangulated_centres(rig, T, model))
        assert Tp.shape == (4, 4)
        np.testing.assert_allclose(Tp[3], [0, 0, 0, 1])
        np.testing.assert_allclose(Tp[:3, 3], T[:3, 3], atol=1e-6)
        np.testing.assert_allclose(Tp[:3, :3], T[:3, :3], atol=1e-9)

    def test_paper_formula(self):
        X = np.array([[1.0, 2.0, 500.0], [26.0, 2.0, 500.0], [1.0, 42.0, 500.0]])
        T = g.pose_paper(X)
        np.testing.assert_allclose(T[:3, 3], X[0])
        np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-15)

    def test_paper_not_orthonormal_on_noise(self, rig, model):
        """Documented behaviour: with noise x̂ and ŷ are not orthogonal, so R is not in SO(3).

        Columns x̂, ŷ stay unit; ẑ = x̂ × ŷ is orthogonal to both but shorter than 1,
        so det(R) = |x̂ × ŷ|^2 < 1. The deviation is small (of the order of the noise).
        """
        assert "not exactly orthonormal" in g.pose_paper.__doc__
        rng = np.random.default_rng(7)
        dots, dets = [], []
        for _ in range(50):
            T = _random_pose(rng)
            R = g.pose_paper(_triangulated_centres(rig, T, model, rng, SIGMA_PX))[:3, :3]
            np.testing.assert_allclose(np.linalg.norm(R[:, :2], axis=0), 1.0, atol=1e-12)
            np.testing.assert_allclose(R[:, :2].T @ R[:, 2], 0.0, atol=1e-12)
            dots.append(R[:, 0] @ R[:, 1])
            dets.append(np.linalg.det(R))
        dots, dets = np.abs(dots), np.array(dets)
        assert np.all(dets < 1.0) and np.all(dets > 0.999)
        np.testing.assert_allclose(dets, 1.0 - dots**2, atol=1e-12)
        assert 1e-5 < np.median(dots) < 1e-2

    @pytest.mark.parametrize("seed", range(5))
    def test_rigid_exact(self, rig, model, seed):
        T = _random_pose(np.random.default_rng(seed))
        Tr = g.pose_rigid(_triangulated_centres(rig, T, model), model)
        np.testing.assert_allclose(Tr[3], [0, 0, 0, 1])
        np.testing.assert_allclose(Tr[:3, 3], T[:3, 3], atol=1e-6)
        np.testing.assert_allclose(Tr[:3, :3], T[:3, :3], atol=1e-9)

    def test_rigid_in_SO3_on_noise(self, rig, model):
        rng = np.random.default_rng(8)
        for _ in range(30):
            T = _random_pose(rng)
            R = g.pose_rigid(_triangulated_centres(rig, T, model, rng, 10 * SIGMA_PX), model)[:3, :3]
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)

    def test_rigid_never_reflects(self):
        # Mirrored measurements: the best rotation, never a reflection (det = +1).
        M = np.array([[0.0, 0, 0], [25, 0, 0], [0, 40, 0], [10, 10, 5]])
        X = M * [1, 1, -1] + [0, 0, 500]
        R = g.pose_rigid(X, M)[:3, :3]
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)

    def test_rigid_more_points_and_arbitrary_model(self):
        rng = np.random.default_rng(9)
        M = rng.uniform(-50, 50, (8, 3))
        T = np.eye(4)
        T[:3, :3] = g.rotation_about_axis(rng.normal(size=3), 2.0)
        T[:3, 3] = [10, -20, 600]
        np.testing.assert_allclose(g.pose_rigid(_apply(T, M), M), T, atol=1e-10)

    def test_rigid_no_worse_than_paper_on_average(self, rig, model):
        """Agreement between methods: both near the truth; the rigid fit is at least as good."""
        rng = np.random.default_rng(10)
        errs = {m: ([], []) for m in g.POSE_METHODS}
        for _ in range(200):
            T = _random_pose(rng)
            X = _triangulated_centres(rig, T, model, rng, SIGMA_PX)
            for m in g.POSE_METHODS:
                Te = g.pose_from_points(X, model, method=m)
                errs[m][0].append(np.linalg.norm(Te[:3, 3] - T[:3, 3]))
                errs[m][1].append(g.rotation_angle(T[:3, :3], Te[:3, :3]))
        t_p, r_p = (np.mean(e) for e in errs["paper"])
        t_r, r_r = (np.mean(e) for e in errs["rigid"])
        # Both near the truth (0.05 px noise → hundredths of a mm, tenths of a degree at most).
        assert t_p < 0.1 and t_r < 0.1
        assert np.rad2deg(r_p) < 0.3 and np.rad2deg(r_r) < 0.3
        assert t_r <= t_p and r_r <= r_p

    def test_pose_from_points_dispatch(self, rig, model):
        T = _random_pose(np.random.default_rng(11))
        X = _triangulated_centres(rig, T, model, np.random.default_rng(12), SIGMA_PX)
        np.testing.assert_array_equal(g.pose_from_points(X, model), g.pose_paper(X))
        np.testing.assert_array_equal(g.pose_from_points(X, model, "paper"), g.pose_paper(X))
        np.testing.assert_array_equal(g.pose_from_points(X, model, "rigid"), g.pose_rigid(X, model))
        assert g.POSE_METHODS == ("paper", "rigid")

    def test_pose_from_points_unknown_method(self, model):
        with pytest.raises(ValueError, match="unknown pose method 'icp'"):
            g.pose_from_points(model, model, method="icp")

    @pytest.mark.parametrize("shapes", [((3, 3), (4, 3)), ((2, 3), (2, 3))])
    def test_rigid_bad_shapes(self, shapes):
        with pytest.raises(ValueError, match=r"need matching \(N>=3, 3\) point sets"):
            g.pose_rigid(np.zeros(shapes[0]), np.ones(shapes[1]))


class TestRotations:
    @pytest.mark.parametrize("angle_deg", [0.0, 1e-3, 0.05, 5.0, 90.0, 179.0])
    def test_rotation_angle_known(self, angle_deg):
        rng = np.random.default_rng(13)
        axis = rng.normal(size=3)
        base = g.rotation_about_axis(rng.normal(size=3), 0.7)
        Rd = g.rotation_about_axis(axis, np.deg2rad(angle_deg))
        # arccos near 0 loses precision (~1e-8 rad), which is below the paper's resolution.
        atol = 2e-7 if angle_deg < 1 else 1e-10
        assert g.rotation_angle(np.eye(3), Rd) == pytest.approx(np.deg2rad(angle_deg), abs=atol)
        assert g.rotation_angle(base, base @ Rd) == pytest.approx(np.deg2rad(angle_deg), abs=atol)
        assert g.rotation_angle(base @ Rd, base) == pytest.approx(np.deg2rad(angle_deg), abs=atol)

    def test_rotation_angle_clipped_not_nan(self):
        R = np.eye(3) * (1 + 1e-12)  # trace slightly above 3
        assert g.rotation_angle(np.eye(3), R) == 0.0
        assert g.rotation_angle(np.eye(3), -np.eye(3) * (1 + 1e-12)) == pytest.approx(np.pi)

    def test_rotation_about_axis(self):
        R = g.rotation_about_axis([0, 0, 2.0], np.pi / 2)  # axis need not be unit
        np.testing.assert_allclose(R @ [1.0, 0, 0], [0, 1, 0], atol=1e-15)
        rng = np.random.default_rng(14)
        axis = rng.normal(size=3)
        R = g.rotation_about_axis(axis, 1.234)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(R @ axis, axis, atol=1e-14)


# --- conics -----------------------------------------------------------------------------------
def _circle_points(center, radius, n):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([center[0] + radius * np.cos(th), center[1] + radius * np.sin(th), np.ones(n)])


def _to_image(H, pts_h):
    x = pts_h @ H.T
    return x[:, :2] / x[:, 2:]


class TestConics:
    def test_circle_conic(self):
        C = g.circle_conic((3.0, -2.0), 5.0)
        assert C.shape == (3, 3)
        np.testing.assert_allclose(C, C.T)
        pts = _circle_points((3.0, -2.0), 5.0, 100)
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", pts, C, pts), 0.0, atol=1e-12)
        assert np.array([3.0, -2.0, 1.0]) @ C @ [3.0, -2.0, 1.0] < 0  # inside is negative
        np.testing.assert_allclose(g.conic_center(C), [3.0, -2.0])

    @pytest.mark.parametrize("seed", range(4))
    def test_project_conic_contains_projected_circle(self, rig, seed):
        T = _random_pose(np.random.default_rng(seed))
        H = g.plane_homography(rig.left.K, T)
        assert H.shape == (3, 3)
        for c in Marker().centers2d:
            for r in (4.0, 10.0):
                C = g.project_conic(g.circle_conic(c, r), H)
                np.testing.assert_allclose(C, C.T)
                assert np.abs(C).max() == pytest.approx(1.0)
                x = _to_image(H, _circle_points(c, r, 360))
                xh = np.column_stack([x, np.ones(len(x))])
                # x^T C x relative to the scale of its terms (|C| = 1, |x| ~ 1e3).
                assert np.abs(np.einsum("ni,ij,nj->n", xh, C, xh)).max() < 1e-9

    def test_plane_homography_matches_ideal_projection(self, rig):
        T = _random_pose(np.random.default_rng(15))
        H = g.plane_homography(rig.left.K, T)
        xy = np.random.default_rng(16).uniform(-20, 60, (20, 2))
        P = _apply(T, np.column_stack([xy, np.zeros(20)]))
        ideal = (P[:, :2] / P[:, 2:]) @ rig.left.K[:2, :2].T + rig.left.K[:2, 2]
        np.testing.assert_allclose(_to_image(H, np.column_stack([xy, np.ones(20)])), ideal, atol=1e-9)

    def test_conic_center_perspective_bias(self, rig):
        """The centre of a projected circle's ellipse is not the projected centre (tilted plane)."""
        T = _random_pose(np.random.default_rng(17))
        T[:3, :3] = g.rotation_about_axis([1.0, 0.3, 0], np.deg2rad(50)) @ np.diag([1.0, -1.0, -1.0])
        H = g.plane_homography(rig.left.K, T)
        C = g.project_conic(g.circle_conic((25.0, 0.0), 10.0), H)
        projected_centre = _to_image(H, np.array([[25.0, 0.0, 1.0]]))[0]
        bias = np.linalg.norm(g.conic_center(C) - projected_centre)
        assert 0.05 < bias < 2.0  # tenths of a pixel: the paper's d(c0,c2) bias

    def test_conic_center_unbiased_when_fronto_parallel(self, rig):
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = [10.0, -5.0, 500.0]
        H = g.plane_homography(rig.left.K, T)
        C = g.project_conic(g.circle_conic((25.0, 0.0), 10.0), H)
        np.testing.assert_allclose(g.conic_center(C), _to_image(H, np.array([[25.0, 0.0, 1.0]]))[0], atol=1e-9)

    @pytest.mark.parametrize("seed", range(6))
    def test_conic_center_equals_fitEllipse_centre(self, rig, seed):
        """cv2.fitEllipse on densely sampled points of a projected circle finds conic_center.

        fitEllipse works in float32 (relative precision ~1e-8 of the ellipse size), so the
        1e-6 px check uses the inner white disk (~30-60 px across) and fits the points
        relative to their rounded mean.
        """
        T = _random_pose(np.random.default_rng(100 + seed))
        H = g.plane_homography(rig.left.K, T)
        c = Marker().centers2d[seed % 3]
        r = Marker().inner_radius
        C = g.project_conic(g.circle_conic(c, r), H)
        x = _to_image(H, _circle_points(c, r, 720))
        off = np.round(x.mean(axis=0))
        (cx, cy), axes, angle = cv2.fitEllipse((x - off).astype(np.float32))
        np.testing.assert_allclose(np.array([cx, cy]) + off, g.conic_center(C), rtol=0, atol=1e-6)
        # And the whole ellipse agrees with the projected conic.
        Ce = g.ellipse_to_conic(np.array([cx, cy]) + off, axes, angle)
        Ce = Ce / np.abs(Ce).max() * np.sign(Ce[0, 0] * C[0, 0])
        np.testing.assert_allclose(Ce, C, atol=1e-6)

    @pytest.mark.parametrize(
        "center, axes, angle",
        [((300.0, 200.0), (80.0, 50.0), 30.0), ((-5.0, 7.5), (20.0, 20.0), 0.0), ((640.5, 511.25), (44.0, 130.0), 123.0)],
    )
    def test_ellipse_to_conic_round_trip(self, center, axes, angle):
        C = g.ellipse_to_conic(center, axes, angle)
        np.testing.assert_allclose(C, C.T)
        np.testing.assert_allclose(g.conic_center(C), center, atol=1e-9)
        # Points of the RotatedRect's parametric ellipse lie on the conic.
        th = np.linspace(0, 2 * np.pi, 400, endpoint=False)
        a, b, phi = axes[0] / 2, axes[1] / 2, np.deg2rad(angle)
        Rm = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
        pts = np.column_stack([a * np.cos(th), b * np.sin(th)]) @ Rm.T + center
        ph = np.column_stack([pts, np.ones(len(pts))])
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", ph, C, ph), 0.0, atol=1e-9)
        # fitEllipse recovers the same ellipse (as a conic: the RotatedRect is not unique).
        off = np.round(np.asarray(center))
        (cx, cy), ax2, ang2 = cv2.fitEllipse((pts - off).astype(np.float32))
        C2 = g.ellipse_to_conic(np.array([cx, cy]) + off, ax2, ang2)
        np.testing.assert_allclose(C2 / np.abs(C2).max(), C / np.abs(C).max(), atol=1e-6)

    def test_ellipse_to_conic_swapped_axes_same_conic(self):
        # OpenCV's (w, h, angle) and (h, w, angle + 90) describe the same ellipse.
        C1 = g.ellipse_to_conic((10.0, 20.0), (30.0, 12.0), 20.0)
        C2 = g.ellipse_to_conic((10.0, 20.0), (12.0, 30.0), 110.0)
        np.testing.assert_allclose(C1, C2, atol=1e-12)


# --- the compiled kernels against the numpy / OpenCV computations they replace ----------
class TestCompiled:
    def test_triangulate_is_opencv_dlt(self, rig):
        P = _working_volume(np.random.default_rng(40), 50)
        uv = rig.project(P) + np.random.default_rng(41).normal(0, 0.5, (2, 50, 2))
        ul, ur = rig.left.undistort_points(uv[0]), rig.right.undistort_points(uv[1])
        H = cv2.triangulatePoints(rig.P1, rig.P2, ul.T.copy(), ur.T.copy())
        np.testing.assert_allclose(g.triangulate(rig, uv[0], uv[1]), (H[:3] / H[3]).T, atol=1e-8)

    def test_perspective_bias_is_the_conic_centre_minus_the_projected_centre(self, rig, model):
        for seed in range(5):
            T = _random_pose(np.random.default_rng(50 + seed))
            H = g.plane_homography(rig.left.K, T)
            centres = np.array([g.conic_center(g.project_conic(g.circle_conic(c, 10.0), H)) for c in model[:, :2]])
            xn = (centres - rig.left.K[:2, 2]) / np.diag(rig.left.K)[:2]  # the default rig has no skew
            expected = rig.left.distort(xn) - rig.left.project(_apply(T, model))
            np.testing.assert_allclose(g.perspective_bias(rig.left, T, model[:, :2], 10.0), expected, atol=1e-7)

    @pytest.mark.parametrize("bias", [True, False])
    def test_solve_rigid_equals_the_stepwise_solve(self, rig, model, bias, monkeypatch):
        """The one compiled call of the bias-corrected rigid solve gives what the chain of
        triangulation, rigid fit and bias steps gives (the paper's pose takes that chain)."""
        from markerpose.results import Detection
        from markerpose.stages import solve

        marker, conf = Marker(), {"pose": "rigid", "bias_correction": bias}
        rng = np.random.default_rng(60)
        for _ in range(10):
            uv = rig.project(_apply(_random_pose(rng), model)) + rng.normal(0, 0.2, (2, 3, 2))
            fast = solve.solve(rig, marker, Detection(uv[0]), Detection(uv[1]), conf)
            with monkeypatch.context() as m:
                m.setattr(solve, "solve_rigid", lambda *a: None)
                slow = solve.solve(rig, marker, Detection(uv[0]), Detection(uv[1]), conf)
            np.testing.assert_allclose(fast.T, slow.T, atol=1e-9)
            np.testing.assert_allclose(fast.centers, slow.centers, atol=1e-9)
            np.testing.assert_allclose(fast.points3d, slow.points3d, atol=1e-9)
            assert fast.residual_px == pytest.approx(slow.residual_px, abs=1e-9)

    def test_view_poses_misfit_is_the_mean_relative_radial_distance(self, rig, model):
        T = _random_pose(np.random.default_rng(70))
        ellipses = g.ring_ellipses(rig.left, T, model, 10.0)
        centres = rig.left.project(_apply(T, model))
        poses = g.view_poses(rig.left, centres, ellipses, model, 10.0)
        assert poses[0][0] < 1e-3 and np.abs(poses[0][1] - T).max() < 1e-6
        for misfit, Tp in poses:
            edges = g.ring_edges(rig.left, Tp, model, 10.0)
            lam = [
                np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", h, g.ellipse_to_conic(*e), h) + 1, 0))
                for e, h in zip(ellipses, np.concatenate([edges, np.ones(edges.shape[:-1] + (1,))], -1))
            ]
            assert misfit == pytest.approx(np.mean(np.abs(np.array(lam) - 1)), abs=1e-9)

    def test_cq_to_rect_is_the_eigen_decomposition(self):
        rng = np.random.default_rng(80)
        for _ in range(200):
            rect = ((rng.uniform(0, 900), rng.uniform(0, 900)), tuple(rng.uniform(4, 90, 2)), rng.uniform(0, 180))
            c, Q = g.rect_to_cq(rect)
            (cx, cy), (w, h), ang = g.cq_to_rect(c, Q)
            lam, V = np.linalg.eigh(Q)
            assert (w, h) == pytest.approx((2 / np.sqrt(lam[0]), 2 / np.sqrt(lam[1])), rel=1e-12)
            expected = np.degrees(np.arctan2(V[1, 0], V[0, 0])) % 180
            assert abs((ang - expected + 90) % 180 - 90) < 1e-9 and (cx, cy) == rect[0]
