"""MarkerPose.track: the previous frames as the prior (markerpose.stages.track)."""

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.geometry import ring_ellipses
from markerpose.nets import default_weights
from markerpose.stages.track import (
    blocks,
    changed,
    default_conf,
    inside,
    predict,
    shift,
)
from markerpose.synth import Imaging, clutter_background, look_at_pose, render_stereo

needs_nets = pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped weights")


@pytest.fixture(scope="module")
def sequence(rig):
    """Eight frames of a marker moving 1.5 mm and 1° a frame, the last two without it."""
    frames = [
        render_stereo(rig, look_at_pose([-5 + 1.5 * k, 2, 560 - k], 30 + k, 45, 10 + k), imaging=Imaging(alpha=0.8), seed=k)
        for k in range(6)
    ]
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
    tracker.tracker.history = [look_at_pose([60.0, 40.0, 600.0], 10, 0, 90)]  # a prior 70 mm and 80° off
    searched, search = [], tracker.tracker.searched
    tracker.tracker.searched = lambda *a: searched.append(search(*a)) or searched[-1]
    est = tracker.track(*frames[1].images)
    assert searched == [None] and est is not None and est.source == "detected"  # the search found nothing like it
    assert np.linalg.norm(est.t - frames[1].T_left_marker[:3, 3]) < 0.02


def test_track_with_the_classical_detector(rig, sequence):
    frames, empty = sequence
    tracker = mp.MarkerPose(rig, detector="classical")
    found = [tracker.track(*f.images) for f in frames]
    assert all(e is not None for e in found) and found[-1].source == "tracked"
    assert tracker.track(empty[0], empty[1]) is None


@needs_nets
def test_after_a_jump_the_prior_restarts_from_the_found_pose(rig, sequence):
    # The marker put down 15 mm away between two frames, then held still. The frame of the
    # jump: the prior fails, the search by appearance finds the marker (without the search,
    # stage 1's window). Its step is many times the step before (a jump, ``jump_ratio``):
    # the next prior takes the marker as standing at the found pose, and tracks it. With
    # the step taken as a velocity (``jump_ratio`` 0), the next prior moves on by the jump
    # and fails, and the search starts from the found pose instead (standing still there).
    frames, _ = sequence
    T = look_at_pose([10.0, -8.0, 555.0], 33, 45, 14)
    still = [render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=20 + k) for k in range(3)]
    for conf, sources, searches in (
        ({}, ["tracked"] * 3, 1),
        (NO_SEARCH, ["detected", "tracked", "tracked"], 1),
        ({"jump_ratio": 0.0}, ["tracked"] * 3, 2),
    ):
        tracker = mp.MarkerPose(rig, track=conf)
        for f in frames[:4]:
            tracker.track(*f.images)
        searched, search = [], tracker.tracker.searched
        tracker.tracker.searched = lambda frame, T_pred, seen=searched, fn=search: (seen.append(T_pred), fn(frame, T_pred))[1]
        found = [tracker.track(*f.images) for f in still]
        assert [e.source for e in found] == sources
        assert all(np.linalg.norm(e.t - T[:3, 3]) < 0.02 for e in found)
        assert len(searched) == searches  # the jump (and, where its step is a velocity, the frame after it)
        if searches == 2:
            np.testing.assert_allclose(searched[1], found[0].T)


