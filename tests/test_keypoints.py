"""Stage 1: network shapes, training targets, decoding, and the shipped weights."""

import numpy as np
import pytest

import markerpose as mp
from markerpose import decode as dec
from markerpose import evidence as evidence_mod
from markerpose import geometry as geo
from markerpose import keypoints as kp
from markerpose.experiments.configs import build
from markerpose.nets import default_weights
from markerpose.train import keypoints as tk

torch = pytest.importorskip("torch")


# --- the network -------------------------------------------------------------------------
def _conv_widths(net):
    return [m.out_channels for m in net.encoder if isinstance(m, torch.nn.Conv2d)]


def test_paper_network_widths_and_shapes():
    """The paper's configuration: 64-64-64-64-128-128-128-128, three pools, 65 + 4 channels at H/8 x W/8."""
    net = kp.build_network(1.0).eval()
    assert _conv_widths(net) == [64, 64, 64, 64, 128, 128, 128, 128]
    assert sum(isinstance(m, torch.nn.MaxPool2d) for m in net.encoder) == 3
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.encoder) == 8
    with torch.inference_mode():
        det, ids = net(torch.zeros(2, 1, 240, 320))
    assert det.shape == (2, 65, 30, 40)
    assert ids.shape == (2, 4, 30, 40)


def test_width_option_scales_layers():
    net = kp.build_network(0.25)
    assert _conv_widths(net) == [16, 16, 16, 16, 32, 32, 32, 32]
    with torch.inference_mode():
        det, ids = net.eval()(torch.zeros(1, 1, 240, 320))
    assert det.shape[1:] == (65, 30, 40) and ids.shape[1:] == (4, 30, 40)


def test_stem_width_sets_the_first_four_convolutions_only():
    net = kp.build_network(0.5, stem_width=0.25)
    assert _conv_widths(net) == [16, 16, 16, 16, 64, 64, 64, 64]
    assert net.det_head[0].out_channels == 128 and net.id_head[0].out_channels == 128
    assert kp.layer_widths(0.25) == kp.layer_widths(0.25, None) == ((16, 16, 16, 16, 32, 32, 32, 32), 64)


@pytest.mark.parametrize("stem, second", [("strided", (3, 3)), ("pointwise", (1, 1))])
def test_strided_stems_halve_once_with_the_pooled_networks_shapes_and_keys(stem, second):
    """The strided stems: one 4x4 stride-2 convolution to twice the first width and a 3x3
    ("strided") or 1x1 ("pointwise") one to the second, no layer at full resolution; the
    same outputs' shapes, and every layer after the stem under the same key and shape as
    in the pooled network (what distillation copies from the teacher)."""
    pooled, strided = kp.build_network(0.375, 0.125), kp.build_network(0.375, 0.125, stem)
    convs = [m for m in strided.encoder if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs[:2]] == [
        (1, 16, (4, 4), (2, 2)),
        (16, 8, second, (1, 1)),
    ]
    assert _conv_widths(strided)[2:] == _conv_widths(pooled)[2:] == [8, 8, 48, 48, 48, 48]
    assert sum(isinstance(m, torch.nn.MaxPool2d) for m in strided.encoder) == 2
    with torch.inference_mode():
        x = torch.rand(2, 1, 256, 320)
        assert [t.shape for t in strided.eval()(x)] == [t.shape for t in pooled.eval()(x)]
        assert strided.encoder[:7](x).shape == pooled.encoder[:7](x).shape == (2, 8, 128, 160)
    a, b = pooled.state_dict(), strided.state_dict()
    differ = {k for k in b if k not in a or a[k].shape != b[k].shape}
    assert differ == {
        "encoder.0.weight",
        "encoder.1.weight",
        "encoder.1.bias",
        "encoder.1.running_mean",
        "encoder.1.running_var",
        "encoder.3.weight",
    }
    assert kp.network_for({"width": 0.375, "stem_width": 0.125}).stem == "pool"
    assert kp.network_for({"width": 0.375, "stem_width": 0.125, "stem": stem}).stem == stem
    with pytest.raises(ValueError, match="stem must be one of"):
        kp.build_network(0.375, stem="conv")


# --- targets and decoding ------------------------------------------------------------------
def _logits_from_targets(det, ids, sharp=20.0):
    """Ideal network outputs for given cell targets (ignored cells → background)."""
    d = np.where(det < 0, 64, det)
    i = np.where(ids < 0, 3, ids)
    det_logits = np.zeros((65,) + d.shape)
    id_logits = np.zeros((4,) + i.shape)
    yy, xx = np.mgrid[0 : d.shape[0], 0 : d.shape[1]]
    det_logits[d, yy, xx] = sharp
    id_logits[i, yy, xx] = sharp
    return det_logits, id_logits


MARKER_PTS = np.array([[100.3, 150.2], [140.7, 160.1], [88.2, 90.6]])  # c0, c1, c2: negative signed area


def test_targets_round_trip_through_decode():
    labels = np.ones(3, np.int8)
    det, ids = tk.make_targets(MARKER_PTS, labels)
    assert det.shape == (30, 40) and ids.shape == (30, 40)
    assert (det != 64).sum() == 3 and (ids != 3).sum() == 3
    pts, score = dec.decode(*_logits_from_targets(det, ids), {"ids": "head"})
    # The targets keep the nearest pixel; decoding returns it.
    np.testing.assert_allclose(pts, np.floor(MARKER_PTS + 0.5), atol=1e-6)
    assert score > 0.9


