"""Tests for markerpose.camera: Camera, StereoRig, the default rig and FileStorage I/O."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from markerpose import Camera, StereoRig
from markerpose import camera as camera_module
from markerpose.camera import build_default_rig

try:  # only the property-based test needs it
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
except ImportError:  # pragma: no cover
    given = None

FIXTURES = Path(__file__).parent / "fixtures"
RIG_KEYS = ("K1", "dist1", "K2", "dist2", "R", "t")

# The values written in the hand-made fixtures (tests/fixtures/StereoParams.{xml,yaml}).
FIXTURE_K1 = np.array([[2487.3521, 0.0, 651.2087], [0.0, 2486.9144, 503.7712], [0.0, 0.0, 1.0]])
FIXTURE_K2 = np.array([[2493.0175, 0.0, 628.4403], [0.0, 2492.6618, 519.0329], [0.0, 0.0, 1.0]])
FIXTURE_D1 = np.array([-8.311745392e-02, 1.520774183e-01, 3.0124e-04, -1.2210e-04, -1.10439e-01])
FIXTURE_D2 = np.array([-7.90123774e-02, 1.29660122e-01, -2.2710e-04, 2.0981e-04, -4.2118e-02])
FIXTURE_R = np.array(
    [
        [9.5470348484021450e-01, -6.4725015954161690e-03, -2.9748842457656670e-01],
        [2.7848993776471544e-03, 9.9991396855177480e-01, -1.2817949543377165e-02],
        [2.9754579541543963e-01, 1.1408865769107705e-02, 9.5463937558245300e-01],
    ]
)
FIXTURE_T = np.array([-1.5873419210583461e02, 1.2034789120931000e00, 2.4876319870142000e01])


def _random_points(rng: np.random.Generator, n: int, spread: float = 0.1) -> np.ndarray:
    """(n, 3) points in the working volume (z in 350..800 mm) inside a cone of half-width ``spread * z``."""
    z = rng.uniform(350.0, 800.0, n)
    xy = rng.uniform(-spread, spread, (n, 2)) * z[:, None]
    return np.column_stack([xy, z])


def _inside(uv: np.ndarray, size, margin: float = 0.0) -> np.ndarray:
    w, h = size
    return np.all((uv >= margin) & (uv <= np.array([w - 1, h - 1]) - margin), axis=-1)


def _rig_matrices(rig: StereoRig) -> dict[str, np.ndarray]:
    return {
        "K1": rig.left.K,
        "dist1": rig.left.dist.reshape(1, 5),
        "K2": rig.right.K,
        "dist2": rig.right.dist.reshape(1, 5),
        "R": rig.R,
        "t": rig.t.reshape(3, 1),
    }


def _write_rig(path: Path, mats: dict[str, np.ndarray]) -> Path:
    """Write whatever matrices are given (possibly malformed) with cv2.FileStorage."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in mats.items():
        fs.write(k, np.asarray(v, dtype=np.float64))
    fs.release()
    return path


def _assert_rigs_equal(a: StereoRig, b: StereoRig, atol: float = 0.0) -> None:
    for x, y in [
        (a.left.K, b.left.K),
        (a.left.dist, b.left.dist),
        (a.right.K, b.right.K),
        (a.right.dist, b.right.dist),
        (a.R, b.R),
        (a.t, b.t),
    ]:
        np.testing.assert_allclose(x, y, rtol=0, atol=atol)
    assert a.left.image_size == b.left.image_size
    assert a.right.image_size == b.right.image_size


