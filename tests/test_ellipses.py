"""Stage 2: EllipSegNet, patches, centres from masks, and its training data."""

import cv2
import numpy as np
import pytest

from markerpose import ellipses as es

torch = pytest.importorskip("torch")


def _disk(size, center, axes, angle=0.0, up=8):
    """Anti-aliased filled ellipse (coverage in [0, 1]) drawn on an up x up finer canvas."""
    big = np.zeros((size[1] * up, size[0] * up), np.float32)
    c = ((center[0] + 0.5) * up - 0.5, (center[1] + 0.5) * up - 0.5)
    cv2.ellipse(big, (c, (2 * axes[0] * up, 2 * axes[1] * up), angle), 1.0, -1, cv2.LINE_8)
    return cv2.resize(big, size, interpolation=cv2.INTER_AREA)


def test_paper_network_widths_shapes_and_size():
    net = es.build_network().eval()
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    widths = [m.out_channels for m in convs]
    assert widths == [16, 16, 32, 32, 64, 64, 64, 64, 64, 32, 32, 16, 16, 16, 1]
    assert all(m.kernel_size == (3, 3) for m in convs[:-1]) and convs[-1].kernel_size == (1, 1)
    with torch.inference_mode():
        assert net(torch.zeros(2, 1, 120, 120)).shape == (2, 1, 120, 120)
    mb = sum(v.numel() * 4 for v in net.state_dict().values()) / 1e6
    assert 1.0 < mb < 1.2  # the paper: 1.1 MB in float32


@pytest.mark.parametrize("side", [120, 60, 250])
def test_patch_maps_back_exactly(side):
    """A disk's centre found in the patch maps back to the image centre, whatever the window
    size, including windows that cross the image border."""
    center = (37.3, 500.6)  # near the left border
    img = (255 * (1 - _disk((640, 600), center, (20.0, 14.0), 25.0))).astype(np.uint8)
    patch, frame = es.extract_patch(img, np.array(center) + [4.0, -3.0], side)
    assert patch.shape == (120, 120)
    found = es.mask_center(1.0 - patch.astype(np.float64) / 255.0, "subpixel")
    assert found is not None
    np.testing.assert_allclose(es.patch_to_image(found[0], frame), center, atol=0.05)
    p = np.array([[3.0, 7.0]])
    np.testing.assert_allclose(es.image_to_patch(es.patch_to_image(p, frame), frame), p)


def test_window_side_follows_the_ring_size():
    from markerpose import Marker

    m = Marker()
    pts = np.array([[100.0, 100.0], [162.5, 100.0], [100.0, 0.0]])  # 2.5 px/mm → ring 50 px
    assert es.window_side(pts, m) == round(es.default_conf["patch_scale"] * 50)
    assert es.window_side(pts, m, {"patch": "fixed"}) == 120


@pytest.mark.parametrize("fit,tol", [("subpixel", 0.03), ("ellipse", 0.3), ("moments", 0.3)])
def test_mask_center_of_an_ellipse(fit, tol):
    prob = _disk((120, 120), (60.37, 58.81), (30.0, 21.0), 33.0)
    c, _ = es.mask_center(prob, fit)
    np.testing.assert_allclose(c, [60.37, 58.81], atol=tol)


def test_mask_center_takes_the_ellipse_nearest_the_centre():
    prob = _disk((120, 120), (64.2, 61.5), (20.0, 15.0)) + _disk((120, 120), (110.0, 12.0), (30.0, 30.0))
    c, _ = es.mask_center(np.clip(prob, 0, 1), "subpixel")
    np.testing.assert_allclose(c, [64.2, 61.5], atol=0.05)
    assert es.mask_center(np.zeros((120, 120)), "subpixel") is None
    with pytest.raises(ValueError, match="unknown fit"):
        es.mask_center(prob, "magic")


def test_missing_weights_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="weights not found"):
        es.EllipseNet(tmp_path / "nope.pt")


# --- training data ------------------------------------------------------------------------
def test_patch_sample_target_and_truth_agree():
    from markerpose.train import ellipses as te

    rng = np.random.default_rng(4)
    errs = []
    for _ in range(6):
        s = te.sample(rng, conf={"tilt": (0.0, 50.0), "ring_px": (50.0, 120.0)})
        assert s.image.shape == (120, 120) and s.image.dtype == np.uint8
        assert s.target.shape == (120, 120) and 0 <= s.target.min() and s.target.max() <= 1
        found = es.mask_center(s.target, "subpixel")
        if found is not None:
            errs.append(np.linalg.norm(es.patch_to_image(found[0], s.frame) - s.center))
    # The exact coverage mask's iso-line ellipse lands on the true imaged-ellipse centre.
    assert len(errs) >= 4 and np.median(errs) < 0.05


def test_patch_sample_is_deterministic():
    from markerpose.train import ellipses as te

    a = te.sample(np.random.default_rng(8))
    b = te.sample(np.random.default_rng(8))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.target, b.target)


def test_ellipse_training_loop_runs_and_exports(tmp_path):
    from markerpose.train import ellipses as te

    conf = {"epochs": 1, "train_size": 16, "val_size": 8, "batch_size": 8, "workers": 1}
    best = te.main(conf, tmp_path / "run", data_dir=tmp_path / "data")
    w = te.export(best, tmp_path / "w.pt")
    net = es.EllipseNet(w)
    out = net(
        [np.zeros((300, 400), np.uint8)], [np.array([[100.0, 100.0], [150.0, 100.0], [100.0, 20.0]])], __import__("markerpose").Marker()
    )
    assert len(out) == 1 and out[0][0].shape == (3, 2) and out[0][1].shape == (3,)
