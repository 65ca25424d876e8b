"""Estimate.cov: each step of the propagation against Monte Carlo, and on rendered pairs."""

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.edges import center_covariances
from markerpose.geometry import pose_rigid, triangulate
from markerpose.synth import Imaging, look_at_pose, render_stereo
from markerpose.uncertainty import point_covariance, pose_covariance, relative_covariance


@pytest.fixture(scope="module")
def rig():
    return mp.StereoRig.default()


def _pose_error(T_true, T_est):
    w = cv2.Rodrigues(T_true[:3, :3] @ T_est[:3, :3].T)[0].ravel()
    return np.r_[T_true[:3, 3] - T_est[:3, 3], w]


def test_ellipse_centre_covariance_matches_monte_carlo():
    rng = np.random.default_rng(0)
    c, a, b, th = np.array([100.0, 80.0]), 30.0, 18.0, 0.4
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    Q = R @ np.diag([1 / a**2, 1 / b**2]) @ R.T
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    ideal = c + (R @ np.stack([a * np.cos(t), b * np.sin(t)])).T
    normals = (Q @ (ideal - c).T).T
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    sigma = 0.2 * (1 + (np.cos(t) > 0))  # half the edges twice as noisy: the weights say so
    centres, predicted = [], []
    for _ in range(400):
        P = ideal + normals * (sigma * rng.standard_normal(len(t)))[:, None]
        W = 1 / sigma**2
        cf, Qf, _ = mp.edges.fit_ellipses(P[None], np.ones((1, len(t)), bool), W[None])
        centres.append(cf[0])
        predicted.append(center_covariances([(P, W, cf[0], Qf[0])])[0])
    mc = np.cov(np.array(centres).T)
    pred = np.mean(predicted, axis=0)
    assert np.trace(pred) == pytest.approx(np.trace(mc), rel=0.2)
    assert np.all(np.isfinite(pred)) and np.linalg.eigvalsh(pred).min() > 0


def test_pose_covariance_matches_monte_carlo(rig):
    rng = np.random.default_rng(1)
    marker = mp.Marker()
    T = look_at_pose(np.array([20.0, -10.0, 600.0]), 35, 20, 50)
    X = marker.points3d @ T[:3, :3].T + T[:3, 3]
    centers = np.stack(rig.project(X))  # (2, 3, 2)
    covs = np.empty((2, 3, 2, 2))
    for v in range(2):
        for k in range(3):
            A = rng.normal(size=(2, 2)) * 0.02
            covs[v, k] = A @ A.T + 0.0004 * np.eye(2)
    errs = []
    for _ in range(600):
        noisy = centers + np.einsum("vkij,vkj->vki", np.linalg.cholesky(covs), rng.standard_normal((2, 3, 2)))
        Xn = triangulate(rig, noisy[0], noisy[1])
        errs.append(_pose_error(T, pose_rigid(Xn, marker.points3d)))
    mc = np.cov(np.array(errs).T)
    pred = pose_covariance(rig, marker.points3d, T, X, centers, covs, "rigid", model_px=0.0)
    assert np.trace(pred[:3, :3]) == pytest.approx(np.trace(mc[:3, :3]), rel=0.15)
    assert np.trace(pred[3:, 3:]) == pytest.approx(np.trace(mc[3:, 3:]), rel=0.15)
    # Calibrated in the Mahalanobis sense too: the mean squared distance of a 6-D error is 6.
    d2 = [e @ np.linalg.solve(pred, e) for e in errs]
    assert np.mean(d2) == pytest.approx(6.0, rel=0.15)
    # The paper's construction, differentiated numerically, agrees in size.
    paper = pose_covariance(rig, marker.points3d, T, X, centers, covs, "paper", model_px=0.0)
    assert paper.shape == (6, 6) and 0.3 < np.trace(paper[:3, :3]) / np.trace(pred[:3, :3]) < 3


def test_relative_and_point_covariances_match_monte_carlo():
    rng = np.random.default_rng(2)
    T_ref = look_at_pose(np.array([-60.0, 0.0, 550.0]), 30, 10, 70)
    T_tool = look_at_pose(np.array([70.0, 20.0, 620.0]), 20, 100, 10)

    def cov6(s):
        A = rng.normal(size=(6, 6)) * s
        return A @ A.T + np.diag([1e-4] * 3 + [1e-8] * 3)

    c_ref, c_tool = cov6(0.01), cov6(0.005)
    c_ref[3:, 3:] *= 1e-4
    c_tool[3:, 3:] *= 1e-4
    c_ref[:3, 3:] = c_ref[3:, :3] = 0
    c_tool[:3, 3:] = c_tool[3:, :3] = 0

    def perturb(T, C):
        x = np.linalg.cholesky(C) @ rng.standard_normal(6)  # the error true - estimated: estimated = true - error
        Tp = np.eye(4)
        Tp[:3, :3] = cv2.Rodrigues(-x[3:])[0] @ T[:3, :3]
        Tp[:3, 3] = T[:3, 3] - x[:3]
        return Tp

    rel_true = np.linalg.inv(T_ref) @ T_tool
    errs, tips = [], []
    tip = np.array([5.0, -120.0, 3.0])
    for _ in range(2000):
        Tr, Tt = perturb(T_ref, c_ref), perturb(T_tool, c_tool)
        errs.append(_pose_error(rel_true, np.linalg.inv(Tr) @ Tt))
        tips.append(Tt[:3, :3] @ tip + Tt[:3, 3])
    mc = np.cov(np.array(errs).T)
    pred = relative_covariance(T_ref, c_ref, T_tool, c_tool)
    assert np.trace(pred[:3, :3]) == pytest.approx(np.trace(mc[:3, :3]), rel=0.15)
    assert np.trace(pred[3:, 3:]) == pytest.approx(np.trace(mc[3:, 3:]), rel=0.15)
    assert np.trace(point_covariance(c_tool, T_tool, tip)) == pytest.approx(np.trace(np.cov(np.array(tips).T)), rel=0.15)


