"""Training data (scenes, augmentations), metrics and the stage-1 training loop."""

import json

import numpy as np
import pytest

from markerpose.train import augment as aug
from markerpose.train import scenes


def test_scene_sample_is_deterministic_and_labelled():
    a = scenes.sample(np.random.default_rng(3), negative=False, conf={"inside": True, "p_occlude": 0.0})
    b = scenes.sample(np.random.default_rng(3), negative=False, conf={"inside": True, "p_occlude": 0.0})
    np.testing.assert_array_equal(a.image, b.image)
    assert a.image.shape == (240, 320) and a.image.dtype == np.uint8
    assert a.points.shape == (3, 2) and a.labels.shape == (3,)
    vis = a.labels == 1
    assert vis.any()
    assert np.all((a.points[vis] >= 0) & (a.points[vis] <= [319, 239]))
    # Ink where a labelled centre's ring is: the ring band is darker than its white centre's
    # surroundings on average (a loose check that labels and pixels agree).
    assert a.scale.shape == (2,) and np.all(a.scale >= 2)


def test_negative_sample_has_no_marker():
    s = scenes.sample(np.random.default_rng(0), negative=True)
    assert np.all(s.labels == 0) and np.all(np.isnan(s.points)) and s.ring_px == 0


def test_fixed_conditions_are_obeyed():
    s = scenes.sample(np.random.default_rng(5), negative=False, conf={"alpha": 0.0625, "blur": 25.0})
    assert s.alpha == 0.0625 and s.blur == 25.0
    s = scenes.sample(np.random.default_rng(5), negative=False, conf={"alpha": (0.25, 0.3)})
    assert 0.25 <= s.alpha <= 0.3


def test_geometric_augmentation_moves_points_with_pixels():
    rng = np.random.default_rng(0)
    pts = np.array([[60.0, 50.0], [200.0, 120.0], [150.0, 200.0]], np.float32)
    for trial in range(10):
        img = np.zeros((240, 320), np.uint8)
        for x, y in pts:
            img[int(y) - 1 : int(y) + 2, int(x) - 1 : int(x) + 2] = 255
        out, p, lab = aug.geometric(img, pts, np.ones(3, np.int8), rng, {"p_affine": 1.0})
        for (x, y), l in zip(p, lab):
            if l != 1:
                continue
            ys, xs = np.nonzero(out[max(int(y) - 4, 0) : int(y) + 5, max(int(x) - 4, 0) : int(x) + 5] > 60)
            assert len(xs), trial
            cx = xs.mean() + max(int(x) - 4, 0)
            cy = ys.mean() + max(int(y) - 4, 0)
            assert abs(cx - x) < 1.0 and abs(cy - y) < 1.0


def test_points_pushed_out_of_the_image_become_absent():
    rng = np.random.default_rng(1)
    pts = np.array([[2.0, 2.0], [160.0, 120.0], [318.0, 238.0]], np.float32)
    conf = {"p_affine": 1.0, "translate": 0.0, "rotate": 0.0, "shear": 0.0, "scale": (1.5, 1.5), "p_hflip": 0, "p_vflip": 0}
    _, p, lab = aug.geometric(np.zeros((240, 320), np.uint8), pts, np.ones(3, np.int8), rng, conf)
    assert lab[0] == 0 and lab[2] == 0 and lab[1] == 1


def test_photometric_keeps_shape_and_type():
    rng = np.random.default_rng(2)
    img = (np.random.default_rng(0).uniform(0, 255, (240, 320))).astype(np.uint8)
    conf = {k: 1.0 for k in aug.default_conf if k.startswith("p_")}
    out = aug.photometric(img, rng, conf)
    assert out.shape == img.shape and out.dtype == np.uint8