# --- Camera: construction ---------------------------------------------------------------
class TestCameraInit:
    def test_shapes_and_defaults(self):
        cam = Camera(np.diag([1000.0, 1000.0, 1.0]))
        assert cam.K.shape == (3, 3) and cam.K.dtype == np.float64
        assert cam.dist.shape == (5,)
        np.testing.assert_array_equal(cam.dist, 0)
        assert cam.image_size is None

    def test_four_coefficients_padded_with_k3_zero(self):
        cam = Camera(np.diag([1000.0, 1000.0, 1.0]), [0.1, -0.2, 1e-3, 2e-3])
        np.testing.assert_array_equal(cam.dist, [0.1, -0.2, 1e-3, 2e-3, 0.0])

    def test_eight_coefficients_with_zero_rational_terms_accepted(self):
        cam = Camera(np.diag([1000.0, 1000.0, 1.0]), [0.1, -0.2, 1e-3, 2e-3, 0.05, 0, 0, 0])
        np.testing.assert_array_equal(cam.dist, [0.1, -0.2, 1e-3, 2e-3, 0.05])

    def test_image_size_cast_to_int_tuple(self):
        cam = Camera(np.diag([1000.0, 1000.0, 1.0]), image_size=np.array([640, 480]))
        assert cam.image_size == (640, 480) and all(type(v) is int for v in cam.image_size)

    @pytest.mark.parametrize(
        "K",
        [
            np.diag([0.0, 1000.0, 1.0]),
            np.diag([1000.0, -5.0, 1.0]),
            np.diag([1000.0, 1000.0, 2.0]),
            np.array([[1000.0, 0, 320], [0, 1000.0, 240], [1e-3, 0, 1]]),
        ],
    )
    def test_bad_intrinsics(self, K):
        with pytest.raises(ValueError, match="K: not an intrinsic matrix"):
            Camera(K)

    def test_K_wrong_size(self):
        with pytest.raises(ValueError, match="K: expected 9 values"):
            Camera(np.eye(2))

    def test_K_non_finite(self):
        K = np.diag([1000.0, 1000.0, 1.0])
        K[0, 2] = np.nan
        with pytest.raises(ValueError, match="K: contains non-finite"):
            Camera(K)

    @pytest.mark.parametrize("dist", [[0.1, 0.2, 0.3], [0.1] * 6])
    def test_dist_wrong_length(self, dist):
        with pytest.raises(ValueError, match="dist"):
            Camera(np.diag([1000.0, 1000.0, 1.0]), dist)

    def test_dist_unsupported_higher_order_terms(self):
        with pytest.raises(ValueError, match="dist: only k1 k2 p1 p2 k3"):
            Camera(np.diag([1000.0, 1000.0, 1.0]), [0.1, 0, 0, 0, 0, 0.01, 0, 0])

    def test_dist_non_finite(self):
        with pytest.raises(ValueError, match="dist: contains non-finite"):
            Camera(np.diag([1000.0, 1000.0, 1.0]), [np.inf, 0, 0, 0, 0])

    @pytest.mark.parametrize("size", [(0, 480), (640, -1)])
    def test_bad_image_size(self, size):
        with pytest.raises(ValueError, match="image_size must be positive"):
            Camera(np.diag([1000.0, 1000.0, 1.0]), image_size=size)

    @pytest.mark.parametrize(
        "size, detail",
        [
            ((1e12, 1e12), "at most 100000 px"),
            ((100001, 480), "at most 100000 px"),
            ((np.nan, 480), "whole numbers of pixels"),
            ((640, np.inf), "whole numbers of pixels"),
            ((640.5, 480), "whole numbers of pixels"),
            ((0, 0), "must be positive"),
            ((-640, -480), "must be positive"),
            ((640, 480, 3), "expected two numbers"),
            ((640,), "expected two numbers"),
            ((), "expected two numbers"),
            ([[640, 480], [1]], "expected two numbers"),
        ],
    )
    def test_unworkable_image_size(self, size, detail):
        with pytest.raises(ValueError, match=rf"^image_size\b.*{re.escape(detail)}") as e:
            Camera(np.diag([1000.0, 1000.0, 1.0]), image_size=size)
        assert "\n" not in str(e.value)

    def test_image_size_whole_floats_and_limits_accepted(self):
        assert Camera(np.diag([1000.0, 1000.0, 1.0]), image_size=(640.0, np.float32(480))).image_size == (640, 480)
        assert Camera(np.diag([1000.0, 1000.0, 1.0]), image_size=[100000, 1]).image_size == (100000, 1)

    @pytest.mark.parametrize(
        "K, detail",
        [
            (np.zeros((3, 3)), "K: not an intrinsic matrix"),
            (np.array([[1.0, 1, 0], [1, 1, 0], [0, 0, 1]]), "K: not an intrinsic matrix"),  # singular, K[1,0] != 0
            (np.array([[1000.0, 0, 320], [5, 1000, 240], [0, 0, 1]]), "K: not an intrinsic matrix"),  # K[1,0] != 0
            (np.diag([1e-300, 1e-300, 1.0]), "K: numerically singular"),
            (np.diag([1000.0, 1e-13, 1.0]), "K: numerically singular"),
            (np.diag([1e300, 1e300, 1.0]), "K: entries must be at most"),
            (np.array([[1000.0, 0, 1e9], [0, 1000, 240], [0, 0, 1]]), "K: entries must be at most"),
            (np.diag([np.inf, 1000.0, 1.0]), "K: contains non-finite"),
        ],
        ids=["zeros", "singular", "lower-triangle", "tiny-f", "tiny-fy", "huge-f", "huge-cx", "inf-f"],
    )
    def test_unworkable_K(self, K, detail):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match=f"^{detail}"):
                Camera(K)

    def test_K_extremes_that_still_work_accepted(self):
        # A normalised camera, a principal point outside the image (a crop) and a long lens.
        for K in [np.eye(3), np.array([[2500.0, 0, -300], [0, 2500, 2000], [0, 0, 1]]), np.diag([1e7, 1e7, 1.0])]:
            np.testing.assert_array_equal(Camera(K).K, K)

    @pytest.mark.parametrize("dist, detail", [([1e300, 0, 0, 0, 0], "above 1e+06"), ([0, 0, np.nan, 0], "non-finite")])
    def test_unworkable_dist(self, dist, detail):
        with pytest.raises(ValueError, match=rf"^dist: .*{re.escape(detail)}"):
            Camera(np.diag([1000.0, 1000.0, 1.0]), dist)


# --- Camera: projection -----------------------------------------------------------------
def _random_camera(rng: np.random.Generator) -> Camera:
    f = rng.uniform(800, 3000)
    K = np.array([[f * rng.uniform(0.99, 1.01), 0, rng.uniform(600, 680)], [0, f, rng.uniform(480, 540)], [0, 0, 1]])
    k1, k2, k3 = rng.uniform(-0.3, 0.0), rng.uniform(-0.1, 0.3), rng.uniform(-0.1, 0.1)
    dist = np.array([k1, k2, rng.normal(0, 1e-3), rng.normal(0, 1e-3), k3])
    return Camera(K, dist, (1280, 1024))


