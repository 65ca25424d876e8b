"""The public API contract (DESIGN §3) on rendered stereo pairs."""

import re

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.geometry import rotation_angle
from markerpose.synth import Imaging, clutter_background, look_at_pose, render_stereo


@pytest.fixture(scope="module", params=["neural", "classical"])
def detector(request):
    """The contract holds for both detectors (neural is the default)."""
    return request.param


@pytest.fixture(scope="module")
def frame(rig):
    return render_stereo(rig, look_at_pose([15, -10, 560], 30, 40, 25), seed=11)


def test_estimate_contract_and_accuracy(rig, frame):
    tracker = mp.MarkerPose(rig, marker=mp.Marker(), detector="classical")
    est = tracker.estimate(*frame.images)
    assert est is not None
    assert est.T.shape == (4, 4) and est.T.dtype == np.float64
    assert est.R.shape == (3, 3) and est.t.shape == (3,)
    assert est.points3d.shape == (3, 3) and est.centers.shape == (2, 3, 2)
    np.testing.assert_array_equal(est.T[3], [0, 0, 0, 1])
    gt = frame.T_left_marker
    assert np.linalg.norm(est.t - gt[:3, 3]) < 0.5  # mm
    assert np.rad2deg(rotation_angle(est.R, gt[:3, :3])) < 0.5
    px = np.linalg.norm(est.centers - np.stack([v.centers for v in frame.views]), axis=2)
    assert px.max() < 1.0


def test_default_detector_is_neural(rig):
    assert mp.MarkerPose(rig).conf["detector"] == "neural"


def test_detect_one_view_orders_by_id(rig, frame, detector):
    det = mp.MarkerPose(rig, detector=detector).detect(frame.images[0])
    assert det is not None and det.centers.shape == (3, 2)
    assert np.linalg.norm(det.centers - frame.views[0].centers, axis=1).max() < 1.0


def test_bgr_input_equals_gray(rig, frame, detector):
    tracker = mp.MarkerPose(rig, detector=detector)
    a = tracker.estimate(*frame.images)
    b = tracker.estimate(*(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in frame.images))
    np.testing.assert_allclose(a.T, b.T, atol=1e-9)


def test_rigid_pose_is_orthonormal_and_agrees_with_paper(rig, frame, detector):
    paper = mp.MarkerPose(rig, detector=detector, solve={"pose": "paper"}).estimate(*frame.images)
    rigid = mp.MarkerPose(rig, detector=detector, solve={"pose": "rigid"}).estimate(*frame.images)
    np.testing.assert_allclose(rigid.R @ rigid.R.T, np.eye(3), atol=1e-12)
    assert np.rad2deg(rotation_angle(paper.R, rigid.R)) < 0.5
    np.testing.assert_allclose(paper.points3d, rigid.points3d)


def test_marker_free_pair_is_none(rig, detector):
    rng = np.random.default_rng(5)
    imgs = [(clutter_background((1280, 1024), rng) * 200).astype(np.uint8) for _ in range(2)]
    assert mp.MarkerPose(rig, detector=detector).estimate(*imgs) is None


def test_marker_in_one_view_only_is_none(rig, frame, detector):
    rng = np.random.default_rng(6)
    empty = (clutter_background((1280, 1024), rng) * 200).astype(np.uint8)
    assert mp.MarkerPose(rig, detector=detector).estimate(frame.images[0], empty) is None


def test_dark_pair_still_tracked(rig, detector):
    f = render_stereo(rig, look_at_pose([0, 0, 500], 20, 0, 0), imaging=Imaging(alpha=0.25), seed=2)
    est = mp.MarkerPose(rig, detector=detector).estimate(*f.images)
    assert est is not None and np.linalg.norm(est.t - f.T_left_marker[:3, 3]) < 1.0


@pytest.mark.parametrize(
    "left, right, match",
    [
        (None, "ok", "left image is None"),
        (np.zeros((0, 0), np.uint8), "ok", "empty"),
        (np.zeros((1024, 1280), np.float32), "ok", "uint8"),
        (np.zeros((1024, 1280, 4), np.uint8), "ok", "gray"),
        ("ok", np.zeros((1000, 1280), np.uint8), "differ in size"),
        ([[0]], "ok", "numpy array"),
    ],
)
def test_bad_input_raises(rig, frame, detector, left, right, match):
    left = frame.images[0] if isinstance(left, str) else left
    right = frame.images[1] if isinstance(right, str) else right
    with pytest.raises(ValueError, match=match):
        mp.MarkerPose(rig, detector=detector).estimate(left, right)