def test_score_counts_failures_as_failures():
    from markerpose.train.keypoints import score

    pts = np.array([[[10, 10], [20, 10], [10, 30]]] * 3, np.float32)
    data = {"points": pts, "labels": np.array([[1, 1, 1], [1, 1, 1], [0, 0, 0]], np.int8), "scale": np.full((3, 2), 4.0, np.float32)}
    preds = [(pts[0] + 0.5, 1.0), None, None]
    m = score(preds, data, tolerance_px=8.0)
    assert m["n_views"] == 2 and m["detected"] == 0.5
    assert m["median_px"] == pytest.approx(np.hypot(2, 2))
    assert m["false_positive"] == 0.0 and m["n_negatives"] == 1
    preds = [(pts[0][[1, 0, 2]], 1.0), (pts[0] + 3, 1.0), (pts[0], 1.0)]  # swapped IDs; 17 px off; a false positive
    m = score(preds, data, tolerance_px=8.0)
    assert m["detected"] == 0.0 and m["false_positive"] == 1.0
    assert m["id_accuracy"] == pytest.approx(4 / 6)


def test_generation_does_not_depend_on_the_number_of_workers(monkeypatch):
    from markerpose.train import data
    from markerpose.train import keypoints as tk

    monkeypatch.setattr(data, "CHUNK", 2)
    a = tk.generate(4, seed=9, workers=1)
    b = tk.generate(4, seed=9, workers=2)
    monkeypatch.setattr(data, "ray_installed", lambda: False)  # a machine without Ray: forked processes
    c = tk.generate(4, seed=9, workers=2)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        np.testing.assert_array_equal(a[k], c[k])


def test_parallel_augmentation_does_not_depend_on_the_number_of_workers():
    from markerpose.train import keypoints as tk

    data = tk.generate(6, seed=3, workers=1)
    idx = np.array([0, 1, 2, 3, 4, 5, 0, 2, 4])

    def epoch(workers, seed=5):
        return list(tk._batches(data, idx, np.random.default_rng(seed), 4, (160, 128), workers))

    two, three = epoch(2), epoch(3)
    assert len(two) == 2 and two[0][0].shape == (4, 128, 160) and two[0][1].shape == (4, 16, 20) and two[0][2].shape == (4, 16, 20)
    for a, b in zip(two, three):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(two[0][0], epoch(2, seed=6)[0][0])  # each epoch's own draws
    one = epoch(1)
    assert len(one) == 2 and one[0][0].shape == (4, 128, 160)


def test_training_loop_checkpoints_and_resumes(tmp_path):
    torch = pytest.importorskip("torch")
    from markerpose import decode as dec
    from markerpose import keypoints as kp
    from markerpose.train import keypoints as tk

    conf = {"width": 0.25, "stem_width": 0.125, "epochs": 1, "train_size": 32, "val_size": 8, "batch_size": 8, "workers": 1}
    best = tk.main(conf, tmp_path / "run", data_dir=tmp_path / "data")
    assert best.is_file() and (tmp_path / "run" / "last.pt").is_file()
    tk.main({**conf, "epochs": 2}, tmp_path / "run", resume=True, data_dir=tmp_path / "data")
    hist = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["epoch"] for h in hist] == [1, 2]
    slim = tk.export(best, tmp_path / "w.pt", data_dir=tmp_path / "data", val_size=8, negatives=16)
    net = kp.KeypointNet(slim)
    assert net.conf["width"] == 0.25 and net.conf["stem_width"] == 0.125
    tuned = torch.load(slim, weights_only=True)["decode"]
    for name in tk.DECODINGS:  # every variant, both operating points; the looks
        assert {name, name + "_stereo"} <= set(tuned), name
    assert {name + "_look" for name in tk.LOOKS} <= set(tuned)
    assert all(tuned[k]["ratio_full"] == dec.default_conf["ratio_full"] for k in tuned if tuned[k].get("ids") == "layout")
    assert all(
        tuned[k][key] == dec.default_conf[key]
        for k in tuned
        if tuned[k].get("align")
        for key in ("align_top", "align_orders", "align_cc_power")
    )
    assert kp.KeypointNet(slim, {"verify": True, "align": True}).conf["min_score"] == tuned["layout_verify_align"]["min_score"]
    assert len(net([np.zeros((480, 640), np.uint8)])) == 1
    # The export writes the ONNX copy inference loads: same thresholds, same logits.
    onnx_net = kp.KeypointNet(slim.with_suffix(".onnx"), {"verify": True, "align": True})
    assert onnx_net.runner.backend == "onnxruntime" and onnx_net.conf["min_score"] == tuned["layout_verify_align"]["min_score"]
    x = np.random.default_rng(0).random((2, 240, 320), np.float32)
    for a, b in zip(net.logits(x), onnx_net.logits(x)):
        np.testing.assert_allclose(a, b, atol=1e-4)
    # ... and its detector-only copy, which stage 1's candidates run.
    assert onnx_net.locator is not None
    np.testing.assert_array_equal(onnx_net.det_logits(x), onnx_net.logits(x)[0])