class TestCameraProjection:
    def test_shapes(self, rig):
        cam = rig.left
        assert cam.project(np.array([0.0, 0.0, 500.0])).shape == (1, 2)
        assert cam.project(np.zeros((0, 3))).shape == (0, 2)
        assert cam.distort(np.zeros((7, 2))).shape == (7, 2)
        assert cam.undistort_points(np.zeros((7, 2))).shape == (7, 2)
        assert cam.undistort_points(np.zeros((0, 2))).shape == (0, 2)

    def test_principal_point(self, rig):
        # The optical axis projects to the principal point whatever the distortion.
        for cam in rig.cameras:
            np.testing.assert_allclose(cam.project([[0.0, 0.0, 123.0]])[0], cam.K[:2, 2], atol=1e-12)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_project_equals_cv2_projectPoints(self, seed):
        rng = np.random.default_rng(seed)
        cam = _random_camera(rng)
        P = _random_points(rng, 500, spread=0.25)
        ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        np.testing.assert_allclose(cam.project(P), ref.reshape(-1, 2), rtol=0, atol=1e-9)

    def test_default_rig_cameras_equal_cv2_projectPoints(self, rig):
        P = _random_points(np.random.default_rng(3), 500)
        for cam in rig.cameras:
            ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, cam.dist)
            np.testing.assert_allclose(cam.project(P), ref.reshape(-1, 2), rtol=0, atol=1e-9)

    def test_distort_equals_cv2_on_normalised_points(self, rig):
        rng = np.random.default_rng(4)
        xn = rng.uniform(-0.3, 0.3, (300, 2))
        for cam in rig.cameras:
            rays = np.column_stack([xn, np.ones(len(xn))])
            ref, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist)
            np.testing.assert_allclose(cam.distort(xn), ref.reshape(-1, 2), rtol=0, atol=1e-9)

    def test_distort_without_distortion_is_K(self):
        cam = Camera(np.array([[1500.0, 0, 640], [0, 1490.0, 512], [0, 0, 1]]))
        xn = np.random.default_rng(5).uniform(-0.3, 0.3, (50, 2))
        ref = xn * [1500.0, 1490.0] + [640, 512]
        np.testing.assert_allclose(cam.distort(xn), ref, atol=1e-12)
        np.testing.assert_allclose(cam.undistort_points(ref), ref, atol=1e-9)

    def test_undistort_inverts_project_over_whole_image(self, rig):
        """Every pixel of the 1280x1024 image: distort(undistort(u)) == u to 1e-6 px.

        Regression: undistort_points called cv2.undistortPointsIter, absent from OpenCV 5.
        """
        for cam in rig.cameras:
            w, h = cam.image_size
            u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            px = np.column_stack([u.ravel(), v.ravel()])
            xn = cam.undistort_points(px, ideal_pixels=False)
            err = np.abs(cam.distort(xn) - px).max()
            assert err <= 1e-6, err
            # ... and the ideal-pixel output is K applied to the normalised one.
            corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
            ideal = cam.undistort_points(corners)
            xn_c = cam.undistort_points(corners, ideal_pixels=False)
            np.testing.assert_allclose(ideal, xn_c @ cam.K[:2, :2].T + cam.K[:2, 2], atol=1e-9)

    def test_undistort_under_strong_distortion_and_beyond_its_fold(self, rig):
        """Newton's undistortion recovers the ideal points under a strong lens (where
        OpenCV's fixed-point iteration need not converge) and gives OpenCV's converged
        result on the rig's lens; beyond the model's fold (no inverse on the lens's branch)
        Newton gives up and OpenCV's iteration returns finite points, as before."""
        cam = Camera(np.array([[1200.0, 0.5, 640], [0, 1190.0, 512], [0, 0, 1]]), [-0.5, 0.0, 1e-3, -2e-3, 0.0])
        xn = np.random.default_rng(3).uniform(-0.45, 0.45, (400, 2))
        xn = xn[np.hypot(*xn.T) < 0.6]  # inside the fold at r ~ 0.82
        np.testing.assert_allclose(cam.undistort_points(cam.distort(xn), ideal_pixels=False), xn, atol=1e-10)
        beyond = cam.distort(np.array([[0.8, 0.0]])) + [[60.0, 0.0]]  # no point distorts there
        xn_b, ok = np.empty((1, 2)), np.ones(1, bool)
        camera_module._undistort(beyond, cam.K, cam.dist, xn_b, ok)
        assert not ok[0]
        assert np.isfinite(cam.undistort_points(beyond)).all()
        px = rig.left.distort(xn)
        ref = rig.left._undistort_normalized(px.reshape(-1, 1, 2), 200)
        np.testing.assert_allclose(rig.left.undistort_points(px, ideal_pixels=False), ref, atol=1e-12)

    def test_undistort_recovers_ideal_pixels_of_3d_points(self, rig):
        P = _random_points(np.random.default_rng(6), 300, spread=0.12)
        for cam in rig.cameras:
            ideal = (P[:, :2] / P[:, 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2]
            np.testing.assert_allclose(cam.undistort_points(cam.project(P)), ideal, rtol=0, atol=1e-6)

    def test_barrel_distortion_pulls_corners_inward(self, rig):
        # k1 < 0: the distorted corner lies nearer the principal point than the ideal one.
        for cam in rig.cameras:
            w, h = cam.image_size
            corner = np.array([[w - 1.0, h - 1.0]])
            ideal = cam.undistort_points(corner)
            assert np.linalg.norm(ideal - cam.K[:2, 2]) > np.linalg.norm(corner - cam.K[:2, 2]) + 1.0


class TestNormalizedGrid:
    def test_shape_and_consistency(self, rig):
        cam = rig.left
        w, h = cam.image_size
        grid = cam.normalized_grid()
        assert grid.shape == (h, w, 2) and grid.dtype == np.float64
        rng = np.random.default_rng(7)
        uv = np.column_stack([rng.integers(0, w, 200), rng.integers(0, h, 200)])
        uv = np.vstack([uv, [[0, 0], [w - 1, h - 1], [w - 1, 0], [0, h - 1]]])
        expected = cam.undistort_points(uv.astype(np.float64), ideal_pixels=False)
        np.testing.assert_allclose(grid[uv[:, 1], uv[:, 0]], expected, rtol=0, atol=1e-12)
        # grid[v, u] is indexed row = y, column = x: x grows along axis 1.
        assert np.all(np.diff(grid[h // 2, :, 0]) > 0) and np.all(np.diff(grid[:, w // 2, 1]) > 0)
        # Cached: the same object on the second call.
        assert cam.normalized_grid() is grid

    def test_cache_invalidated_when_intrinsics_change(self):
        cam = Camera(np.array([[100.0, 0, 15.5], [0, 100.0, 11.5], [0, 0, 1]]), [-0.1, 0, 0, 0, 0], (32, 24))
        g1 = cam.normalized_grid().copy()
        cam.K = cam.K * np.array([[2.0], [2.0], [1.0]])
        g2 = cam.normalized_grid()
        assert not np.allclose(g1, g2)
        np.testing.assert_allclose(cam.distort(g2.reshape(-1, 2)).reshape(24, 32, 2)[3, 5], [5, 3], atol=1e-9)

    def test_requires_image_size(self):
        with pytest.raises(ValueError, match="image_size"):
            Camera(np.diag([100.0, 100.0, 1.0])).normalized_grid()


# --- StereoRig ---------------------------------------------------------------------------
class TestStereoRig:
    def test_default_rig_description(self, rig):
        for cam in rig.cameras:
            assert cam.image_size == (1280, 1024)
            assert cam.K[0, 0] == pytest.approx(2500, rel=0.01)
            assert cam.K[1, 1] == pytest.approx(2500, rel=0.01)
            assert np.all(np.abs(cam.K[:2, 2] - [640, 512]) < 20)
            assert cam.dist[0] < 0  # mild barrel distortion
        assert 150 <= rig.baseline <= 200
        assert rig.baseline == pytest.approx(175.0, abs=1e-9)
        assert rig.R.shape == (3, 3) and rig.t.shape == (3,)

    def test_default_matches_build_default_rig(self, rig):
        # The shipped YAML is build_default_rig() written with 17 significant digits.
        _assert_rigs_equal(rig, build_default_rig(), atol=1e-12)

    def test_default_rig_extrinsics_are_a_toed_in_pair(self, rig):
        # The right camera sits to the +x side of the left one (in left coordinates).
        c_right = -rig.R.T @ rig.t
        assert c_right[0] > 150 and abs(c_right[1]) < 1e-9
        # Optical axes converge in front of the rig, inside the working volume.
        d_right = rig.R.T @ np.array([0.0, 0.0, 1.0])
        s, u = np.linalg.lstsq(np.column_stack([[0.0, 0.0, 1.0], -d_right]), c_right, rcond=None)[0]
        gap = np.linalg.norm(np.array([0.0, 0.0, s]) - (c_right + u * d_right))
        assert gap < 1e-6 and 350 < s < 800 and 350 < u < 800

    def test_projection_matrices(self, rig):
        assert rig.P1.shape == (3, 4) and rig.P2.shape == (3, 4)
        P = _random_points(np.random.default_rng(8), 100)
        Ph = np.column_stack([P, np.ones(len(P))])
        for Pm, cam, Pc in [(rig.P1, rig.left, P), (rig.P2, rig.right, rig.to_right(P))]:
            x = Ph @ Pm.T
            ideal = x[:, :2] / x[:, 2:]
            # P maps to ideal (undistorted) pixels of the camera-frame point.
            np.testing.assert_allclose(ideal, (Pc[:, :2] / Pc[:, 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2], atol=1e-9)
            np.testing.assert_allclose(ideal, cam.undistort_points(cam.project(Pc)), atol=1e-6)

    def test_to_right_and_T_right_left(self, rig):
        P = _random_points(np.random.default_rng(9), 50)
        Pr = rig.to_right(P)
        assert Pr.shape == (50, 3)
        np.testing.assert_allclose(Pr, (rig.T_right_left @ np.column_stack([P, np.ones(50)]).T)[:3].T, atol=1e-12)
        # The right optical centre maps to the right origin; distances are preserved.
        np.testing.assert_allclose(rig.to_right(-rig.R.T @ rig.t), np.zeros((1, 3)), atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(Pr[1:] - Pr[:-1], axis=1), np.linalg.norm(P[1:] - P[:-1], axis=1))

    def test_project_shape_and_equals_cv2(self, rig):
        P = _random_points(np.random.default_rng(10), 200)
        uv = rig.project(P)
        assert uv.shape == (2, 200, 2)
        assert rig.project(P[0]).shape == (2, 1, 2)
        rvec, _ = cv2.Rodrigues(rig.R)
        ref_l, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), rig.left.K, rig.left.dist)
        ref_r, _ = cv2.projectPoints(P, rvec, rig.t, rig.right.K, rig.right.dist)
        np.testing.assert_allclose(uv[0], ref_l.reshape(-1, 2), rtol=0, atol=1e-9)
        np.testing.assert_allclose(uv[1], ref_r.reshape(-1, 2), rtol=0, atol=1e-9)

    def test_both_views_see_the_working_volume_along_left_axis(self, rig):
        """A fronto-parallel marker centred on the left optical axis at 350..800 mm is in both images."""
        th = np.linspace(0, 2 * np.pi, 36, endpoint=False)
        ring = 10.0 * np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
        centers = np.array([[0.0, 0, 0], [25, 0, 0], [0, 40, 0]]) - [12.5, 20, 0]  # bbox centred on the axis
        pts = (centers[:, None, :] + ring[None]).reshape(-1, 3)
        for z in np.linspace(350, 800, 10):
            uv = rig.project(pts + [0, 0, z])
            assert np.all(_inside(uv, rig.left.image_size, margin=10)), z

    def test_both_views_see_points_around_axis_and_convergence(self, rig):
        rng = np.random.default_rng(11)
        z = rng.uniform(350, 800, 1000)
        near_axis = np.column_stack([rng.uniform(-30, 30, (1000, 2)), z])
        assert np.all(_inside(rig.project(near_axis), rig.left.image_size))
        converge = np.array([0.0, 0.0, 566.8])  # where the optical axes meet (see test above)
        cube = converge + rng.uniform(-60, 60, (1000, 3))
        assert np.all(_inside(rig.project(cube), rig.left.image_size))

    def test_point_behind_baseline_not_in_right_view(self, rig):
        # Sanity of the visibility test itself: far to the left is outside the right image.
        uv = rig.project([[-300.0, 0.0, 400.0]])
        assert not _inside(uv[1], rig.right.image_size).any()

    @pytest.mark.parametrize(
        "R, msg",
        [
            (np.diag([1.0, 1.0, -1.0]), "R: not a rotation"),  # reflection
            (np.eye(3) * 1.01, "R: not a rotation"),
            (np.eye(2), "R: expected 9 values"),
        ],
    )
    def test_bad_R(self, rig, R, msg):
        with pytest.raises(ValueError, match=msg):
            StereoRig(rig.left, rig.right, R, rig.t)

    def test_bad_t(self, rig):
        with pytest.raises(ValueError, match="t: expected 3 values"):
            StereoRig(rig.left, rig.right, rig.R, np.zeros(4))

    @pytest.mark.parametrize(
        "R, msg",
        [
            (np.full((3, 3), np.nan), "R: contains non-finite"),
            (np.full((3, 3), 1e300), "R: not a rotation"),  # no overflow warning on the way
            (np.zeros((3, 3)), "R: not a rotation"),
            (np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]), "R: not a rotation"),  # a permutation, det -1
            (-np.eye(3), "R: not a rotation"),  # point reflection, det -1
            (np.array([[1.0, 1e-3, 0], [0, 1, 0], [0, 0, 1]]), "R: not a rotation"),  # not orthonormal
        ],
    )
    def test_unworkable_R(self, rig, R, msg):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match=msg):
                StereoRig(rig.left, rig.right, R, rig.t)

    @pytest.mark.parametrize(
        "t, detail",
        [
            (np.zeros(3), "baseline |t| = 0 mm is below 0.001 mm"),
            ([1e-9, 0, 0], "baseline |t| = 1e-09 mm is below 0.001 mm"),
            ([-5e-4, 5e-4, 0], "is below 0.001 mm"),
            ([1e300, 1e300, 1e300], "is above 1e+09 mm"),
            ([1.7e308, 1.7e308, 0], "is above 1e+09 mm"),  # |t| itself overflows
            ([np.nan, 0, 0], "contains non-finite"),
            ([0, -np.inf, 0], "contains non-finite"),
        ],
    )
    def test_unworkable_t(self, rig, t, detail):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match=f"^t: .*{re.escape(detail)}"):
                StereoRig(rig.left, rig.right, rig.R, t)

    def test_short_baseline_at_the_floor_accepted(self, rig):
        assert StereoRig(rig.left, rig.right, rig.R, [1e-3, 0, 0]).baseline == pytest.approx(1e-3)

    def test_default_t_is_refused(self, rig):
        # The dataclass default t = 0 would put both cameras at the same place.
        with pytest.raises(ValueError, match="t: baseline"):
            StereoRig(rig.left, rig.right)