def test_a_step_found_after_a_failed_prior_is_a_jump_only_well_beyond_the_step_before(rig):
    """``Tracker._jumped``: the rings' move into a pose found after the prior failed against
    their move in the frame before, rotation counted as translation is; no judgement
    without a step before, nor with ``jump_ratio`` 0."""
    from markerpose.stages.track import Tracker

    mk = mp.Marker()
    tracker = Tracker(default_conf, rig, mk)
    T = [look_at_pose([2.0 * k, 0.0, 560.0], 30, 45, 0) for k in range(3)]
    tracker.history = T[:1]
    assert not tracker._jumped(look_at_pose([40.0, 0.0, 560.0], 30, 45, 0))  # one pose: no step before
    tracker.history = T[:2]
    assert not tracker._jumped(T[2])  # the same step again: a velocity
    assert not tracker._jumped(look_at_pose([7.5, 0.0, 560.0], 30, 45, 0))  # 2.75x the step: still one
    assert tracker._jumped(look_at_pose([20.0, 0.0, 560.0], 30, 45, 0))  # 9x: a jump
    assert tracker._jumped(look_at_pose([2.0, 0.0, 560.0], 30, 45, 25))  # turned in place by 25°: a jump
    tracker.conf = {**default_conf, "jump_ratio": 0.0}
    assert not tracker._jumped(look_at_pose([20.0, 0.0, 560.0], 30, 45, 0))


def _view_shift(rig, T_from, T_to, view):
    """(3, 2) image displacements (px) of the rings' ellipse centres from pose T_from to T_to."""
    cam, to_view, mk = rig.cameras[view], (np.eye(4), rig.T_right_left)[view], mp.Marker()
    c = [np.array([e[0] for e in ring_ellipses(cam, to_view @ T, mk.points3d, mk.outer_radius)]) for T in (T_from, T_to)]
    return c[1] - c[0]


def test_known_noises_are_used_for_the_frame(monkeypatch):
    from markerpose import classical
    from markerpose.frame import Frame

    grays = [np.zeros((64, 64), np.uint8), np.ones((64, 64), np.uint8)]
    calls = []
    monkeypatch.setattr(classical, "noise_sigma", lambda g: calls.append(1) or 9.0)
    frame = Frame(grays)
    assert frame.noises(grays, known=[1.5, 2.5]) == [1.5, 2.5]
    assert frame.noises(grays) == [1.5, 2.5] and frame.noises(grays[1:]) == [2.5] and not calls
    assert Frame(grays).noises(grays) == [9.0, 9.0] and len(calls) == 2  # a new call: estimated


def test_shift_finds_the_marker_where_the_prior_missed_it(rig):
    # The prior puts the marker 15 mm and 7° from where it is (the rings 57-86 px away,
    # up to 17 px apart), sharp and under 15 px of motion blur: the correlation of its drawn
    # appearance, then of each ring's, finds each ring's displacement to ~1 px (the edge
    # fit captures several) in both views. No marker: a low correlation. A
    # predicted plate outside the image: no search.
    mk = mp.Marker()
    T_true = look_at_pose([10.0, -8.0, 555.0], 33, 45, 16)
    T_prior = look_at_pose([-5.0, 2.0, 560.0], 30, 45, 10)
    rng = np.random.default_rng(3)
    bgs = tuple(clutter_background(c.image_size, rng, ring_distractors=4, ring_ratio=0.4) for c in rig.cameras)
    for blur in (0.0, 15.0):
        f = render_stereo(rig, T_true, imaging=Imaging(alpha=0.8, motion_blur=blur, motion_angle=20.0), background=bgs, seed=7)
        for view, gray in enumerate(f.images):
            gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY) if gray.ndim == 3 else gray
            T = (np.eye(4), rig.T_right_left)[view] @ T_prior
            d, score = shift(gray, rig.cameras[view], T, mk, 0.5)
            truth = _view_shift(rig, T_prior, T_true, view)
            assert np.ptp(truth, axis=0).max() > 12 and np.linalg.norm(truth, axis=1).min() > 50
            assert np.linalg.norm(d - truth, axis=1).max() < 1.5 and score > default_conf["shift_min_score"]
    empty = (bgs[0] * 200).astype(np.uint8)
    assert shift(empty, rig.cameras[0], T_prior, mk, 0.5)[1] < default_conf["shift_min_score"] - 0.1
    off = look_at_pose([400.0, 0.0, 560.0], 30, 45, 10)
    assert shift(empty, rig.cameras[0], off, mk, 0.5) is None