def test_distillation_starts_from_the_teacher_and_fits_the_new_stem_to_its_features(tmp_path):
    """--teacher: the student takes the teacher's widths and every weight whose shape
    agrees; the stem stage moves only the stem, towards the teacher's stem features; the
    run exports a network that loads with its strided stem, ONNX and PyTorch agreeing."""
    torch = pytest.importorskip("torch")
    from markerpose import keypoints as kp
    from markerpose.nets import default_weights, load_checkpoint
    from markerpose.train import keypoints as tk

    teacher_path = default_weights("keypoints-mid").with_suffix(".pt")
    c = {**tk.default_conf, "teacher": teacher_path, "stem": "strided", "stem_steps": 40, "device": "cpu"}
    teacher, ck = tk._teacher(c), load_checkpoint(teacher_path, "keypoints")
    assert (c["width"], c["stem_width"]) == (ck["width"], ck["stem_width"])
    torch.manual_seed(0)
    net = kp.build_network(c["width"], c["stem_width"], "strided")
    rng = np.random.default_rng(0)
    x = torch.from_numpy(tk.generate(4, seed=5, workers=1)["image"].astype(np.float32) / 255.0)[:, None]

    def inputs(rng):
        return (x for _ in range(10))

    net.eval()
    with torch.no_grad():
        target = teacher.encoder[:7](x)
        before = torch.nn.functional.mse_loss(net.encoder[:7](x), target).item()
    tk._start_from_teacher(net, teacher, c, inputs)
    net.eval()
    with torch.no_grad():
        after = torch.nn.functional.mse_loss(net.encoder[:7](x), target).item()
    assert after < 0.6 * before
    mine, theirs = net.state_dict(), teacher.state_dict()
    for k, v in theirs.items():
        if not k.startswith(("encoder.0.", "encoder.1.", "encoder.3.", "encoder.4.")):
            assert torch.equal(mine[k], v), k  # the layers after the stem: the teacher's, untouched
    # One short run end to end: the widths are the teacher's, whatever the conf says.
    conf = {
        "teacher": teacher_path,
        "stem": "strided",
        "stem_steps": 4,
        "epochs": 1,
        "train_size": 16,
        "val_size": 8,
        "batch_size": 8,
        "workers": 1,
    }
    best = tk.main(conf, tmp_path / "run", data_dir=tmp_path / "data")
    slim = tk.export(best, tmp_path / "w.pt", data_dir=tmp_path / "data", val_size=8, negatives=16)
    a, b = kp.KeypointNet(slim), kp.KeypointNet(slim.with_suffix(".onnx"))
    assert a.conf["stem"] == b.conf["stem"] == "strided" and a.conf["width"] == c["width"]
    im = rng.random((2, 256, 320), np.float32)
    for u, v in zip(a.logits(im), b.logits(im)):
        np.testing.assert_allclose(u, v, atol=1e-4)


def test_training_window_keeps_the_marker_and_shifts_its_points():
    from markerpose.train.keypoints import crop

    rng = np.random.default_rng(0)
    img = np.zeros((240, 320), np.uint8)
    pts = np.array([[100.0, 100.0], [130.0, 104.0], [96.0, 60.0]], np.float32)
    for x, y in pts:
        img[int(y), int(x)] = 255
    for _ in range(20):
        out, p, lab = crop(img, pts, np.ones(3, np.int8), rng)
        assert out.shape == (144, 192)
        ys, xs = np.nonzero(out)
        lit = sorted(zip(xs.tolist(), ys.tolist()))
        if (lab == 1).all():
            assert lit == sorted((int(x), int(y)) for x, y in p)
    # A point outside the window is absent, one on its edge ignored.
    out, p, lab = crop(
        img, np.array([[1.0, 1.0], [319.0, 239.0], [160.0, 120.0]], np.float32), np.ones(3, np.int8), np.random.default_rng(1)
    )
    assert lab[2] in (1, -1) and (lab[:2] != 1).all()


