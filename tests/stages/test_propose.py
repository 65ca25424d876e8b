"""The propose stage (markerpose.stages.propose): stage 1's candidates, its looks."""

import numpy as np
import pytest

import markerpose as mp
from markerpose import decode as dec
from markerpose import keypoints as kp
from markerpose.ellipses import PATCH
from markerpose.frame import Frame
from markerpose.nets import default_weights
from markerpose.stages import propose
from markerpose.synth import Imaging, look_at_pose, render_stereo

needs_nets = pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped weights")


@needs_nets
def test_each_ring_has_a_candidate_and_a_call_makes_each_input_once(rig):
    f = render_stereo(rig, look_at_pose([10, -20, 600], 35, 60, 15), imaging=Imaging(alpha=0.7), seed=5)
    proposer = propose.NeuralProposer(propose.default_conf, mp.Marker(), "stereo")
    assert proposer.looks() == (1.0, 2.0)
    frame = Frame(list(f.images))
    cand = proposer.candidates(frame.grays, kept=frame.looked)
    assert len(frame.looked) == 2  # one input per view at the first look
    for c, view in zip(cand, f.views):
        assert c.shape[1] == 3 and len(c) <= propose.MAX_CANDIDATES
        assert np.all(np.diff(c[:, 2]) <= 0)  # best first
        d = np.linalg.norm(c[None, :, :2] - view.centers[:, None], axis=2).min(1)
        assert np.all(d < 4.0), d  # each ring's centre within a few px of a candidate
    proposer.evidence(frame.grays[0], f.views[0].centers[None], kept=frame.looked)
    assert len(frame.looked) == 2  # the evidence looked where the look did


@needs_nets
def test_second_look_off_is_one_look():
    proposer = propose.NeuralProposer({**propose.default_conf, "second_look": 1.0}, mp.Marker(), "stereo")
    assert proposer.looks() == (1.0,)


def test_settings_are_checked():
    with pytest.raises(ValueError, match=r"propose.second_look must be a number >= 1, got 0.5"):
        propose.check_conf({**propose.default_conf, "second_look": 0.5})
    with pytest.raises(ValueError, match=r"unknown propose setting 'candidates'"):  # a constant now: MAX_CANDIDATES
        propose.check_conf({**propose.default_conf, "candidates": 8})


@needs_nets
def test_the_second_look_is_skipped_where_no_view_has_three_strong_candidates(rig):
    """A marker at 1.9 m (rings too small to be matched at the first look) still gets the
    second look: its rings score above ``second_look_min`` at the first. Clutter without the
    marker whose candidates all score under it does not (one forward pass, not two)."""
    from markerpose.experiments.endtoend import SETS, random_pairs

    proposer = propose.NeuralProposer(propose.default_conf, mp.Marker(), "stereo")
    far = render_stereo(rig, look_at_pose([-40, 20, 1900], 50, 30, 120), imaging=Imaging(alpha=0.6), seed=2)
    assert proposer.worth_second_look(proposer.candidates(Frame(list(far.images)).grays))
    weak = [np.array([[10.0, 10, 0.9], [50, 50, 0.25], [90, 90, 0.19]]), np.array([[10.0, 10, 0.9], [50, 50, 0.1]])]
    assert not proposer.worth_second_look(weak)
    # Two strong rings in a view (the third one shadowed, say) are worth it too.
    assert proposer.worth_second_look([np.array([[10.0, 10, 0.99], [50, 50, 0.85], [90, 90, 0.1]]), weak[1]])
    assert propose.NeuralProposer({**propose.default_conf, "second_look_min": 0.0}, mp.Marker(), "stereo").worth_second_look(weak)
    # Marker-free held-out pairs: most are decided after one look.
    tracker = mp.MarkerPose(rig)
    looks = []
    for f, _ in random_pairs({**SETS["marker_free"], "seed": 77}, 6, rig, mp.Marker()):
        assert tracker.estimate(*f.images) is None
        looks.append(proposer.worth_second_look(proposer.candidates(Frame(list(f.images)).grays)))
    assert sum(looks) <= 3, looks


def _whole_map_peaks(det, threshold, k, radius):
    """decode.peaks the long way: every cell's softmax, the whole map dilated."""
    return [dec._refine(s, dec.nms(s, radius, threshold, k)) for s in dec.score_maps(det)]