# --- FileStorage I/O -----------------------------------------------------------------------
class TestRigFiles:
    @pytest.mark.parametrize("suffix", [".yaml", ".yml", ".xml"])
    def test_round_trip(self, rig, tmp_path, suffix):
        path = rig.save(tmp_path / f"rig{suffix}")
        assert path == tmp_path / f"rig{suffix}" and path.is_file()
        _assert_rigs_equal(StereoRig.load(path), rig)  # bit-exact: 17 significant digits

    def test_round_trip_without_image_size(self, tmp_path):
        rig = StereoRig.load(FIXTURES / "StereoParams.xml")
        assert rig.left.image_size is None
        _assert_rigs_equal(StereoRig.load(rig.save(tmp_path / "rig.xml")), rig)

    def test_xml_format_is_the_original_layout(self, rig, tmp_path):
        text = rig.save(tmp_path / "rig.xml").read_text()
        assert text.startswith('<?xml version="1.0"?>\n<opencv_storage>')
        for key in RIG_KEYS:
            assert f'<{key} type_id="opencv-matrix">' in text

    def test_load_accepts_str_path(self, rig, tmp_path):
        path = rig.save(tmp_path / "rig.yaml")
        _assert_rigs_equal(StereoRig.load(str(path)), rig)

    @pytest.mark.parametrize("name", ["StereoParams.xml", "StereoParams.yaml"])
    def test_hand_written_fixture_loads_unchanged(self, name):
        rig = StereoRig.load(FIXTURES / name)
        np.testing.assert_array_equal(rig.left.K, FIXTURE_K1)
        np.testing.assert_array_equal(rig.right.K, FIXTURE_K2)
        np.testing.assert_array_equal(rig.left.dist, FIXTURE_D1)
        np.testing.assert_array_equal(rig.right.dist, FIXTURE_D2)
        np.testing.assert_array_equal(rig.R, FIXTURE_R)
        np.testing.assert_array_equal(rig.t, FIXTURE_T)
        assert rig.baseline == pytest.approx(160.676, abs=1e-3)

    def test_fixture_xml_has_extra_keys_E_F(self):
        # The original project's file also stores E and F: they must be ignored, not rejected.
        text = (FIXTURES / "StereoParams.xml").read_text()
        assert text.startswith('<?xml version="1.0"?>\n<opencv_storage>')
        assert '<E type_id="opencv-matrix">' in text and '<F type_id="opencv-matrix">' in text

    def test_fixture_yaml_image_size_sequence(self):
        rig = StereoRig.load(FIXTURES / "StereoParams.yaml")
        assert rig.left.image_size == (1280, 1024) and rig.right.image_size == (1280, 1024)

    def test_fixture_xml_and_yaml_agree(self):
        a = StereoRig.load(FIXTURES / "StereoParams.xml")
        b = StereoRig.load(FIXTURES / "StereoParams.yaml")
        b.left.image_size = b.right.image_size = None
        _assert_rigs_equal(a, b)

    @pytest.mark.parametrize("suffix", [".yaml", ".xml"])
    @pytest.mark.parametrize("key", RIG_KEYS)
    def test_missing_key(self, rig, tmp_path, key, suffix):
        mats = _rig_matrices(rig)
        del mats[key]
        path = _write_rig(tmp_path / f"rig{suffix}", mats)
        with pytest.raises(ValueError, match=f"missing key '{key}'"):
            StereoRig.load(path)

    @pytest.mark.parametrize(
        "key, value, detail",
        [
            ("K1", np.eye(2), "expected 9 values"),
            ("K2", np.ones((3, 4)), "expected 9 values"),
            ("dist1", np.zeros((1, 3)), "expected 4 or 5"),
            ("dist2", np.ones((1, 8)), "higher-order terms"),
            ("R", np.eye(4), "expected 9 values"),
            ("t", np.zeros((4, 1)), "expected 3 values"),
            ("R", np.diag([1.0, 1.0, -1.0]), "not a rotation"),
            ("R", np.array([[1.0, 0.2, 0], [0, 1, 0], [0, 0, 1]]), "not a rotation"),
            ("K1", np.diag([0.0, 2500.0, 1.0]), "not an intrinsic matrix"),
            ("K2", np.array([[2500.0, 0, 640], [0, 0.0, 512], [0, 0, 1]]), "not an intrinsic matrix"),
        ],
    )
    def test_malformed_key(self, rig, tmp_path, key, value, detail):
        mats = _rig_matrices(rig)
        mats[key] = value
        path = _write_rig(tmp_path / "rig.yaml", mats)
        with pytest.raises(ValueError, match=rf"key '{key}' is malformed.*{re.escape(detail)}"):
            StereoRig.load(path)

    def test_key_that_is_not_a_matrix(self, tmp_path):
        text = (FIXTURES / "StereoParams.yaml").read_text()
        text = text.replace("t: !!opencv-matrix", "t_unused: !!opencv-matrix") + "t: 5\n"
        (tmp_path / "scalar.yaml").write_text(text)
        with pytest.raises(ValueError, match="key 't' is not a matrix"):
            StereoRig.load(tmp_path / "scalar.yaml")

    def test_key_that_is_a_plain_map(self, tmp_path):
        """Regression: a map that is not an opencv-matrix leaked a cv2.error."""
        text = (FIXTURES / "StereoParams.yaml").read_text()
        text = text.replace("R: !!opencv-matrix", "R_unused: !!opencv-matrix") + "R: { a: 1, b: 2 }\n"
        (tmp_path / "map.yaml").write_text(text)
        with pytest.raises(ValueError, match="key 'R' is not a matrix"):
            StereoRig.load(tmp_path / "map.yaml")

    def test_plain_sequences_accepted(self, rig, tmp_path):
        # Hand-written files may give t and dist as plain sequences.
        text = (FIXTURES / "StereoParams.yaml").read_text()
        text = text.replace("t: !!opencv-matrix", "t_unused: !!opencv-matrix") + "t: [ 1.5, -2.0, 3.25 ]\n"
        (tmp_path / "seq.yaml").write_text(text)
        np.testing.assert_array_equal(StereoRig.load(tmp_path / "seq.yaml").t, [1.5, -2.0, 3.25])

    def test_bad_image_size(self, tmp_path):
        text = (FIXTURES / "StereoParams.yaml").read_text().replace("[ 1280, 1024 ]", "[ 1280, 1024, 3 ]")
        (tmp_path / "size.yaml").write_text(text)
        with pytest.raises(ValueError, match="image_size"):
            StereoRig.load(tmp_path / "size.yaml")

    @pytest.mark.parametrize(
        "key, value, detail",
        [
            # zero or tiny baseline (was: RuntimeWarning: invalid value encountered in divide, later)
            ("t", np.zeros((3, 1)), "t: baseline |t| = 0 mm is below 0.001 mm"),
            ("t", np.array([[1e-9], [0], [0]]), "t: baseline |t| = 1e-09 mm is below 0.001 mm"),
            ("t", np.full((3, 1), 1e300), "t: baseline |t| = 1.73e+300 mm is above 1e+09 mm"),
            ("t", np.array([[np.inf], [0], [0]]), "t: contains non-finite"),
            # singular / non-sensible K (was: LinAlgError: Singular matrix, later, not naming K1)
            ("K1", np.zeros((3, 3)), "K1: not an intrinsic matrix"),
            ("K2", np.array([[1.0, 1, 0], [1, 1, 0], [0, 0, 1]]), "K2: not an intrinsic matrix"),
            ("K1", np.array([[2500.0, 0, 640], [0, 2500, 512], [0, 0, 0]]), "K1: not an intrinsic matrix"),
            ("K2", np.diag([-2500.0, 2500.0, 1.0]), "K2: not an intrinsic matrix"),
            ("K1", np.diag([1e-300, 1e-300, 1.0]), "K1: numerically singular"),
            ("K2", np.diag([1e300, 1e300, 1.0]), "K2: entries must be at most 1e+08 px"),
            ("K1", np.diag([np.nan, 2500.0, 1.0]), "K1: contains non-finite"),
            # absurd image_size (was: accepted, or a bare "cannot convert float NaN to integer" /
            # OverflowError, or reported as key 'K1')
            ("image_size", np.array([[1e12, 1e12]]), "image_size: width and height must be at most 100000 px"),
            ("image_size", np.array([[np.nan, 1024]]), "image_size: width and height must be whole numbers"),
            ("image_size", np.array([[1280, np.inf]]), "image_size: width and height must be whole numbers"),
            ("image_size", np.array([[1280.5, 1024]]), "image_size: width and height must be whole numbers"),
            ("image_size", np.array([[-1280, 1024]]), "image_size must be positive"),
            ("image_size", np.array([[0, 0]]), "image_size must be positive"),
            # R, dist
            ("R", np.full((3, 3), np.nan), "R: contains non-finite"),
            ("R", np.full((3, 3), 1e300), "R: not a rotation"),
            ("R", -np.eye(3), "R: not a rotation"),
            ("dist1", np.array([[np.nan, 0, 0, 0, 0]]), "dist1: contains non-finite"),
            ("dist2", np.array([[0, 0, 0, 0, -np.inf]]), "dist2: contains non-finite"),
            ("dist2", np.array([[1e300, 0, 0, 0, 0]]), "dist2: coefficient magnitude above 1e+06"),
        ],
    )
    @pytest.mark.parametrize("suffix", [".yaml", ".xml"])
    def test_unworkable_value(self, rig, tmp_path, key, value, detail, suffix):
        """Rigs that used to load and fail later fail at load time: one line, the file, the key."""
        mats = _rig_matrices(rig)
        mats["image_size"] = np.array([[1280, 1024]])
        mats[key] = value
        path = _write_rig(tmp_path / f"rig{suffix}", mats)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # and no RuntimeWarning on the way
            with pytest.raises(ValueError) as e:
                StereoRig.load(path)
        msg = str(e.value)
        assert msg.startswith(f"{path}: key '{key}' is malformed: {detail}"), msg
        assert "\n" not in msg

    @pytest.mark.parametrize(
        "text, detail",
        [
            ("[ 1280, .nan ]", "whole numbers"),
            ("[ 1e12, 1e12 ]", "at most 100000 px"),
            ("[ 1280.5, 1024 ]", "whole numbers"),
            ("[ -1280, 1024 ]", "must be positive"),
        ],
    )
    def test_unworkable_image_size_sequence(self, tmp_path, text, detail):
        text = (FIXTURES / "StereoParams.yaml").read_text().replace("[ 1280, 1024 ]", text)
        (tmp_path / "size.yaml").write_text(text)
        with pytest.raises(ValueError, match=rf"size\.yaml: key 'image_size' is malformed: image_size.*{detail}"):
            StereoRig.load(tmp_path / "size.yaml")

    def test_image_size_that_is_a_plain_map(self, tmp_path):
        """Regression: a map that is not an opencv-matrix leaked a cv2.error."""
        text = (FIXTURES / "StereoParams.yaml").read_text().replace("[ 1280, 1024 ]", "{ w: 1280, h: 1024 }")
        (tmp_path / "map.yaml").write_text(text)
        with pytest.raises(ValueError, match="key 'image_size' must hold two numbers"):
            StereoRig.load(tmp_path / "map.yaml")

    def test_perturbed_rig_loads_or_raises_value_error(self, rig, tmp_path_factory):
        """Property: garbage numbers in a valid rig file never escape as another exception."""
        if given is None:
            pytest.skip("hypothesis is not installed")
        _check_perturbed_rigs(rig, tmp_path_factory.mktemp("fuzz"))

    def test_missing_file(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="rig file not found"):
            StereoRig.load(tmp_path / "nope.yaml")

    def test_directory_is_not_a_file(self, tmp_path):
        with pytest.raises(FileNotFoundError):
            StereoRig.load(tmp_path)

    @pytest.mark.parametrize(
        "name, content",
        [
            ("garbage.yaml", b"\x00\x01 hello {{{ not yaml"),
            ("garbage.xml", b"<opencv_storage><K1>"),
            ("empty.yaml", b""),
            ("notes.txt", b"just some text\n"),
            ("noise.bin", bytes(range(256)) * 4),
        ],
        ids=["binary-yaml", "truncated-xml", "empty", "text", "noise"],
    )
    def test_garbage_file(self, tmp_path, name, content):
        """Regression: unparsable files raised SystemError from the cv2.FileStorage constructor."""
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match="not a readable OpenCV FileStorage"):
            StereoRig.load(tmp_path / name)

    def test_valid_storage_without_rig_keys(self, tmp_path):
        (tmp_path / "other.yaml").write_text("%YAML:1.0\n---\nfoo: 1\n")
        with pytest.raises(ValueError, match="missing key 'K1'"):
            StereoRig.load(tmp_path / "other.yaml")

    def test_save_rejects_unknown_suffix(self, rig, tmp_path):
        with pytest.raises(ValueError, match=r"\.yaml, \.yml or \.xml"):
            rig.save(tmp_path / "rig.json")
        assert not (tmp_path / "rig.json").exists()


