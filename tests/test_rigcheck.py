"""Rig check: a camera turned after calibration is caught within frames, a stable rig never."""

import dataclasses

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.rigcheck import RigCheck, default_conf, statistics
from markerpose.synth import Imaging, look_at_pose, render_stereo


@pytest.fixture(scope="module")
def rig():
    return mp.StereoRig.default()


def _turned(rig, deg, axis):
    """The rig with its right camera turned by ``deg`` about ``axis`` (its own frame)."""
    Rd = cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float))[0]
    return dataclasses.replace(rig, R=Rd @ rig.R, t=Rd @ rig.t)


def _frames(rig, n, seed=0):
    for k in range(n):
        T = look_at_pose(np.array([30 * np.sin(k / 5), 20 * np.cos(k / 7), 560 + 40 * np.sin(k / 9)]), 25, 30 + 5 * k, 10 + 3 * k)
        yield render_stereo(rig, T, mp.Marker(), Imaging(alpha=0.6), seed=seed + k)


def test_stable_rig_stays_quiet_and_a_turned_camera_fires(rig):
    tracker = mp.MarkerPose(rig)
    for f in _frames(rig, 8):
        est = tracker.track(*f.images)
        assert est.rig_warning is None and est.status() == "ok"
        ze, zs = statistics(rig, est, mp.Marker().points3d, default_conf)
        assert abs(ze) < 2 and abs(zs) < 2
    assert tracker.rig_check.fired is None
    # The right camera turned 0.05° about its vertical axis: along the epipolar lines, so
    # only the marker's triangulated size shows it.
    fired = None
    for k, f in enumerate(_frames(_turned(rig, 0.05, (0, 1, 0)), 12, seed=50)):
        est = tracker.track(*f.images)
        if est.rig_warning is not None:
            fired = k
            break
    assert fired is not None and fired < 10
    assert est.status() == "rig changed" and "recalibrate" in est.rig_warning
    tracker.rig_check.reset()
    assert tracker.rig_check.fired is None


def test_a_camera_turned_across_the_epipolar_lines_fires_at_once(rig):
    check = RigCheck(rig)
    tracker = mp.MarkerPose(rig)
    for f in _frames(_turned(rig, 0.05, (1, 0, 0)), 3, seed=80):
        est = tracker.track(*f.images)
        if check.update(est, mp.Marker().points3d) is not None:
            break
    assert check.fired is not None and check.fired_at <= 2 and "epipolar" in check.fired


def test_a_pair_whose_views_do_not_fit_the_rig_gives_no_pose_and_says_why():
    """One view shifted 40 px along the baseline (a bumped camera, the wrong rig file) passes
    every shape check and triangulates 30 mm off; its residual (5 px) says the rig does not fit:
    no pose from estimate(), and why says so; in a stream the rig check fires on that pair (status
    "rig changed"). The paper's presets give every pose."""
    from markerpose.synth import look_at_pose, render_stereo

    rig = mp.StereoRig.default()
    T = look_at_pose([0, 0, 560], 20, 30, 0)
    left, right = render_stereo(rig, T, seed=1).images
    shifted = np.roll(right, 40, axis=1)
    tracker = mp.MarkerPose(rig)
    assert tracker.estimate(left, right) is not None
    assert tracker.estimate(left, shifted) is None and "do not fit the rig" in tracker.why
    assert tracker.track(left, right).status() == "ok"
    assert tracker.track(left, shifted).status() == "rig changed" and tracker.rig_check.fired
    assert mp.MarkerPose(rig, preset="paper").estimate(left, shifted) is not None
    assert mp.MarkerPose(rig, verify={"max_residual_px": float("inf")}).estimate(left, shifted) is not None


def test_the_compiled_statistics_equal_the_numpy_ones(rig, monkeypatch):
    """The statistics in one compiled call equal numpy's (undistortion, epipolar distances,
    the points' covariances by the moved triangulations) on tracked poses of a stable and of a
    turned rig; where the compiled undistortion refuses a centre, numpy's path answers."""
    from markerpose import rigcheck

    model = mp.Marker().points3d
    for r in (rig, _turned(rig, 0.05, (1, 0, 0))):
        tracker = mp.MarkerPose(r)
        for f in _frames(r, 3, seed=20):
            est = tracker.track(*f.images)
            covs = np.stack([d.center_cov for d in est.detections])
            F = rigcheck.fundamental_matrix(r)
            want = rigcheck._statistics_numpy(r, est, covs, model, default_conf, F)
            got = statistics(r, est, model, default_conf)
            np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9)
    monkeypatch.setattr(rigcheck, "_statistics", lambda *a: False)
    assert statistics(r, est, model, default_conf) == want