@pytest.mark.parametrize("threshold", [1e-4, 0.01, 0.3])
def test_peaks_from_the_live_cells_alone_are_the_whole_maps_to_the_bit(threshold):
    """decode.peaks runs the softmax only on the cells whose bound reaches the threshold
    (and their neighbours): the same rows, bit for bit, as the whole score map gives, with
    peaks on cell borders, in the map's corners, on plateaus and in noise."""
    rng = np.random.default_rng(7)
    det = rng.normal(0, 1.5, (4, 65, 12, 16)).astype(np.float32)
    det[:, 64] += rng.uniform(0, 6, (4, 12, 16)).astype(np.float32)  # a "no centre" logit of every strength
    det[0, 7, 3, 4] = det[0, 56, 3, 5] = 8.0  # two peaks either side of a cell border
    det[1, 0, 0, 0] = det[1, 63, 11, 15] = 9.0  # the map's corners
    det[2, 10, 5, 5] = det[2, 12, 5, 5] = 7.5  # a plateau: equal scores 2 px apart
    det[3] = rng.normal(0, 3, (65, 12, 16))  # noise: many weak maxima
    found = dec.peaks(det, threshold, 16, 4)
    for got, want in zip(found, _whole_map_peaks(det, threshold, 16, 4)):
        assert got.shape == want.shape
        np.testing.assert_array_equal(got, want)
    assert sum(len(f) for f in found) > 4


@needs_nets
def test_the_shipped_network_finds_the_same_candidates_either_way():
    """On rendered views (sharp, blurred, marker-free) the candidates from the live cells
    equal those from the whole score maps."""
    from markerpose.stages.propose import network_weights

    net = kp.KeypointNet(network_weights("mid"), stereo=True)
    rig = mp.StereoRig.default()
    views = []
    for seed, blur in enumerate((0.0, 25.0)):
        views += render_stereo(
            rig, look_at_pose([10, -20, 500 + 150 * seed], 35, 20, 60), imaging=Imaging(motion_blur=blur), seed=seed
        ).images
    views.append(np.full((1024, 1280), 90, np.uint8))
    det = net.det_logits(np.stack([kp.to_input(v, (320, 256))[0] for v in views]))
    for got, want in zip(dec.peaks(det, 0.01, 16, 4), _whole_map_peaks(det, 0.01, 16, 4)):
        np.testing.assert_array_equal(got, want)