@needs_nets
def test_a_jump_near_the_prior_is_tracked_without_stage_1(rig, sequence):
    # The marker put down 15 mm away: the prior's edge fit misses it, the search by its
    # appearance finds it, and the frame is tracked (as accurately), without stage 1.
    frames, _ = sequence
    T = look_at_pose([10.0, -8.0, 555.0], 33, 45, 14)
    f = render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=30)
    tracker = mp.MarkerPose(rig)
    for g in frames[:4]:
        tracker.track(*g.images)
    seen = _spy_looks(tracker.detector.proposer)
    est = tracker.track(*f.images)
    assert seen == [] and est is not None and est.source == "tracked"
    assert np.linalg.norm(est.t - T[:3, 3]) < 0.02
    ref = mp.MarkerPose(rig).estimate(*f.images)
    assert np.linalg.norm(est.t - ref.t) < 0.005


def test_changed_sees_a_ring_coming_into_view_not_the_noise():
    rng = np.random.default_rng(3)
    bg = clutter_background((640, 480), rng) * 180 + 20
    yy, xx = np.mgrid[:480, :640]
    band = (np.hypot(xx - 300.3, yy - 200.6) > 6) & (np.hypot(xx - 300.3, yy - 200.6) < 12)  # a far ring's 6 px band

    def shot(sigma, extra=0.0, blur=0.0):
        noise = rng.normal(0, 1, bg.shape)
        if blur:  # noise correlated across pixels, as demosaicing and denoising make it
            noise = cv2.GaussianBlur(noise, (0, 0), blur) / cv2.GaussianBlur(noise, (0, 0), blur).std()
        return np.clip(bg + extra + sigma * noise, 0, 255).astype(np.uint8)

    for sigma in (1.0, 3.0):
        base = blocks(shot(sigma), 8)
        assert base.shape == (60, 80) and base.dtype == np.float32
        for blur in (0.0, 1.5):
            assert not any(changed(base, blocks(shot(sigma, blur=blur), 8), 6.0) for _ in range(5))
        # The ring comes in, its band 4 noise sigmas under its surroundings (the edge fit takes 2).
        assert changed(base, blocks(shot(sigma, np.where(band, -4 * sigma - 1, 0.0)), 8), 6.0)
    base = blocks(shot(3.0), 8)
    # The whole scene changed (another view, the light): a change, however robust the spread.
    assert changed(base, blocks(np.clip(shot(3.0) * 1.1, 0, 255).astype(np.uint8), 8), 6.0)
    assert changed(base, blocks(np.roll(shot(3.0), 40, axis=1), 8), 6.0)
    # Exact means, the partial last row and column of pixels left out.
    odd = (np.arange(35 * 19) % 251).astype(np.uint8).reshape(19, 35)
    np.testing.assert_allclose(blocks(odd, 8), odd[:16, :32].reshape(2, 8, 4, 8).mean((1, 3)), rtol=1e-6)


@needs_nets
def test_while_lost_an_unchanged_pair_is_not_detected_again(rig):
    # A still scene without the marker, in the dark (the marker's faintest change), fresh
    # sensor noise every frame: after one cold detection finds nothing, unchanged pairs
    # return None without a detection until the refresh; the marker coming into view is
    # found on its first frame.
    rng = np.random.default_rng(11)
    bgs = tuple(clutter_background((1280, 1024), rng) for _ in range(2))
    dark = Imaging(alpha=0.0625)
    away = [render_stereo(rig, look_at_pose([700.0, 0, 560], 30, 45, 10), imaging=dark, background=bgs, seed=40 + k) for k in range(4)]
    here = render_stereo(rig, look_at_pose([-5.0, 0, 560], 30, 45, 10), imaging=dark, background=bgs, seed=50)
    tracker = mp.MarkerPose(rig, track={"lost_refresh": 3})
    detected = []
    for f in away:
        assert tracker.track(*f.images) is None
        detected.append("propose" in tracker.timings)
    assert detected == [True, False, False, True]  # cold, skipped twice, cold again (the refresh)
    assert "not changed" in (tracker.track(*away[0].images), tracker.why)[1]  # the next unchanged pair
    tracker.reset()  # a new sequence: nothing to compare with
    assert tracker.track(*away[1].images) is None and "propose" in tracker.timings
    est = tracker.track(*here.images)
    assert est is not None and est.source == "detected"
    assert np.linalg.norm(est.t - here.T_left_marker[:3, 3]) < 0.05
    # With the gate off every lost pair is detected cold.
    off = mp.MarkerPose(rig, track={"lost_change": 0})
    for f in away[:2]:
        assert off.track(*f.images) is None and "propose" in off.timings