# --- property-based: garbage in a valid rig file ---------------------------------------------
GARBAGE = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e300, 1e-300, 5e-324, 1.7976931348623157e308, 1e12, -1.0, 1e-9]
FUZZ_KEYS = (*RIG_KEYS, "image_size")


def _check_perturbed_rigs(rig: StereoRig, tmp: Path) -> None:
    base = _rig_matrices(rig)
    base["image_size"] = np.array([[1280.0, 1024.0]])
    value = st.one_of(st.sampled_from(GARBAGE), st.floats(allow_nan=True, allow_infinity=True))
    edit = st.tuples(st.sampled_from(FUZZ_KEYS), st.integers(0, 8), value)

    @settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(edits=st.lists(edit, min_size=1, max_size=3), suffix=st.sampled_from([".yaml", ".xml"]))
    def check(edits, suffix):
        mats = {k: np.array(v, dtype=np.float64) for k, v in base.items()}
        for key, i, v in edits:
            mats[key].flat[i % mats[key].size] = v
        path = _write_rig(tmp / f"rig{suffix}", mats)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                loaded = StereoRig.load(path)
            except ValueError as e:  # any other exception type (or a warning) fails the test
                assert str(e).startswith(f"{path}: ") and "\n" not in str(e), str(e)
                return
            for a in (loaded.left.K, loaded.right.K, loaded.left.dist, loaded.right.dist, loaded.R, loaded.t):
                assert np.all(np.isfinite(a))
            assert 1e-3 <= loaded.baseline <= 1e9
            assert np.all(np.isfinite(loaded.P1)) and np.all(np.isfinite(loaded.P2))
            w, h = loaded.left.image_size
            assert 0 < w <= 100000 and 0 < h <= 100000

    check()