def test_image_size_must_match_the_calibration(rig, detector):
    small = np.zeros((480, 640), np.uint8)
    with pytest.raises(ValueError, match="calibrated for 1280x1024"):
        mp.MarkerPose(rig, detector=detector).estimate(small, small)


def test_bad_configuration(rig):
    with pytest.raises(ValueError, match="weights not found"):
        mp.MarkerPose(rig, propose={"weights": "/nonexistent/keypoints.pt"})
    with pytest.raises(ValueError, match=r"refine.method must be one of \[.*got 'magic'"):
        mp.MarkerPose(rig, refine={"method": "magic"})
    with pytest.raises(ValueError, match=r"detector must be one of \['neural', 'stereo', 'decoded', 'classical'\], got 'magic'"):
        mp.MarkerPose(rig, detector="magic")
    with pytest.raises(ValueError, match="solve.pose must be one of"):
        mp.MarkerPose(rig, solve={"pose": "best"})
    with pytest.raises(ValueError, match="unknown option 'speed'"):
        mp.MarkerPose(rig, speed=3)
    # A flat option of earlier releases says where it went.
    with pytest.raises(ValueError, match=r"unknown option 'bias_correction' \(now solve="):
        mp.MarkerPose(rig, bias_correction=False)
    with pytest.raises(ValueError, match=r"unknown verify setting 'plate'"):
        mp.MarkerPose(rig, verify={"plate": 1})
    # Every stage setting is checked against its rule, not only its name.
    for stage, bad, what in (
        ("propose", {"threshold": float("nan")}, r"propose.threshold must be a number in \[0, 1\], got nan"),
        ("match", {"max_fits": 0}, r"match.max_fits must be a whole number >= 1, got 0"),
        ("verify", {"epipolar_tol": -1}, r"verify.epipolar_tol must be a number > 0"),
        ("track", {"lost_block": 2.5}, r"track.lost_block must be a whole number >= 1"),
        ("refine", {"blur_fit": "yes"}, r"refine.blur_fit must be true or false"),
        ("match", {"method": "magic"}, r"match.method must be one of \['stereo', 'layout', 'head'\]"),
    ):
        with pytest.raises(ValueError, match=what):
            mp.MarkerPose(rig, **{stage: bad})
    with pytest.raises(ValueError, match="threads must be a whole number >= 1"):
        mp.MarkerPose(rig, threads=0)
    with pytest.raises(ValueError, match="takes a dict"):
        mp.MarkerPose(rig, solve="paper")
    with pytest.raises(ValueError, match="unknown preset 'best'"):
        mp.MarkerPose(rig, preset="best")
    with pytest.raises(ValueError, match="StereoRig"):
        mp.MarkerPose("rig.yaml")


def test_fuzzed_images_raise_value_error_or_give_none(rig):
    """Images as a user's mistakes come (any dtype, shape, channels, size): a ValueError
    naming the image, or a result — never another exception, never a pose from nothing."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    tracker = mp.MarkerPose(rig, detector="classical")
    sizes = st.sampled_from([(0, 0), (8, 8), (1024, 1280), (1280, 1024), (512, 640), (1024, 1279)])
    dtypes = st.sampled_from([np.uint8, np.uint16, np.int8, np.float32, np.float64, bool])
    channels = st.sampled_from([None, 1, 2, 3, 4])

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(size=sizes, dtype=dtypes, ch=channels, fill=st.integers(0, 255), other=st.booleans())
    def check(size, dtype, ch, fill, other):
        shape = size if ch is None else (*size, ch)
        img = np.full(shape, fill).astype(dtype)
        good = np.full((1024, 1280), 128, np.uint8)
        left, right = (img, good) if other else (good, img)
        try:
            est = tracker.estimate(left, right)
        except ValueError as exc:
            assert "image" in str(exc)
        else:
            assert est is None  # flat images hold no marker
        try:
            det = tracker.detect(img, view=0)
        except ValueError as exc:
            assert "image" in str(exc)
        else:
            assert det is None

    check()


@pytest.mark.parametrize("bad", [np.zeros((1024, 1280, 4), np.uint8), np.zeros((512, 640), np.uint8), np.zeros((1280, 1024), np.uint8)])
def test_detect_checks_the_image_against_the_rig(rig, bad):
    """A resized, transposed or cropped view is refused rather than detected in the rig's pixel frame."""
    with pytest.raises(ValueError, match="image"):
        mp.MarkerPose(rig, detector="classical").detect(bad, view=1)