def test_track_conf_is_checked(rig):
    for bad in (
        {"near_margin": -1},
        {"shift_margin": -0.5},
        {"shift_min_score": 1.5},
        {"lost_change": -1},
        {"lost_block": 0},
        {"lost_refresh": 0},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            mp.MarkerPose(rig, detector="classical", track=bad)


NO_SEARCH = {"shift_margin": 0}  # track() straight from a failed prior to stage 1


def _spy_looks(proposer) -> list:
    """The proposer's looks from now on, in order ("near", "whole"), as a list it fills."""
    seen: list = []
    near, whole = proposer.near, proposer.candidates
    proposer.near = lambda *a: seen.append("near") or near(*a)
    proposer.candidates = lambda *a: seen.append("whole") or whole(*a)
    return seen


@needs_nets
def test_when_the_prior_fails_stage_1_looks_near_the_prediction_first(rig, sequence):
    # Without the search by appearance: the marker put down ~15 mm from its last pose: stage 1 looks only in a
    # window around the prediction (a fraction of the image) and finds it there. Put down
    # ~180 mm away, outside that window: found by the whole-image detection after it.
    frames, _ = sequence
    near_pose = look_at_pose([10.0, -8.0, 555.0], 33, 45, 14)
    far_pose = look_at_pose([-150.0, 60.0, 640.0], 25, 45, 0)
    for T, looks in ((near_pose, ["near"]), (far_pose, ["near", "whole"])):
        f = render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=30)
        tracker = mp.MarkerPose(rig, track=NO_SEARCH)
        for g in frames[:4]:
            tracker.track(*g.images)
        seen = _spy_looks(tracker.detector.proposer)
        est = tracker.track(*f.images)
        assert est is not None and est.source == "detected" and np.linalg.norm(est.t - T[:3, 3]) < 0.02
        assert seen[: len(looks)] == looks and (len(looks) == 2 or "whole" not in seen)
    # A pair no marker pose explains (the left view twice) while tracking: the near look and
    # the whole-image detection share one frame's work budget, as estimate() has it.
    tracker = mp.MarkerPose(rig, track=NO_SEARCH)
    for g in frames[:4]:
        tracker.track(*g.images)
    runs, fit = [], tracker.detector.fit
    tracker.detector.fit = lambda frame, *a: (runs.append(frame.fits_left > 0), fit(frame, *a))[1]
    left = render_stereo(rig, near_pose, imaging=Imaging(alpha=0.8), seed=31).images[0]
    assert tracker.track(left, left) is None
    assert sum(runs) <= tracker.conf["match"]["max_fits"]
    # A marker close to the cameras fills most of stage 1's input: no window, the whole images.
    close = [render_stereo(rig, look_at_pose([0.0, 0.0, 360.0 - k], 20, 45, 10), imaging=Imaging(alpha=0.8), seed=60 + k) for k in range(3)]
    tracker = mp.MarkerPose(rig, track=NO_SEARCH)
    for g in close[:2]:
        assert tracker.track(*g.images) is not None
    seen = _spy_looks(tracker.detector.proposer)
    jumped = render_stereo(rig, look_at_pose([15.0, 5.0, 360.0], 20, 45, 10), imaging=Imaging(alpha=0.8), seed=63)
    assert tracker.track(*jumped.images).source == "detected" and seen[0] == "whole"
    # near_margin 0: the whole images at once.
    tracker = mp.MarkerPose(rig, track={**NO_SEARCH, "near_margin": 0})
    for g in frames[:4]:
        tracker.track(*g.images)
    tracker.detector.proposer.near = lambda *a: pytest.fail("no near look with near_margin 0")
    assert tracker.track(*render_stereo(rig, near_pose, imaging=Imaging(alpha=0.8), seed=30).images).source == "detected"


