"""MarkerPose.track: the previous frames as the prior (markerpose.stages.track)."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.nets import default_weights
from markerpose.stages.track import inside, predict
from markerpose.synth import Imaging, clutter_background, look_at_pose, render_stereo

needs_nets = pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped weights")


@pytest.fixture(scope="module")
def rig():
    return mp.StereoRig.default()


@pytest.fixture(scope="module")
def sequence(rig):
    """Eight frames of a marker moving 1.5 mm and 1° a frame, the last two without it."""
    frames = [render_stereo(rig, look_at_pose([-5 + 1.5 * k, 2, 560 - k], 30 + k, 45, 10 + k), imaging=Imaging(alpha=0.8), seed=k)
              for k in range(6)]
    rng = np.random.default_rng(5)
    empty = [(clutter_background((1280, 1024), rng) * 200).astype(np.uint8) for _ in range(2)]
    return frames, empty


def test_predict_is_constant_velocity_then_constant_acceleration():
    T0 = np.eye(4)
    T1 = look_at_pose([1.0, 0.0, 500.0], 5, 0, 0)
    assert np.allclose(predict([T1]), T1)
    T2 = predict([T0, T1])
    np.testing.assert_allclose(T2 @ np.linalg.inv(T1), T1 @ np.linalg.inv(T0), atol=1e-9)  # the same step again
    np.testing.assert_allclose(predict([T0, T1, T2]), predict([T1, T2]), atol=1e-9)  # steady motion: no acceleration
    # Uniformly accelerated (x = 0.5 a k^2, a = 2 mm per frame squared), or turning at a
    # steady rate: the next pose exactly.
    def moved(k):
        T = look_at_pose([0.0, 0.0, 500.0], 20, 30, 10)
        T[0, 3] += k * k
        return T

    def turned(k):
        return look_at_pose([0.0, 0.0, 500.0], 20, 30, 3.0 * k)

    for pose in (moved, turned):
        np.testing.assert_allclose(predict([pose(4), pose(5), pose(6)]), pose(7), atol=1e-9)


def test_inside_needs_every_ring_with_a_margin():
    ring = ((100.0, 100.0), (40.0, 30.0), 0.0)
    assert inside([ring], (640, 480), 2.0)
    assert not inside([ring, ((630.0, 100.0), (40.0, 30.0), 0.0)], (640, 480), 2.0)


@needs_nets
def test_track_follows_detects_again_and_loses_cleanly(rig, sequence):
    frames, empty = sequence
    tracker, cold = mp.MarkerPose(rig), mp.MarkerPose(rig)
    sources = []
    for f in frames:
        est = tracker.track(*f.images)
        ref = cold.estimate(*f.images)
        assert est is not None and ref is not None
        sources.append(est.source)
        # As accurate as cold detection on the same frame (the same edges, refitted).
        assert np.linalg.norm(est.t - f.T_left_marker[:3, 3]) < 0.02
        assert np.linalg.norm(est.t - ref.t) < 0.001 and est.residual_px < 0.1
    assert sources[0] == "detected" and set(sources[2:]) == {"tracked"}
    # The marker leaves both views: None, never a stale pose; then it is found again at once.
    for img in empty:
        assert tracker.track(img, img) is None
    again = tracker.track(*frames[0].images)
    assert again is not None and again.source == "detected"
    tracker.reset()
    assert tracker.track(*frames[1].images).source == "detected"


@needs_nets
def test_a_wrong_prior_falls_back_to_detection(rig, sequence):
    frames, _ = sequence
    tracker = mp.MarkerPose(rig)
    tracker.track(*frames[0].images)
    tracker._history = [look_at_pose([60.0, 40.0, 600.0], 10, 0, 90)]  # a prior 70 mm and 80° off
    est = tracker.track(*frames[1].images)
    assert est is not None and est.source == "detected"
    assert np.linalg.norm(est.t - frames[1].T_left_marker[:3, 3]) < 0.02


def test_track_with_the_classical_detector(rig, sequence):
    frames, empty = sequence
    tracker = mp.MarkerPose(rig, detector="classical")
    found = [tracker.track(*f.images) for f in frames]
    assert all(e is not None for e in found) and found[-1].source == "tracked"
    assert tracker.track(empty[0], empty[1]) is None


@needs_nets
def test_after_a_jump_the_prior_restarts_from_the_found_pose(rig, sequence):
    # The marker put down 15 mm away between two frames, then held still: the frame of the
    # jump is detected cold; the next one is tracked (standing still at the found pose, not
    # moving on by the jump), and so are those after it.
    frames, _ = sequence
    T = look_at_pose([10.0, -8.0, 555.0], 33, 45, 14)
    still = [render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=20 + k) for k in range(3)]
    tracker = mp.MarkerPose(rig)
    for f in frames[:4]:
        tracker.track(*f.images)
    sources = [tracker.track(*f.images).source for f in still]
    assert sources == ["detected", "tracked", "tracked"]