def test_why_says_which_stage_found_nothing(rig, frame):
    """After a call that gives no pose, ``tracker.why`` names the stage and the figure
    that stopped it; after a success it is None."""
    tracker = mp.MarkerPose(rig, detector="classical")
    assert tracker.estimate(*frame.images) is not None and tracker.why is None
    blank = np.full_like(frame.images[0], 90)
    assert tracker.estimate(frame.images[0], blank) is None
    assert re.search(r"no pair of marker-like ring triples \(\d+ left, 0 right\) agrees with the epipolar geometry", tracker.why)
    strict = mp.MarkerPose(rig, detector="classical", verify={"max_shape_error": 1e-6})
    assert strict.estimate(*frame.images) is None
    assert re.match(r"shape check: the triangulated centres are 0\.\d+ mm from the marker's layout \(limit 1e-06 mm\)", strict.why)
    assert tracker.detect(blank) is None and tracker.why == "no marker-like triple of rings in this view"


@pytest.mark.parametrize("swap", [False, True], ids=["left view twice", "views swapped"])
def test_inconsistent_pair_costs_a_bounded_amount_of_work(rig, frame, swap, monkeypatch):
    """A pair no pose explains is given up after ``match.max_fits`` refined hypotheses and
    ``refine.max_blur_fits`` blurred-ring fits, with no pose; a valid pair needs one."""
    from markerpose import blurfit
    from markerpose.stages import refine

    calls = {"fits": 0, "blur": 0}
    refine_call, blur_fit = refine.Refiner.__call__, blurfit.fit_blurred_rings

    def counted_refine(self, *a, **k):
        calls["fits"] += 1
        return refine_call(self, *a, **k)

    def counted_blur(*a, **k):
        calls["blur"] += 1
        return blur_fit(*a, **k)

    monkeypatch.setattr(refine.Refiner, "__call__", counted_refine)
    monkeypatch.setattr(blurfit, "fit_blurred_rings", counted_blur)
    tracker = mp.MarkerPose(rig)
    assert tracker.estimate(*frame.images) is not None and calls["fits"] == 1
    blurred = render_stereo(rig, look_at_pose([15, -10, 560], 30, 40, 25), imaging=Imaging(motion_blur=25.0, motion_angle=30.0), seed=11)
    left, right = blurred.images
    calls.update(fits=0, blur=0)
    assert tracker.estimate(*((right, left) if swap else (left, left))) is None
    assert calls["fits"] <= tracker.conf["match"]["max_fits"] and calls["blur"] <= tracker.conf["refine"]["max_blur_fits"]
    unbounded = mp.MarkerPose(rig, match={"max_fits": 100}, refine={"max_blur_fits": 100})
    calls.update(fits=0, blur=0)
    # Without the budget, and with the second look taken whatever the first fitted (which
    # here bounds the work too: Frame.plate_seen), the same pair costs more fits.
    from markerpose.frame import Frame

    monkeypatch.setattr(Frame, "plate_seen", property(lambda self: False, lambda self, value: None), raising=False)
    assert unbounded.estimate(*((right, left) if swap else (left, left))) is None
    assert calls["fits"] > tracker.conf["match"]["max_fits"]  # the budget is what bounds it


def _blas_threads() -> list:
    from threadpoolctl import ThreadpoolController

    return [p["num_threads"] for p in ThreadpoolController().select(user_api="blas").info()]


def test_blas_runs_on_one_thread_inside_a_call_only(rig, frame, monkeypatch):
    from threadpoolctl import threadpool_limits

    if not _blas_threads():
        pytest.skip("numpy's BLAS is not one threadpoolctl can see")
    tracker = mp.MarkerPose(rig)
    inside = []
    tool = tracker.tools["marker"]
    cold = tool.cold
    monkeypatch.setattr(tool, "cold", lambda frame: (inside.append(_blas_threads()), cold(frame))[1])
    with threadpool_limits(limits=2, user_api="blas"):
        est = tracker.estimate(*frame.images)
        assert est is not None and inside and all(n == 1 for n in inside[0])
        assert all(n == 2 for n in _blas_threads())  # put back after the call


def test_serial_blas_is_counted_across_overlapping_calls():
    from threadpoolctl import threadpool_limits

    from markerpose.pipeline import _SerialBlas

    if not _blas_threads():
        pytest.skip("numpy's BLAS is not one threadpoolctl can see")
    serial = _SerialBlas()
    with threadpool_limits(limits=2, user_api="blas"):
        outer = serial()
        outer.__enter__()
        with serial():  # a second tracker's frame (another thread) starts and ends meanwhile
            assert all(n == 1 for n in _blas_threads())
        assert all(n == 1 for n in _blas_threads())  # the first one is still running
        outer.__exit__(None, None, None)
        assert all(n == 2 for n in _blas_threads())