def test_the_input_four_times_smaller_is_opencvs_area_resize():
    """The compiled 4x4 block means (stage 1's default input at 1280x1024) equal OpenCV's
    area resize to the bit, ties (a block's mean at half a grey level) included; other
    sizes and a strided image take OpenCV's resize itself."""
    import cv2

    rng = np.random.default_rng(3)
    for shape, size in [((1024, 1280), (320, 256)), ((64, 96), (24, 16)), ((1024, 1280), (320, 240)), ((1024, 1280), (640, 512))]:
        gray = rng.integers(0, 256, shape, dtype=np.uint8)
        gray[:8, :8] = np.tile([[0, 1], [1, 0]], (4, 4))  # a block whose mean is exactly 0.5: rounds to 0 (even)
        gray[8:12, :4] = 1
        gray[8:10, :4] = 2  # mean 1.5: rounds to 2
        want = cv2.resize(gray, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        got, scale = kp.to_input(gray, size)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_allclose(scale, [shape[1] / size[0], shape[0] / size[1]])
    wide = rng.integers(0, 256, (1024, 2560), dtype=np.uint8)
    np.testing.assert_array_equal(kp.to_input(wide[:, ::2], (320, 256))[0], kp.to_input(np.ascontiguousarray(wide[:, ::2]), (320, 256))[0])


@needs_nets
def test_the_detector_only_copy_gives_the_whole_networks_det_logits(tmp_path):
    """The shipped stage-1 networks' detector-only copies give the whole network's
    detector logits exactly; a copy that does not match its weights' metadata is not used."""
    import shutil

    from markerpose.nets import WEIGHTS_DIR, detector_only_path

    x = np.random.default_rng(0).random((3, 256, 320), dtype=np.float32)
    for name in ("keypoints-mid", "keypoints", "keypoints-lite"):
        net = kp.KeypointNet(WEIGHTS_DIR / f"{name}.onnx")
        assert net.locator is not None, name
        np.testing.assert_array_equal(net.det_logits(x), net.logits(x)[0])
    shutil.copy(WEIGHTS_DIR / "keypoints-mid.onnx", tmp_path / "mine.onnx")
    shutil.copy(WEIGHTS_DIR / "keypoints-lite-det.onnx", detector_only_path(tmp_path / "mine.onnx"))  # another network's copy
    mine = kp.KeypointNet(tmp_path / "mine.onnx")
    assert mine.locator is None
    np.testing.assert_array_equal(mine.det_logits(x), mine.logits(x)[0])


@needs_nets
@pytest.mark.parametrize("name", ["keypoints-mid-int8", "keypoints-mid", "keypoints-lite"])
def test_the_stacked_copy_runs_a_pair_as_the_network_runs_each_view(tmp_path, name):
    """A stereo pair's views as the two channels of the shipped stacked copy give what the
    detector-only network gives each view (ONNX Runtime, two or one thread); a stacked copy
    of other weights is not used."""
    import shutil

    from markerpose.nets import WEIGHTS_DIR, stacked_views_path

    x = np.random.default_rng(2).random((2, 256, 320), dtype=np.float32)
    plain = kp.KeypointNet(WEIGHTS_DIR / f"{name}.onnx", threads=2)
    each = np.concatenate([plain.det_logits(x[i : i + 1]) for i in range(2)])
    for threads in (2, 1):
        net = kp.KeypointNet(WEIGHTS_DIR / f"{name}.onnx", threads=threads, stack_views=True)
        assert net.locator.stacked and not plain.locator.stacked
        np.testing.assert_allclose(net.det_logits(x), each, rtol=0, atol=1e-5)
        np.testing.assert_allclose(net.det_logits(x[:1]), each[:1], rtol=0, atol=1e-5)  # one view: the plain copy
    shutil.copy(WEIGHTS_DIR / f"{name}.onnx", tmp_path / "mine.onnx")
    shutil.copy(WEIGHTS_DIR / f"{name}-det.onnx", tmp_path / "mine-det.onnx")
    other = "keypoints-mid-det-pair.onnx" if "int8" in name else "keypoints-mid-int8-det-pair.onnx"
    shutil.copy(WEIGHTS_DIR / other, stacked_views_path(tmp_path / "mine-det.onnx"))
    mine = kp.KeypointNet(tmp_path / "mine.onnx", stack_views=True)
    assert not mine.locator.stacked
    np.testing.assert_allclose(mine.det_logits(x), each, rtol=0, atol=1e-5)


@needs_nets
@pytest.mark.parametrize("name", ["keypoints-mid-int8", "keypoints-mid", "keypoints-lite"])
def test_the_shipped_stacked_copy_is_what_stack_views_makes(tmp_path, name):
    onnx = pytest.importorskip("onnx")
    from markerpose.nets import WEIGHTS_DIR, stack_views, stacked_views_path

    made = stack_views(WEIGHTS_DIR / f"{name}-det.onnx", tmp_path / "made.onnx")
    shipped = onnx.load(str(stacked_views_path(WEIGHTS_DIR / f"{name}-det.onnx")))
    assert onnx.load(str(made)).SerializeToString() == shipped.SerializeToString()


def test_stack_views_refuses_a_wide_stem_and_a_stacked_copy(tmp_path):
    pytest.importorskip("onnx")
    from markerpose.nets import WEIGHTS_DIR, stack_views, stacked_views_path

    with pytest.raises(ValueError, match="nothing to stack"):
        stack_views(WEIGHTS_DIR / "keypoints-det.onnx", tmp_path / "x.onnx")  # 16 channels from the first layer
    with pytest.raises(ValueError, match="already a stacked copy"):
        stack_views(stacked_views_path(WEIGHTS_DIR / "keypoints-mid-int8-det.onnx"), tmp_path / "y.onnx")


@needs_nets
@pytest.mark.parametrize("wide", [True, False])
def test_the_mid_network_stacks_the_views_on_cpus_with_avx512(monkeypatch, wide):
    """The mid network's shipped stacked copy runs the pair on CPUs with AVX-512 (or when
    asked); the fast network, whose first layer is 16 channels wide, has none and runs
    the views as a batch whatever the CPU."""
    monkeypatch.setattr(propose, "wide_vectors", lambda: wide)
    mid = {**propose.default_conf, "network": "mid"}
    stage = propose.NeuralProposer(mid, mp.Marker(), "stereo")
    assert stage.net.locator.stacked == wide
    forced = propose.NeuralProposer({**mid, "stack_views": True}, mp.Marker(), "stereo")
    assert forced.net.locator.stacked
    fast = propose.NeuralProposer({**propose.default_conf, "stack_views": True}, mp.Marker(), "stereo")
    assert propose.default_conf["network"] == "fast" and not fast.net.locator.stacked


def test_stack_views_setting_is_checked():
    with pytest.raises(ValueError, match="stack_views"):
        propose.check_conf({**propose.default_conf, "stack_views": "yes"})


_FORKED = {}


def _run_forked(x):
    return _FORKED["runner"](x)[0]


@needs_nets
def test_a_batch_split_over_two_sessions_is_the_batch_run_whole():
    """ONNX Runtime runs a batch as two halves at once: the outputs are those of each input
    alone, also in a process forked after the halves' thread started."""
    import multiprocessing

    from markerpose.nets import WEIGHTS_DIR, load_network

    runner = load_network(WEIGHTS_DIR / "ellipses.onnx", "ellipses", None, threads=2)[0]
    x = np.random.default_rng(1).random((5, 1, PATCH, PATCH), dtype=np.float32)
    whole = runner(x)[0]
    one = np.concatenate([runner(x[i : i + 1])[0] for i in range(5)])
    np.testing.assert_allclose(whole, one, atol=1e-5)
    _FORKED["runner"] = runner  # the child inherits it by the fork, not by pickling
    with multiprocessing.get_context("fork").Pool(1) as pool:
        forked = pool.apply(_run_forked, (x,))
    np.testing.assert_allclose(forked, whole, atol=1e-5)


def test_a_worker_asked_from_its_own_thread_runs_both_in_turn():
    """Worker.both from the worker's own thread (a fit that itself asks for two at once)
    runs both there rather than wait on itself."""
    from markerpose.threads import Worker

    worker = Worker()
    inner = worker.submit(lambda: worker.both(lambda: 1, lambda: 2)).result(timeout=10)
    assert inner == (1, 2) and worker.both(lambda: "a", lambda: "b") == ("a", "b")


@needs_nets
def test_a_pairs_views_go_from_image_to_candidates_each_on_its_own_half(rig, monkeypatch):
    """Where ONNX Runtime runs a batch as two halves, a pair's two views each go from their
    image to their candidates on one half (and one thread): the candidates are the batch's,
    at both looks."""
    net = kp.KeypointNet(propose.network_weights("fast"), stereo=True, threads=2)
    runner = net.locator if net.locator is not None else net.runner
    assert runner.halves is not None
    f = render_stereo(rig, look_at_pose([10, -20, 650], 30, 45, 20), imaging=Imaging(alpha=0.7), seed=9)
    views = [np.asarray(v) for v in f.images]
    ran = []
    counted = tuple((lambda x, h=h, j=j: ran.append(j) or h(x)) for j, h in enumerate(runner.halves))
    for zoom in (1.0, 2.0):
        ran.clear()
        monkeypatch.setattr(runner, "halves", counted)
        split = net.candidates(views, 0.01, 16, zoom)
        assert sorted(ran) == [0, 1]
        monkeypatch.setattr(runner, "halves", None)  # the batch, run whole
        batch = net.candidates(views, 0.01, 16, zoom)
        assert len(split) == 2 and all(len(c) >= 3 for c in split)
        for a, b in zip(split, batch):
            np.testing.assert_array_equal(a, b)


@needs_nets
def test_a_near_looks_windows_split_over_the_halves_give_the_batchs_candidates(rig, monkeypatch):
    """Stage 1 looking only near points: where the windows run as two halves, each half's
    windows are cut, run and decoded on its own thread; the candidates are those of the
    windows run as one batch."""
    net = kp.KeypointNet(propose.network_weights("fast"), stereo=True, threads=2)
    runner = net.locator if net.locator is not None else net.runner
    f = render_stereo(rig, look_at_pose([20, -15, 520], 30, 50, 70), imaging=Imaging(alpha=0.8), seed=31)
    grays = [np.ascontiguousarray(im) for im in f.images]
    near = [np.array([[640.0, 512.0], [300.0, 700.0]]), np.array([[600.0, 500.0]])]
    ran = []
    counted = tuple((lambda x, h=h, j=j: ran.append((j, len(x))) or h(x)) for j, h in enumerate(runner.halves))
    for zoom, window in ((1.0, 48), (2.0, 64)):
        ran.clear()
        monkeypatch.setattr(runner, "halves", counted)
        split = net.candidates(grays, 0.01, 16, zoom, near=near, window=window, kept=[])
        assert sorted(j for j, _ in ran) == [0, 1] and sum(n for _, n in ran) >= 3
        monkeypatch.setattr(runner, "halves", None)
        batch = net.candidates(grays, 0.01, 16, zoom, near=near, window=window, kept=[])
        assert len(split[0]) and all(np.array_equal(a, b) for a, b in zip(split, batch))