@pytest.mark.parametrize(
    "text",
    [
        "%YAML:1.0\nK1: " + "[" * 40000 + "]" * 40000 + "\n",
        '<?xml version="1.0"?>\n<opencv_storage>' + "<a>" * 40000 + "</a>" * 40000 + "</opencv_storage>\n",
        "%YAML:1.0\nK1:\n" + "".join(" " * (2 * k) + f"k{k}:\n" for k in range(1, 200)),
    ],
    ids=["yaml-flow", "xml", "yaml-block"],
)
def test_deeply_nested_rig_files_are_refused_before_opencv_reads_them(tmp_path, text):
    """OpenCV's reader recurses per level and crashes the process on deep nesting."""
    path = tmp_path / ("rig.xml" if text.startswith("<?xml") else "rig.yaml")
    path.write_text(text)
    with pytest.raises(ValueError, match="nested .* levels deep"):
        StereoRig.load(path)


def test_oversized_rig_files_are_refused(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text("%YAML:1.0\n" + "# padding\n" * 200_000)
    with pytest.raises(ValueError, match="bytes; a rig file is a few kB"):
        StereoRig.load(path)


def test_a_rig_for_tiny_images_is_refused_by_the_tracker():
    import dataclasses

    import markerpose as mp

    rig = StereoRig.default()
    tiny = dataclasses.replace(rig, left=Camera(rig.left.K, rig.left.dist, (8, 8)), right=Camera(rig.right.K, rig.right.dist, (8, 8)))
    with pytest.raises(ValueError, match="8x8 px images: too small"):
        mp.MarkerPose(tiny)


def test_pytorch_weights_without_pytorch_are_a_one_line_error(tmp_path, monkeypatch):
    import importlib.util

    import markerpose as mp

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a))
    (tmp_path / "w.pt").write_bytes(b"")
    with pytest.raises(ValueError, match="PyTorch checkpoints need PyTorch"):
        mp.MarkerPose(StereoRig.default(), propose={"weights": str(tmp_path / "w.pt")})