def test_serial_blas_puts_the_threads_back_when_a_call_raises(rig):
    from threadpoolctl import threadpool_limits

    if not _blas_threads():
        pytest.skip("numpy's BLAS is not one threadpoolctl can see")
    tracker = mp.MarkerPose(rig)
    with threadpool_limits(limits=2, user_api="blas"):
        with pytest.raises(ValueError):
            tracker.estimate(np.zeros((10, 10), np.uint8), np.zeros((10, 10), np.uint8))  # not the rig's size
        assert all(n == 2 for n in _blas_threads())
        from markerpose.pipeline import serial_blas

        assert serial_blas._inside == 0


def test_each_view_noise_is_estimated_once_a_frame(rig, frame, monkeypatch):
    """However many hypotheses a cold detection refines, each image's noise estimate (the
    edge fit's contrast floor) is computed once per call, and again in the next call (a
    new frame, even in the same buffers)."""
    from markerpose import classical

    tracker = mp.MarkerPose(rig)
    expected = tracker.estimate(*frame.images)
    seen, counted = [], []
    real, from_counts = classical.noise_sigma, classical.noise_from_residuals
    monkeypatch.setattr(classical, "noise_sigma", lambda g: seen.append(id(g)) or real(g))
    # stage 1's input of a 1280x1024 view counts the estimate's residuals in its own pass
    monkeypatch.setattr(classical, "noise_from_residuals", lambda h: counted.append(1) or from_counts(h))
    for _ in range(2):
        seen.clear(), counted.clear()
        est = tracker.estimate(*frame.images)
        assert len(seen) == len(set(seen)) and len(seen) + len(counted) == 2
        np.testing.assert_array_equal(est.T, expected.T)


def test_two_trackers_in_two_threads_share_nothing(rig):
    """Each thread's tracker gives what it gives alone; one tracker called from a second
    thread while it handles a frame refuses with a clear error."""
    import threading

    from markerpose.synth import Imaging

    poses = [look_at_pose([-5 + 2.0 * k, 2, 560 - k], 30 + k, 45, 10 + k) for k in range(4)]
    others = [look_at_pose([20 - 2.0 * k, -10, 600 + k], 25, 30 + k, 70) for k in range(4)]
    seqs = [[render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=k).images for k, T in enumerate(p)] for p in (poses, others)]
    alone = []
    for seq in seqs:
        tracker = mp.MarkerPose(rig, detector="classical")
        alone.append([tracker.track(*pair).T for pair in seq])
    got: list = [None, None]

    def run(i):
        tracker = mp.MarkerPose(rig, detector="classical")
        got[i] = [tracker.track(*pair).T for pair in seqs[i]]

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for a, b in zip(alone, got):
        np.testing.assert_array_equal(np.stack(a), np.stack(b))
    tracker = mp.MarkerPose(rig, detector="classical")
    entered, release = threading.Event(), threading.Event()
    tool = tracker.tools["marker"]
    cold = tool.cold
    tool.cold = lambda frame: (entered.set(), release.wait(10), cold(frame))[2]
    worker = threading.Thread(target=tracker.estimate, args=seqs[0][0])
    worker.start()
    assert entered.wait(10)
    with pytest.raises(RuntimeError, match="another thread"):
        tracker.track(*seqs[0][0])
    release.set()
    worker.join()
    assert tracker.track(*seqs[0][0]) is not None  # free again


def test_a_built_tracker_is_left_out_of_the_cyclic_collectors_scans():
    """What is alive when a MarkerPose is built (its runtimes' objects, the tracker) is
    frozen: a full collection on a stream's frame no longer scans it; a dropped tracker is
    still freed (by reference counting)."""
    import subprocess
    import sys

    code = """
import gc, weakref
import markerpose as mp
before = gc.get_freeze_count()
t = mp.MarkerPose(mp.StereoRig.default())
frozen = gc.get_freeze_count()
scanned = any(o is t.conf for o in gc.get_objects())
gone = weakref.ref(t.detector)
del t
gc.collect()
print(before, frozen, scanned, gone() is None)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True).stdout.split()
    assert int(out[0]) == 0 and int(out[1]) > 10_000
    assert out[2] == "False" and out[3] == "True"