class _Pipeline:
    """A stand-in for MarkerPose's side of tracking: each step answers from its own queue
    (an Estimate or None) and the calls are recorded."""

    def __init__(self, fitted=(), near=(), cold=()):
        self.answers = {"fitted": list(fitted), "near": list(near), "cold": list(cold)}
        self.calls: list = []

    def _answer(self, step, *args):
        self.calls.append((step, *args))
        return self.answers[step].pop(0) if self.answers[step] else None

    def fitted(self, frame, predicted, first_tol, noises):
        return self._answer("fitted", first_tol)

    def near(self, frame, T_pred):
        return self._answer("near")

    def cold(self, frame):
        return self._answer("cold")


def _estimate(T, residual=0.1):
    from markerpose.results import Estimate

    return Estimate(T=T, points3d=np.zeros((3, 3)), centers=np.zeros((2, 3, 2)), residual_px=residual)


def _frame(value=0):
    from markerpose.frame import Frame

    return Frame([np.full((1024, 1280), value, np.uint8)] * 2)


def test_tracker_state_machine_with_a_stand_in_pipeline(rig):
    """The Tracker alone: cold first, then the prior's fit; a fit over the residual gate
    counts as failed; a failed prior goes to the near detection, then the cold one; a lost
    marker in an unchanged scene is not detected again until ``lost_refresh``."""
    from markerpose.stages.track import Tracker

    conf = {**default_conf, "shift_margin": 0.0, "lost_refresh": 3}  # no search by appearance: no images needed
    tracker = Tracker(conf, rig, mp.Marker())
    T = [look_at_pose([1.0 * k, 0.0, 560.0], 30, 45, 0) for k in range(4)]
    pipe = _Pipeline(cold=[_estimate(T[0])], fitted=[_estimate(T[1])])
    assert tracker.next(_frame(), pipe) is not None and tracker.history[-1] is T[0]
    assert tracker.next(_frame(), pipe).T is T[1]
    assert [c[0] for c in pipe.calls] == ["cold", "fitted"] and pipe.calls[1][1] == conf["one_pass_move"]
    assert len(tracker.history) == 2 and tracker.noise[1] == 1
    # The prior's fit over the residual gate: failed; the near look (at the prediction), then cold.
    pipe = _Pipeline(fitted=[_estimate(T[2], residual=conf["max_residual_px"] * 2)], cold=[_estimate(T[2])])
    frame = _frame()
    assert tracker.next(frame, pipe).T is T[2]
    assert [c[0] for c in pipe.calls] == ["fitted", "near", "cold"] and frame.why is None
    assert tracker.after_miss and len(tracker.history) == 2  # velocity only after a miss
    # Lost in a still scene: one cold detection, then nothing until lost_refresh pairs.
    tracker.reset()
    pipe = _Pipeline()
    for k in range(4):
        frame = _frame()
        assert tracker.next(frame, pipe) is None
        assert frame.why == (
            "no marker found" if k in (0, 3) else "lost, and the pair has not changed since the last one detected without the marker"
        )
    assert [c[0] for c in pipe.calls] == ["cold", "cold"]
    assert tracker.next(_frame(200), pipe) is None and len(pipe.calls) == 3  # the scene changed: detected