def test_training_window_option():
    """--window W H reaches the training conf as given; windows that are not multiples of 8
    within 320x240 are refused before any rendering; crop honours the size."""
    pytest.importorskip("torch")
    from markerpose import cli
    from markerpose.train import keypoints as tk

    args = cli.build_parser().parse_args(["train", "keypoints", "--window", "160", "128"])
    assert tuple(args.window) == (160, 128)
    assert tuple(cli.build_parser().parse_args(["train", "keypoints"]).window) == tk.default_conf["window"]
    assert tk.check_window([160, 128]) == (160, 128) and tk.check_window(None) is None
    for bad in ((150, 128), (160, 0), (328, 240), (320, 248)):
        with pytest.raises(ValueError, match="multiples of 8"):
            tk.check_window(bad)
    with pytest.raises(ValueError, match="multiples of 8"):
        tk.main({"window": (100, 100)}, "unused", data_dir="unused")
    out, _, _ = tk.crop(
        np.zeros((240, 320), np.uint8), np.full((3, 2), 150.0, np.float32), np.ones(3, np.int8), np.random.default_rng(0), (160, 128)
    )
    assert out.shape == (128, 160)


def test_stage1_detection_by_ring_size():
    """eval keypoints' breakdown: views binned by the ring's diameter in input px, misses counted."""
    from markerpose.train.keypoints import by_ring_size

    pts = np.array([[[100, 100], [120, 100], [100, 130]]] * 4, np.float32)
    data = {
        "points": pts,
        "labels": np.array([[1, 1, 1], [1, 1, 1], [1, 1, 1], [1, 0, 1]], np.int8),  # the last: a ring absent
        "scale": np.full((4, 2), 4.0, np.float32),
        "ring_px": np.array([20.0, 24.0, 100.0, 100.0], np.float32),  # 5, 6 and 25 input px
    }
    preds = [(pts[0], 1.0), None, (pts[2] + 3.0, 1.0), None]  # 3 input px = 12 full-res px off: a miss
    out = by_ring_size(preds, data)
    assert [(b["bin"], b["n_views"], b["detected"]) for b in out] == [("0-8", 2, 0.5), ("18-26", 1, 0.0)]


def test_epoch_order_draws_small_rings_more_often():
    """small_boost: views with rings under 12 input px drawn that many times as often; 1 keeps a permutation."""
    from markerpose.train.keypoints import epoch_order

    # 1000 views: 100 small (8 input px), 800 large (30 px), 100 marker-free.
    ring = np.r_[np.full(100, 32.0), np.full(800, 120.0), np.zeros(100)].astype(np.float32)
    data = {"ring_px": ring, "scale": np.full((1000, 2), 4.0, np.float32)}
    plain = epoch_order(data, np.random.default_rng(0))
    assert sorted(plain.tolist()) == list(range(1000))
    idx = epoch_order(data, np.random.default_rng(0), small_boost=3.0)
    assert len(idx) == 1000
    share = (idx < 100).mean()  # expected 300 / 1200 = 0.25 (plain: 0.10)
    assert 0.21 < share < 0.29
    assert 0.05 < (idx >= 900).mean() < 0.12  # negatives keep their weight (100 / 1200)
    with pytest.raises(ValueError):
        epoch_order(data, np.random.default_rng(0), small_boost=0.0)


def test_speed_times_the_pair_and_the_second_look():
    pytest.importorskip("torch")
    from markerpose.train.keypoints import speed

    r = speed((0.25, (0.5, 0.25)), runs=2)
    assert r[0.25]["params"] == 81301 and r[0.25]["pair_ms"] > 0 and r[0.25]["look_ms"] > 0
    assert r[(0.5, 0.25)]["params"] > 3 * r[0.25]["params"]  # the deeper layers and heads twice as wide