def test_estimate_cov_on_rendered_pairs(rig):
    marker = mp.Marker()
    T = look_at_pose(np.array([10.0, 5.0, 520.0]), 30, 40, 20)
    f = render_stereo(rig, T, marker, Imaging(alpha=0.6), seed=5)
    est = mp.MarkerPose(rig).estimate(*f.images)
    assert est.cov.shape == (6, 6)
    np.testing.assert_allclose(est.cov, est.cov.T)
    assert np.linalg.eigvalsh(est.cov).min() > 0
    assert 0 < est.sd_mm < 0.05 and 0 < est.sd_deg < 0.05
    assert est.point_sd_mm([0.0, -100.0, 0.0]) > est.sd_mm  # a tip far from the rings is less certain
    assert all(d.center_cov.shape == (3, 2, 2) for d in est.detections)
    # A darker pair of the same pose: larger uncertainty, from its own fits.
    dark = mp.MarkerPose(rig).estimate(*render_stereo(rig, T, marker, Imaging(alpha=0.0625), seed=5).images)
    assert dark.sd_mm > 1.5 * est.sd_mm
    # The paper's contour centres have no fit to take a covariance from.
    assert mp.MarkerPose(rig, preset="paper-classical").estimate(*f.images).cov is None


def test_shared_edge_shift_moves_the_centre_by_the_radius():
    """A shift g . (x - c) shared by every edge of a circle of radius R moves the fitted
    centre by R g: its covariance adds R^2 cov(g)."""
    R = 25.0
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    rng = np.random.default_rng(3)
    P = np.column_stack([50 + R * np.cos(t), 40 + R * np.sin(t)]) + rng.normal(0, 0.05, (48, 2))
    W = np.ones(48)
    c, Q = np.array([50.0, 40.0]), np.eye(2) / R**2
    S = np.array([[4e-8, 1e-8], [1e-8, 2e-8]])
    alone, shared = center_covariances([(P, W, c, Q), (P, W, c, Q, S)])
    np.testing.assert_allclose(shared - alone, R**2 * S, rtol=0.05)


def test_blurred_ring_fit_gives_centre_covariances(rig):
    T = look_at_pose(np.array([0.0, 0.0, 560.0]), 20, 30, 10)
    f = render_stereo(rig, T, mp.Marker(), Imaging(alpha=0.6, motion_blur=25.0, motion_angle=30.0), seed=7)
    est = mp.MarkerPose(rig).estimate(*f.images)
    assert est is not None and max(d.blur_px for d in est.detections) > 5  # the blurred-ring fit ran
    assert est.cov is not None and np.all(np.isfinite(est.cov)) and 0 < est.sd_mm < 0.2


def test_status_rules(rig):
    f = render_stereo(rig, look_at_pose(np.array([0.0, 0.0, 560.0]), 20, 30, 10), mp.Marker(), Imaging(alpha=0.6), seed=8)
    est = mp.MarkerPose(rig).estimate(*f.images)
    assert est.status() == "ok"
    assert est.status(max_sd_mm=0.5 * est.sd_mm) == "low accuracy"
    far_tip = [0.0, -5000.0, 0.0]  # a tip 5 m away: its error is the rotation's lever
    assert est.status(point=far_tip) == "low accuracy"
    assert mp.MarkerPose(rig, preset="paper-classical").estimate(*f.images).status() == "unrated"


def test_calibrated_volume_in_rig_files_and_status(rig, tmp_path):
    import dataclasses

    f = render_stereo(rig, look_at_pose(np.array([0.0, 0.0, 560.0]), 20, 30, 10), mp.Marker(), Imaging(alpha=0.6), seed=9)
    near = dataclasses.replace(rig, volume=np.array([[-150.0, -150.0, 300.0], [150.0, 150.0, 450.0]]))
    saved = mp.StereoRig.load(near.save(tmp_path / "rig.yaml"))
    np.testing.assert_allclose(saved.volume, near.volume)
    assert mp.MarkerPose(saved).estimate(*f.images).status() == "outside the calibrated volume"  # 560 mm > 450 + 15
    wide = dataclasses.replace(rig, volume=np.array([[-150.0, -150.0, 300.0], [150.0, 150.0, 900.0]]))
    assert mp.MarkerPose(wide).estimate(*f.images).status() == "ok"
    with pytest.raises(ValueError, match="lowest corner"):
        dataclasses.replace(rig, volume=np.array([[0.0, 0.0, 900.0], [1.0, 1.0, 300.0]]))