def test_targets_ignore_and_absent():
    det, ids = tk.make_targets(MARKER_PTS, np.array([1, -1, 0], np.int8))
    assert (det == -100).sum() == 1 and (ids == -100).sum() == 1
    assert (det < 64).sum() - (det == -100).sum() == 1  # only c0 is a target
    assert ids[int(MARKER_PTS[0, 1] + 0.5) // 8, int(MARKER_PTS[0, 0] + 0.5) // 8] == 0


def test_decode_repairs_colliding_ids():
    det, ids = tk.make_targets(MARKER_PTS, np.ones(3, np.int8))
    dl, il = _logits_from_targets(det, ids)
    # The ID head calls both c1 and c2 "c1", but is unsure about the c2 point.
    cy, cx = int(MARKER_PTS[2, 1] + 0.5) // 8, int(MARKER_PTS[2, 0] + 0.5) // 8
    il[:, cy, cx] = [0.0, 2.0, 1.5, -5.0]
    pts, _ = dec.decode(dl, il, {"ids": "head"})
    np.testing.assert_allclose(pts, np.floor(MARKER_PTS + 0.5), atol=1e-6)


def _point_logits(points):
    """Network outputs with a sharp peak at each of three points (network-input px) and
    no ID information: the decoder must name the rings by the layout."""
    det, _ = tk.make_targets(points, np.ones(3, np.int8))
    dl = np.zeros((65, 30, 40))
    dl[64] = 10.0
    cy, cx = np.nonzero(det != 64)
    dl[det[cy, cx], cy, cx] = 20.0
    return dl, np.zeros((4, 30, 40))


def _view(tilt_deg: float, tilt_axis_deg: float, roll_deg: float, dist: float = 600.0, f: float = 300.0):
    """Ring centres of the default marker seen by a pinhole camera (y down), marker facing it."""

    def rot(axis, a):
        a = np.radians(a)
        c, s = np.cos(a), np.sin(a)
        k = np.asarray(axis, float) / np.linalg.norm(axis)
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + s * K + (1 - c) * K @ K

    ax = [np.cos(np.radians(tilt_axis_deg)), np.sin(np.radians(tilt_axis_deg)), 0]
    R = rot([1, 0, 0], 180) @ rot(ax, tilt_deg) @ rot([0, 0, 1], roll_deg)  # face the camera (-z)
    X = (R @ np.column_stack([mp.Marker().centers2d - [10, 20], np.zeros(3)]).T).T + [0, 0, dist]
    return f * X[:, :2] / X[:, 2:] + [160, 120]


def test_layout_ratio_tells_the_rings_apart():
    """The marker's shape picks the right ID order among the three with the right
    handedness, from frontal views to 55° of tilt about any axis, at any roll."""
    layout = mp.Marker().centers2d
    for tilt in (0, 30, 55):
        for axis in (0, 45, 90, 135):
            for roll in (0, 100, 230):
                p = _view(tilt, axis, roll)
                assert geo.signed_area(p) < 0
                right = geo.layout_ratio(p, layout)
                wrong = [geo.layout_ratio(p[np.roll([0, 1, 2], k)], layout) for k in (1, 2)]
                assert right > 0.5  # cos 55° = 0.57, less perspective
                assert max(wrong) < right, (tilt, axis, roll, right, wrong)
    assert abs(geo.layout_ratio(_view(0, 0, 40), layout) - 1.0) < 1e-3


def test_decode_by_layout_needs_no_id_head():
    """With ids="layout" an uninformative ID head still gives the right order; with the
    paper's ids="head" it gives nothing."""
    p = _view(35, 60, 290)
    det, ids = tk.make_targets(p, np.ones(3, np.int8))
    dl, il = _logits_from_targets(det, ids)
    il[:] = 0.0  # the ID head says nothing
    pts, _ = dec.decode(dl, il, {"ids": "layout"})
    np.testing.assert_allclose(pts, np.floor(p + 0.5), atol=1e-6)
    assert dec.decode(dl, il, {"ids": "head", "min_id_prob": 0.3}) is None
    with pytest.raises(ValueError, match="ids"):
        dec.decode(dl, il, {"ids": "magic"})


def test_steep_marker_is_not_scored_down_to_its_ratio():
    """Layout IDs: a marker tilted by ~60° (layout ratio ~0.45) keeps its ID order and
    scores min(1, ratio / ratio_full) of a frontal view, not the ratio itself (v0.12)."""
    p = _view(62, 30, 100, dist=250.0)
    r = geo.layout_ratio(p, mp.Marker().centers2d)
    assert 0.35 < r < 0.5
    det, ids = tk.make_targets(p, np.ones(3, np.int8))
    dl, il = _logits_from_targets(det, ids)
    soft, old = dec.decode(dl, il, {"ids": "layout"}), dec.decode(dl, il, {"ids": "layout", "ratio_full": None})
    np.testing.assert_allclose(soft[0], np.floor(p + 0.5), atol=1e-6)
    np.testing.assert_array_equal(soft[0], old[0])
    assert soft[1] / old[1] == pytest.approx(min(1.0, r / dec.default_conf["ratio_full"]) / r, rel=1e-3)


def test_decode_by_layout_rejects_wrong_shapes():
    """Three ring-like points in a line or in the mirror image are not the marker."""
    det, ids = tk.make_targets(np.array([[100.0, 100.0], [130.0, 100.0], [160.0, 101.0]]), np.ones(3, np.int8))
    assert dec.decode(*_logits_from_targets(det, ids), {"ids": "layout"}) is None
    mirrored = MARKER_PTS.copy()
    mirrored[:, 0] = 319 - mirrored[:, 0]
    det, ids = tk.make_targets(mirrored, np.ones(3, np.int8))
    assert dec.decode(*_logits_from_targets(det, ids), {"ids": "layout"}) is None


def test_decode_rejects_mirror_image_and_empty():
    mirrored = MARKER_PTS.copy()
    mirrored[:, 0] = 319 - mirrored[:, 0]
    assert geo.signed_area(MARKER_PTS) < 0 < geo.signed_area(mirrored)
    det, ids = tk.make_targets(mirrored, np.ones(3, np.int8))
    assert dec.decode(*_logits_from_targets(det, ids)) is None
    det, ids = tk.make_targets(MARKER_PTS, np.zeros(3, np.int8))
    assert dec.decode(*_logits_from_targets(det, ids)) is None
    det, ids = tk.make_targets(MARKER_PTS, np.array([1, 1, 0], np.int8))
    assert dec.decode(*_logits_from_targets(det, ids)) is None  # two rings are not a marker


def test_nms_keeps_separated_maxima():
    s = np.zeros((40, 60))
    s[10, 10], s[10, 12], s[30, 50] = 0.9, 0.8, 0.5
    out = dec.nms(s, radius=4, threshold=0.1, k=5)
    np.testing.assert_array_equal(out[:, :2], [[10, 10], [50, 30]])


def test_nms_breaks_ties_in_the_maps_order_and_keeps_a_zero_plateaus_peak():
    """Equal maxima come best first in the map's row-major order (a stable sort, whatever
    their number); a peak on a plateau of zeros (threshold 0) stays where it is."""
    s = np.zeros((60, 200), np.float32)
    s[5::10, 5::10] = 0.5  # 120 equal maxima
    s[33, 77] = 0.5
    out = dec.nms(s, 2, 0.1, 200)
    ys, xs = np.nonzero(s >= 0.5)
    np.testing.assert_array_equal(out[:, :2], np.c_[xs, ys])
    assert dec._refine(np.zeros((8, 8), np.float32), np.array([[3.0, 4.0, 0.0]])).tolist() == [[3.0, 4.0, 0.0]]


def test_peaks_of_a_batch_are_each_images_candidates_at_their_3x3_centroids():
    """decode.peaks (one softmax for a batch) gives what candidates gives image by image,
    each peak at the score-weighted centroid of its 3x3 neighbourhood inside the map
    (read directly here), also at the map's border."""
    rng = np.random.default_rng(4)
    det = rng.normal(0, 1, (3, 65, 6, 8)).astype(np.float32)
    det[:, 64] += 2.0
    det[0, 0, 0, 0] = det[1, 63, 5, 7] = det[2, 27, 2, 3] = 9.0  # peaks in a corner, the far corner, inside
    ids = np.zeros((3, 4, 6, 8), np.float32)
    found = dec.peaks(det, 0.01, 5, 2)
    for b in range(3):
        cand, _ = dec.candidates(det[b], ids[b], 0.01, 5, 2)
        np.testing.assert_array_equal(found[b], cand)
        scores = dec.score_map(det[b])
        peaks = dec.nms(scores, 2, 0.01, 5)
        assert len(peaks) == len(cand) > 0
        for (x, y, sc), got in zip(peaks, cand):
            ys, xs = np.mgrid[max(int(y) - 1, 0) : int(y) + 2, max(int(x) - 1, 0) : int(x) + 2]
            ys, xs = ys[(ys < scores.shape[0]) & (xs < scores.shape[1])], xs[(ys < scores.shape[0]) & (xs < scores.shape[1])]
            w = scores[ys, xs].astype(np.float64)
            np.testing.assert_allclose(got, [(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum(), sc], rtol=1e-12)


def test_default_nms_keeps_the_close_rings_of_a_steep_marker():
    """A steeply tilted marker can put two ring centres ~3-6 input px apart: the default
    decoding radius keeps both maxima (v0.8's radius of 4 kept one)."""
    s = np.zeros((40, 60))
    s[10, 10], s[10, 13] = 0.9, 0.8
    r = dec.default_conf["nms_radius"]
    np.testing.assert_array_equal(dec.nms(s, r, 0.1, 5)[:, :2], [[10, 10], [13, 10]])
    assert len(dec.nms(s, 4, 0.1, 5)) == 1


def test_input_and_full_resolution_mapping():
    gray = np.zeros((1024, 1280), np.uint8)
    gray[500:520, 600:640] = 255
    x, scale = kp.to_input(gray)
    assert x.shape == (240, 320) and x.dtype == np.float32 and x.max() <= 1.0
    np.testing.assert_allclose(scale, [4.0, 1024 / 240])
    # Pixel centres: input pixel (0, 0) covers full pixels 0..3 → centre 1.5.
    np.testing.assert_allclose(kp.to_full(np.array([[0.0, 0.0]]), scale)[0], [1.5, (1024 / 240 - 1) / 2])


def test_missing_weights_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="weights not found"):
        kp.KeypointNet(tmp_path / "nope.pt")
    torch.save({"foo": 1}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="state_dict"):
        kp.KeypointNet(tmp_path / "bad.pt")


# --- the shipped weights on rendered views ------------------------------------------------------
shipped = pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped stage-1 weights")


@shipped
def test_shipped_network_output_is_none_or_right():
    """The shipped stage 1 returns, per view, None or three centres within 8 px by ID
    (its detection rate is reported by `markerpose eval keypoints`, not asserted here)."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    net = kp.KeypointNet()
    assert set(net.conf) >= {"threshold", "min_score", "min_id_prob", "width", "ids"}
    views = [
        render_view(rig.left, look_at_pose([x, -10, 550], 35, 60, r), imaging=Imaging(alpha=0.5), seed=4)
        for x, r in ((20, 130), (0, 10), (-30, 250))
    ]
    empty = np.full_like(views[0][0], 90)
    *found, nothing = net([v[0] for v in views] + [empty])
    assert nothing is None
    for f, (_, truth) in zip(found, views):
        assert f is None or np.linalg.norm(f[0] - truth.centers, axis=1).max() < 8.0


@shipped
def test_neural_pipeline_is_none_or_right():
    from markerpose.synth import Imaging, look_at_pose, render_stereo

    rig = mp.StereoRig.default()
    tracker = build("neural-classical-refine", rig)
    coarse = mp.MarkerPose(rig, refine={"method": "none"})
    for seed, (x, tilt, roll) in enumerate(((10, 25, 200), (-20, 10, 30), (30, 40, 100))):
        T = look_at_pose([x, 5, 520], tilt, 10, roll)
        frame = render_stereo(rig, T, imaging=Imaging(alpha=0.7), seed=11 + seed)
        est = tracker.estimate(*frame.images)
        assert est is None or np.linalg.norm(est.t - T[:3, 3]) < 0.1  # mm
        est = coarse.estimate(*frame.images)
        assert est is None or np.linalg.norm(est.t - T[:3, 3]) < 10.0
        assert set(tracker.timings) >= {"propose", "match", "refine", "verify", "solve", "total"}
    assert tracker.estimate(np.full_like(frame.images[0], 80), frame.images[1]) is None


def test_candidate_recall_separates_finding_from_labelling():
    from markerpose.train.keypoints import candidate_recall

    p = _view(20, 0, 30)
    det, ids = tk.make_targets(p, np.ones(3, np.int8))
    dl, il = _logits_from_targets(det, ids)
    data = {"points": p[None].astype(np.float32), "labels": np.ones((1, 3), np.int8), "scale": np.ones((1, 2), np.float32)}
    r = candidate_recall(dl[None], il[None], data, {})
    assert r == {"candidates_found": 1.0, "id_head_right": 1.0}
    il[:] = 0.0  # found, but the ID head cannot tell the rings apart
    assert candidate_recall(dl[None], il[None], data, {})["id_head_right"] == 0.0
    dl[:] = 0.0  # nothing stands out: no candidate above the threshold
    dl[64] = 10.0
    assert candidate_recall(dl[None], il[None], data, {})["candidates_found"] == 0.0


def _save_kp(path, decode, width=0.25, **extra):
    """A stage-1 weights file as ``markerpose train keypoints --export`` writes it."""
    from markerpose.nets import FORMAT

    torch.save(
        {
            "format": {"network": "keypoints", "version": FORMAT},
            "state_dict": kp.build_network(width).state_dict(),
            "width": width,
            "decode": decode,
            **extra,
        },
        path,
    )


def test_operating_points_from_the_checkpoint(tmp_path):
    """Thresholds tuned at export: per ID mode, single-view or stereo; the caller's win."""
    path = tmp_path / "kp.pt"
    decode = {"layout": {"min_score": 0.5}, "layout_stereo": {"min_score": 0.2}, "head": {"min_score": 0.6}}
    _save_kp(path, decode)
    assert kp.KeypointNet(path).conf["min_score"] == 0.5
    assert kp.KeypointNet(path, stereo=True).conf["min_score"] == 0.2
    assert kp.KeypointNet(path, {"ids": "head"}, stereo=True).conf["min_score"] == 0.6  # no stereo point: single-view
    assert kp.KeypointNet(path, {"min_score": 0.1}, stereo=True).conf["min_score"] == 0.1
    assert kp.KeypointNet(path, {"ratio_full": 0.6}).conf["ratio_full"] == 0.6
    with pytest.raises(ValueError, match="ids"):
        kp.KeypointNet(path, {"ids": "nope"})


def test_weight_files_that_cannot_work_fail_at_load(tmp_path):
    """Every broken or foreign weights file is a ValueError naming the file, at load."""
    from markerpose.ellipses import EllipseNet
    from markerpose.ellipses import build_network as es_net
    from markerpose.nets import FORMAT

    good = tmp_path / "good.pt"
    _save_kp(good, {})
    raw = good.read_bytes()
    cases = {
        "empty.pt": (b"", "not a readable PyTorch weights file"),
        "truncated.pt": (raw[: len(raw) // 2], "not a readable PyTorch weights file"),
        "random.pt": (np.random.default_rng(0).bytes(4096), "not a readable PyTorch weights file"),
    }
    for name, (data, match) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=match):
            kp.KeypointNet(tmp_path / name)
    other = tmp_path / "ellipses.pt"  # the other network's file
    torch.save({"format": {"network": "ellipses", "version": FORMAT}, "state_dict": es_net().state_dict()}, other)
    with pytest.raises(ValueError, match="not a markerpose keypoints weights file of format"):
        kp.KeypointNet(other)
    with pytest.raises(ValueError, match="not a markerpose ellipses weights file of format"):
        EllipseNet(good)
    wide = tmp_path / "wide.pt"  # weights of another width than the file says
    _save_kp(wide, {}, width=0.25)
    ck = torch.load(wide, weights_only=True)
    ck["width"] = 0.5
    torch.save(ck, wide)
    with pytest.raises(ValueError, match="the weights do not fit the network"):
        kp.KeypointNet(wide)
    old = tmp_path / "old.pt"  # exported before the format entry: its thresholds are not trusted
    torch.save({"state_dict": kp.build_network(0.25).state_dict(), "width": 0.25, "decode": {}}, old)
    with pytest.raises(ValueError, match="without a format entry"):
        kp.KeypointNet(old)
    zipped = tmp_path / "list.pt"  # a readable file that is not a dict
    torch.save([1, 2, 3], zipped)
    with pytest.raises(ValueError, match="holds a list"):
        kp.KeypointNet(zipped)
    # The shipped files pass.
    assert kp.KeypointNet().conf["width"] > 0 and EllipseNet() is not None


def test_second_look_runs_only_where_nothing_was_found(tmp_path, monkeypatch):
    """second_look=2: views without a marker go through the network again at 640x480,
    with the tuned look threshold; a zoom below 1 is an error."""
    path = tmp_path / "kp.pt"
    decode = {"layout": {}, "layout_verify": {"min_score": 0.05}, "layout_verify_look": {"look_min_score": 0.3}}
    _save_kp(path, decode)
    assert kp.KeypointNet(path, {"verify": True}).conf["look_min_score"] is None
    net = kp.KeypointNet(path, {"verify": True, "second_look": 2.0})
    assert net.conf["look_min_score"] == 0.3 and net.conf["min_score"] == 0.05
    assert kp.look_conf(net.conf)["min_score"] == 0.3
    with pytest.raises(ValueError, match="second_look"):
        kp.KeypointNet(path, {"second_look": 0.5})
    shapes = []

    def nothing(batch):  # every cell "no centre": no candidate, no marker
        shapes.append(batch.shape)
        hc, wc = batch.shape[1] // dec.CELL, batch.shape[2] // dec.CELL
        det = np.zeros((len(batch), 65, hc, wc), np.float32)
        det[:, 64] = 20.0
        return det, np.zeros((len(batch), 4, hc, wc), np.float32)

    monkeypatch.setattr(net, "logits", nothing)
    imgs = [np.full((1024, 1280), 90, np.uint8), np.full((960, 1280), 60, np.uint8)]
    assert net(imgs) == [None, None]
    assert shapes == [(2, 240, 320), (2, 480, 640)]
    shapes.clear()
    net.conf["second_look"] = 1.0
    assert net(imgs) == [None, None] and shapes == [(2, 240, 320)]


def test_look_again_maps_the_zoomed_points_back(monkeypatch):
    """eval keypoints' second look: only the views without a result, enlarged, points
    mapped back to the 320x240 input."""
    from markerpose.train import keypoints as tk

    seen = {}

    def fake_logits(net, images, batch=32, device="cpu"):
        seen["shape"] = images.shape
        return np.zeros((len(images), 65, 1, 1)), np.zeros((len(images), 4, 1, 1))

    zoomed = np.array([[101.0, 41.0], [141.0, 41.0], [101.0, 121.0]])
    monkeypatch.setattr(tk, "logits", fake_logits)
    monkeypatch.setattr(tk, "decode_all", lambda det, ids, images, conf, desc=None: [(zoomed, conf["min_score"])] * len(det))
    images = np.zeros((3, 240, 320), np.uint8)
    first = [(np.zeros((3, 2)), 0.9), None, None]
    out = tk.look_again(None, images, first, {"second_look": 2.0, "min_score": 0.1, "look_min_score": 0.4})
    assert seen["shape"] == (2, 480, 640)
    assert out[0] is first[0]
    np.testing.assert_allclose(out[1][0], [[50.25, 20.25], [70.25, 20.25], [50.25, 60.25]])
    assert out[2][1] == 0.4  # decoded with the look threshold
    assert tk.look_again(None, images, first, {"second_look": 1.0}) == first
    # A shared cache: the network runs only on views it has not seen at this zoom.
    cache: dict = {}
    tk.look_again(None, images, [first[0], first[0], None], {"second_look": 2.0, "min_score": 0.1}, zoomed=cache)
    assert seen["shape"] == (1, 480, 640) and set(cache) == {2}
    out = tk.look_again(None, images, first, {"second_look": 2.0, "min_score": 0.1}, zoomed=cache)
    assert seen["shape"] == (1, 480, 640) and set(cache) == {1, 2}  # only view 1 was new
    assert out[1] is not None and out[2] is not None


@shipped
def test_second_look_finds_a_distant_marker():
    """A marker 2.3 m from the default rig (rings ~22 px wide at full resolution, ~5 px
    at 320x240): the second look at 640x480 finds it, centres within 3 px."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    net = kp.KeypointNet(conf={"verify": True, "second_look": 2.0})
    for k, (x, tilt, roll) in enumerate(((0, 20, 40), (60, 35, 200))):
        img, truth = render_view(rig.left, look_at_pose([x, 20, 2300], tilt, 30, roll), imaging=Imaging(alpha=0.6), seed=k)
        (found,) = net([img])
        assert found is not None and np.linalg.norm(found[0] - truth.centers, axis=1).max() < 3.0


# --- ring evidence (verify) ------------------------------------------------------------------
def test_ring_evidence_tells_the_printed_marker_from_ring_decoys(drawn_rings):
    """The marker's triple (black bands on one white plate) scores high; the same triangle
    of rings drawn straight on a dark background (no plate), a triple whose order puts the
    rings' sizes wrong, and a triple over plain clutter score low."""
    import cv2

    m = mp.Marker()
    s = 2.0  # px per mm, rotated by 25°, placed at (90, 130); y flips (image y points down)
    a = np.deg2rad(25)
    A = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.diag([1.0, -1.0])
    to_img = lambda q: np.asarray(q) @ A.T + [90, 130]  # noqa: E731
    img = np.full((240, 320), 0.25, np.float32)
    x0, y0, x1, y1 = m.plate
    cv2.fillConvexPoly(img, np.round(to_img([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) * 16).astype(np.int32), 0.85, cv2.LINE_AA, shift=4)
    marker = to_img(m.centers2d)
    drawn_rings(img, marker, m.outer_radius * s, m.inner_radius * s, 0.08, 0.85)
    decoys = marker + [170, 80]  # the same triangle of rings, but on the dark background
    drawn_rings(img, decoys, m.outer_radius * s, m.inner_radius * s, 0.05, 0.8)
    rng = np.random.default_rng(0)
    img = np.clip(img + rng.normal(0, 0.01, img.shape), 0, 1).astype(np.float32)
    ev = evidence_mod.ring_evidence(img, np.stack([marker, decoys, marker[[0, 2, 1]], marker + [180, -40]]), m)
    assert ev.shape == (4,) and np.all((ev >= 0) & (ev <= 1))
    assert ev[0] > 0.6, ev
    assert ev[1] < 0.2 and ev[3] < 0.2 and ev[2] < ev[0] / 2, ev
    # Decoding: the decoys score higher in the network; with verify the marker wins.
    dl = np.zeros((65, 30, 40))
    dl[64] = 10.0
    for pts, logit in ((marker, 12.0), (decoys, 20.0)):
        det, _ = tk.make_targets(pts, np.ones(3, np.int8))
        cy, cx = np.nonzero(det != 64)
        dl[det[cy, cx], cy, cx] = logit
    il = np.zeros((4, 30, 40))  # an ID head that says nothing
    no, yes = ({"ids": "layout", "verify": v, "min_score": 0.0} for v in (False, True))
    assert np.abs(dec.decode(dl, il, no)[0] - marker).max() > 20  # a triple with decoys in it
    np.testing.assert_allclose(dec.decode(dl, il, yes, m, img)[0], np.floor(marker + 0.5), atol=1e-3)
    with pytest.raises(ValueError, match="image"):
        dec.decode(dl, il, {"verify": True})


# --- alignment (ours) ----------------------------------------------------------------------
@pytest.mark.parametrize("alpha, blur, tilt, z", [(0.5, 0.0, 40, 550), (0.0625, 0.0, 60, 400), (0.5, 15.0, 10, 750)])
def test_align_triple_refines_centres_a_pixel_off(alpha, blur, tilt, z):
    """Three centres 1.35 network-input px off (what stage 1's cells leave) come back
    within 0.15 px of the projected truth — bright, dark, blurred, steep."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([20, -10, z], tilt, 60, 130), imaging=Imaging(alpha=alpha, motion_blur=blur), seed=4)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    start = gt + np.random.default_rng(1).uniform(-1.35, 1.35, (3, 2))
    q, cc = dec.align_triple(small, start)
    assert cc is not None and cc > 0.9
    assert np.linalg.norm(q - gt, axis=1).max() < 0.15


def test_align_move_rule_nearest_keeps_a_point_off_towards_its_neighbour():
    """A small, steep marker whose stage-1 point is ~2.5 input px off towards a neighbour
    (closer than 0.4 of the shrunken distance between the points allows): "spacing"
    drops the right alignment, "nearest" keeps it, within 0.3 px of the truth."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([0, 0, 700], 55, 60, 20), imaging=Imaging(alpha=0.6, motion_blur=5.0), seed=3)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    spacing = dec._min_spacing(gt)
    a, b = min(((0, 1), (0, 2), (1, 2)), key=lambda ab: np.linalg.norm(gt[ab[0]] - gt[ab[1]]))
    start = gt.copy()
    start[a] += 0.42 * (gt[b] - gt[a])  # towards its nearest neighbour
    assert 0.42 * spacing > 0.4 * dec._min_spacing(start)  # "spacing" must drop the right alignment
    q, cc = dec.align_triple(small, start, move_rule="spacing")
    assert cc is None and np.array_equal(q, start)
    q, cc = dec.align_triple(small, start, move_rule="nearest")
    assert cc is not None and cc > 0.9
    assert np.linalg.norm(q - gt, axis=1).max() < 0.3
    with pytest.raises(ValueError, match="move_rule"):
        dec.align_triple(small, start, move_rule="nope")


def test_align_triple_gives_up_cleanly():
    """No marker to align to, or a degenerate start: the points come back unchanged with None."""
    pts = np.array([[100.0, 120.0], [130.0, 120.0], [100.0, 72.0]])
    for image, start in ((np.full((240, 320), 0.4, np.float32), pts), (np.zeros((240, 320), np.float32), np.zeros((3, 2)))):
        q, cc = dec.align_triple(image, start)
        assert cc is None and np.array_equal(q, start)


def test_decode_with_align_needs_the_image_and_refines():
    """decode(align=True) raises without the image; with it, a triple the network puts
    on its cells comes back refined onto the rings."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([0, 0, 500], 30, 60, 40), imaging=Imaging(alpha=0.5), seed=2)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    dl, il = _point_logits(np.round(gt))  # centres on whole pixels
    conf = {"ids": "layout", "verify": True, "min_score": 0.0, "align": True}
    with pytest.raises(ValueError, match="align"):
        dec.decode(dl, il, {**conf, "verify": False})
    plain = dec.decode(dl, il, {**conf, "align": False}, image=small)
    aligned = dec.decode(dl, il, conf, image=small)
    e_plain = np.linalg.norm(plain[0] - gt, axis=1).max()
    e_aligned = np.linalg.norm(aligned[0] - gt, axis=1).max()
    assert e_aligned < 0.15 < e_plain, (e_plain, e_aligned)


def test_align_recovers_a_steep_triple_whose_ratio_the_cells_put_under_min_ratio():
    """A blurred marker tilted by 66° (layout ratio 0.41) whose stage-1 points, ~2 px off,
    have a ratio of 0.34 < min_ratio: v0.13's decoding (align_min_ratio None) finds
    nothing; v0.14's lets the triple in, aligns it and keeps it at its true ratio."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([10, 0, 450], 66, 60, 20), imaging=Imaging(alpha=0.5, motion_blur=10.0), seed=2)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    start = np.round(gt + np.random.default_rng(0).uniform(-2, 2, (3, 2)))
    layout = mp.Marker().centers2d
    assert geo.layout_ratio(start, layout) < dec.default_conf["min_ratio"] <= geo.layout_ratio(gt, layout)
    dl, il = _point_logits(start)
    conf = {"ids": "layout", "verify": True, "align": True, "min_score": 0.01}  # not the same points in a wrong order
    assert dec.decode(dl, il, {**conf, "align_min_ratio": None}, image=small) is None
    found = dec.decode(dl, il, conf, image=small)
    assert found is not None and np.linalg.norm(found[0] - gt, axis=1).max() < 0.2
    assert geo.layout_ratio(found[0], layout) >= dec.default_conf["min_ratio"]
    # Without alignment the loose ratio does not apply.
    assert dec.decode(dl, il, {**conf, "align": False}, image=small) is None


def test_align_tries_the_other_orders_of_a_steep_triple():
    """A blurred marker tilted by 68° whose stage-1 points, ~2 px off, make a wrong ID
    order the most marker-like one: aligning each triple in its best order alone
    (align_orders 1, v0.14) finds nothing; aligning its three orders finds the marker
    to within 0.3 px, in the right order."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([10, 0, 600], 68, 0, 20), imaging=Imaging(alpha=0.7, motion_blur=8.0), seed=2)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    start = np.round(gt + np.random.default_rng(1).uniform(-2.5, 2.5, (3, 2)))
    dl, il = _point_logits(start)
    conf = {"ids": "layout", "verify": True, "align": True, "min_score": 0.01}
    assert dec.decode(dl, il, {**conf, "align_orders": 1}, image=small) is None
    found = dec.decode(dl, il, {**conf, "align_orders": 3}, image=small)
    assert found is not None and np.linalg.norm(found[0] - gt, axis=1).max() < 0.3


def test_align_cc_power_scales_the_aligned_score_by_the_correlation():
    """align_cc_power p: the aligned triple's score times its ECC correlation to the p
    (0: unchanged), the points unchanged."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([0, 0, 500], 40, 30, 10), imaging=Imaging(alpha=0.5), seed=3)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    dl, il = _point_logits(np.round(gt))
    conf = {"ids": "layout", "verify": True, "align": True, "min_score": 0.0, "align_cc_power": 0}
    plain = dec.decode(dl, il, conf, image=small)
    squared = dec.decode(dl, il, {**conf, "align_cc_power": 2}, image=small)
    cand, _ = dec.candidates(dl, il, dec.default_conf["threshold"], 10, dec.default_conf["nms_radius"])
    start = cand[:, :2][np.argmin(np.linalg.norm(cand[:, None, :2] - gt[None], axis=2), axis=0)]
    _, cc = dec.align_triple(small, start)
    assert cc is not None and 0.5 < cc < 1
    np.testing.assert_allclose(squared[0], plain[0])
    assert squared[1] == pytest.approx(plain[1] * cc**2, rel=1e-9)


def test_tuned_key_names_the_alignment():
    assert kp.tuned_key("layout", True, True, True) == "layout_verify_align_stereo"
    assert kp.tuned_key("layout", True) == "layout_verify"


# --- every triple in every order, at once --------------------------------------------------
def test_triple_orders_cover_every_ordered_triple_once():
    import itertools

    idx = geo.triple_orders(5)
    assert idx.shape == (60, 3)
    assert [tuple(r) for r in idx] == [p for t in itertools.combinations(range(5), 3) for p in itertools.permutations(t)]
    assert geo.triple_orders(2).shape == (0, 3)


def _decode_by_loop(det, ids, conf, image=None):
    """The decoding's choice of triple written as a plain loop over triples and orders
    (``align`` off): the reference the vectorised :func:`dec.decode` must agree with.
    Each triple's ID order is the one with the best score using the layout ratio itself;
    the triples compete with the ratio softened by ``ratio_full`` (layout IDs)."""
    import itertools

    c = {**dec.default_conf, **conf}
    cand, prob = dec.candidates(det, ids, c["threshold"], c["max_candidates"], c["nms_radius"])
    best = None
    for trio in itertools.combinations(range(len(cand)), 3):
        order = None  # (points, score with the ratio, score with the softened ratio)
        for perm in itertools.permutations(trio):
            perm = list(perm)
            p, p_id = cand[perm, :2], prob[perm, [0, 1, 2]]
            if geo.signed_area(p) >= 0:
                continue
            if c["ids"] == "head":
                if p_id.min() < c["min_id_prob"]:
                    continue
                s = np.prod(cand[perm, 2] * p_id) ** (1 / 3)
                r = soft = 1.0
            else:
                r = geo.layout_ratio(p, mp.Marker().centers2d)
                if r < c["min_ratio"]:
                    continue
                s = np.prod(cand[perm, 2]) ** (1 / 3) * np.prod(p_id) ** (c["id_weight"] / 3)
                soft = r if c["ratio_full"] is None else min(1.0, r / c["ratio_full"])
            if c["verify"]:
                s *= evidence_mod.plate_evidence(image, p[None])[0]
            if order is None or s * r > order[1]:
                order = (p, s * r, s * soft)
        if order is not None and (best is None or order[2] > best[1]):
            best = (order[0], order[2])
    return None if best is None or best[1] < c["min_score"] else best


@pytest.mark.parametrize(
    "conf",
    [
        {"ids": "head", "min_id_prob": 0.05},
        {"ids": "layout"},
        {"ids": "layout", "ratio_full": None},
        {"ids": "layout", "verify": True},
        {"ids": "layout", "verify": True, "ratio_full": None},
    ],
)
def test_decode_agrees_with_a_loop_over_triples(conf):
    rng = np.random.default_rng(3)
    image = rng.uniform(0, 1, (240, 320)).astype(np.float32)
    agreed = found = 0
    for _ in range(12):
        det = rng.normal(0, 3, (65, 30, 40))
        det[64] += 6.0  # mostly "no centre", a few dozen peaks
        ids = rng.normal(0, 1, (4, 30, 40))
        conf_ = {**conf, "threshold": 0.02, "min_score": 0.0}
        a, b = dec.decode(det, ids, conf_, image=image), _decode_by_loop(det, ids, conf_, image)
        assert (a is None) == (b is None)
        if a is not None:
            found += 1
            agreed += int(np.array_equal(a[0], b[0]) and np.isclose(a[1], b[1], rtol=1e-12))
    assert found >= 6 and agreed == found


def test_decode_all_gives_the_same_with_worker_processes():
    """The export's and evaluation's decoding split over processes returns what one
    process returns, view by view and in order (ring evidence and alignment on)."""
    from markerpose.train import keypoints as tk

    rng = np.random.default_rng(5)
    n = 2 * tk._DECODE_CHUNK + 7
    det = rng.normal(0, 3, (n, 65, 30, 40))
    det[:, 64] += 6.0
    ids = rng.normal(0, 1, (n, 4, 30, 40))
    images = rng.integers(0, 256, (n, 240, 320), dtype=np.uint8)
    conf = {"ids": "layout", "verify": True, "align": True, "threshold": 0.02, "min_score": 0.0}
    one, two = (tk.decode_all(det, ids, images, conf, workers=w) for w in (1, 2))
    assert len(one) == len(two) == n and sum(o is not None for o in one) >= n // 2
    for a, b in zip(one, two):
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a[0], b[0]) and a[1] == b[1]


def test_align_skips_triples_that_cannot_reach_min_score(monkeypatch):
    """A triple whose network score is under min_score is not aligned (alignment, the
    correlation and the evidence only scale a score down), and the result is what
    decoding at min_score 0 and thresholding afterwards gives."""
    from markerpose.synth import Imaging, look_at_pose, render_view

    rig = mp.StereoRig.default()
    img, truth = render_view(rig.left, look_at_pose([0, 0, 500], 30, 60, 40), imaging=Imaging(alpha=0.5), seed=2)
    small, scale = kp.to_input(img)
    gt = (truth.centers + 0.5) / scale - 0.5
    dl, il = _point_logits(np.round(gt))
    det, _ = tk.make_targets(np.round(gt) + [150, 0], np.ones(3, np.int8))  # a weaker ghost of the triangle
    cy, cx = np.nonzero(det != 64)
    dl[det[cy, cx], cy, cx] = 8.0  # location score ~0.12 against ~1
    calls = []
    real = dec.align_triple
    monkeypatch.setattr(dec, "align_triple", lambda *a, **k: calls.append(1) or real(*a, **k))
    conf = {"ids": "layout", "verify": True, "align": True, "align_top": 3}
    every = dec.decode(dl, il, {**conf, "min_score": 0.0}, image=small)
    n_all = len(calls)
    calls.clear()
    floor = 0.5  # above the ghost's score, under the marker's
    kept = dec.decode(dl, il, {**conf, "min_score": floor}, image=small)
    assert every is not None and every[1] >= floor and n_all == 3 and 1 <= len(calls) < n_all
    np.testing.assert_array_equal(kept[0], every[0])
    assert kept[1] == every[1]
    calls.clear()
    assert dec.decode(dl, il, {**conf, "min_score": 1.01}, image=small) is None and not calls
