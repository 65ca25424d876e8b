"""Renderer: geometric exactness of the anti-aliased rings, ground truth, sensor model."""

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.geometry import conic_center
from markerpose.synth import Imaging, look_at_pose, motion_kernel, render_stereo, render_view

POSES = [  # (c0 position mm, tilt deg, tilt axis deg, roll deg): the working volume's corners
    ([0, 0, 400], 45, 30, 10),
    ([30, -20, 600], 20, 30, 70),
    ([-50, 40, 780], 60, 30, 200),
    ([60, 30, 500], 0, 0, 0),
    ([-60, 30, 700], 50, 120, 100),
]


def iso_crossings(img: np.ndarray, level: float, up: int = 2) -> np.ndarray:
    """(N, 2) sub-pixel points where the image crosses ``level`` along rows and columns.

    The image is upsampled (bicubic) by ``up`` first and crossings are interpolated
    linearly, then mapped back to the image's pixel coordinates.
    """
    big = cv2.resize(img, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
    pts = []
    for axis in (0, 1):
        a = big if axis == 1 else big.T
        d0, d1 = a[:, :-1], a[:, 1:]
        r, c = np.nonzero((d0 - level) * (d1 - level) < 0)
        f = (level - d0[r, c]) / (d1[r, c] - d0[r, c])
        p = np.column_stack([c + f, r])
        pts.append(p if axis == 1 else p[:, ::-1])
    return (np.vstack(pts) + 0.5) / up - 0.5


def near_conic(pts_ideal: np.ndarray, C: np.ndarray, tol: float = 1.0) -> np.ndarray:
    """Boolean selector of points within ~tol px of the conic (first-order distance)."""
    hp = np.column_stack([pts_ideal, np.ones(len(pts_ideal))])
    g = np.einsum("ni,ij,nj->n", hp, C, hp)
    grad = 2 * (hp @ C)[:, :2]
    return np.abs(g) / np.linalg.norm(grad, axis=1) < tol


def conic_area(C):
    A, b = C[:2, :2], C[:2, 2]
    k = b @ np.linalg.solve(A, b) - C[2, 2]
    return np.pi * k / np.sqrt(np.linalg.det(A))


@pytest.mark.parametrize("distorted", [False, True])
def test_edge_ellipse_matches_analytic_conic(rig, distorted):
    """Ellipse fitted to the sub-pixel outer edge of a noise-free render == analytic ellipse (≤ 0.01 px)."""
    cam = rig.left if distorted else mp.Camera(rig.left.K, np.zeros(5), rig.left.image_size)
    im = Imaging.ideal(psf_sigma=0.7)
    bg = np.full((1024, 1280), 0.5, np.float32)
    errors = []
    for k, (pos, tilt, axis, roll) in enumerate(POSES):
        img, truth = render_view(cam, look_at_pose(pos, tilt, axis, roll), imaging=im, background=bg, seed=k)
        level = 255 * im.exposure * (im.paper + im.ink) / 2
        pts = cam.undistort_points(iso_crossings(img, level))  # ideal pixels (identity if undistorted)
        for C in truth.outer_conics:
            sel = pts[near_conic(pts, C)]
            assert len(sel) > 100
            (cx, cy), _, _ = cv2.fitEllipse(sel.astype(np.float32))
            errors.append(np.hypot(cx - conic_center(C)[0], cy - conic_center(C)[1]))
    assert max(errors) <= 0.01, errors


def test_ink_coverage_centroid_is_exact(rig):
    """Box-filter coverage: the centroid of ink in a noise-free render equals the analytic annulus centroid."""
    cam = mp.Camera(rig.left.K, np.zeros(5), rig.left.image_size)
    im = Imaging.ideal(ink=0.0, paper=1.0, psf_sigma=0.0)
    bg = np.full((1024, 1280), 1.0, np.float32)  # background like paper: only ink counts
    for k, (pos, tilt, axis, roll) in enumerate(POSES[:2]):
        img, truth = render_view(cam, look_at_pose(pos, tilt, axis, roll), imaging=im, background=bg, seed=k)
        cov = 1.0 - img / (255.0 * im.exposure)
        for i, (Co, Ci) in enumerate(zip(truth.outer_conics, truth.inner_conics)):
            ys, xs = np.nonzero(truth.mask == i + 1)
            y0, y1, x0, x1 = ys.min() - 3, ys.max() + 4, xs.min() - 3, xs.max() + 4
            w = cov[y0:y1, x0:x1]
            yy, xx = np.mgrid[y0:y1, x0:x1]
            ao, ai = conic_area(Co), conic_area(Ci)
            expected = (ao * conic_center(Co) - ai * conic_center(Ci)) / (ao - ai)
            got = np.array([(w * xx).sum(), (w * yy).sum()]) / w.sum()
            assert w.sum() == pytest.approx(ao - ai, rel=2e-4)
            np.testing.assert_allclose(got, expected, atol=2e-3)


def test_truth_centers_equal_cv2_projectPoints(rig):
    T = look_at_pose([10, -5, 520], 35, 60, 40)
    frame = render_stereo(rig, T, seed=1)
    marker = mp.Marker()
    for cam, view in zip(rig.cameras, frame.views):
        rvec, _ = cv2.Rodrigues(view.T_cam_marker[:3, :3])
        ref, _ = cv2.projectPoints(marker.points3d, rvec, view.T_cam_marker[:3, 3], cam.K, cam.dist)
        np.testing.assert_allclose(view.centers, ref.reshape(3, 2), atol=1e-9)
    np.testing.assert_allclose(frame.views[1].T_cam_marker, rig.T_right_left @ T)
    both = rig.project(marker.points3d @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(np.stack([v.centers for v in frame.views]), both, atol=1e-9)


def test_perspective_bias_is_present_and_small(rig):
    """The imaged ellipse centre differs from the projected 3D centre (tilted marker), by < 1 px."""
    _, truth = render_view(rig.left, look_at_pose([0, 0, 400], 50, 0, 0), seed=0)
    bias = np.linalg.norm(truth.outer_centers - truth.centers, axis=1)
    assert np.all(bias > 0.05) and np.all(bias < 1.0)


def test_deterministic_from_seed(rig):
    T = look_at_pose([0, 0, 550], 20, 0, 0)
    a = render_stereo(rig, T, seed=7)
    b = render_stereo(rig, T, seed=7)
    c = render_stereo(rig, T, seed=8)
    for x, y in zip(a.images, b.images):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.images[0], c.images[0])
    assert a.images[0].dtype == np.uint8 and a.images[0].shape == (1024, 1280)


def test_mask_labels_rings(rig):
    _, truth = render_view(rig.left, look_at_pose([0, 0, 500], 0, 0, 0), seed=0)
    for i in range(3):
        x, y = np.rint(truth.centers[i]).astype(int)
        assert truth.mask[y, x] == i + 1
    assert set(np.unique(truth.mask)) == {0, 1, 2, 3}
    assert truth.in_image.all()


def test_sensor_noise_and_darkness(rig):
    """Flat paper region: mean follows alpha; variance follows shot + read noise."""
    cam = mp.Camera(rig.left.K, np.zeros(5), rig.left.image_size)
    T = look_at_pose([0, 0, 350], 0, 0, 0)
    bg = np.full((1024, 1280), 0.3, np.float32)
    for alpha in (1.0, 0.25, 0.0625):
        im = Imaging(alpha=alpha, gradient=0.0, vignetting=0.0, psf_sigma=0.0, quantize=False)
        img, truth = render_view(cam, T, imaging=im, background=bg, seed=3)
        # A paper patch between c0 and c1 (marker x = 12.5 mm, y = -15 mm).
        p = cam.project((T[:3, :3] @ np.array([12.5, -15.0, 0]) + T[:3, 3])[None])[0]
        x, y = np.rint(p).astype(int)
        patch = img[y - 10 : y + 10, x - 10 : x + 10]
        electrons = alpha * im.exposure * im.full_well * im.paper
        gain = 255.0 / im.full_well
        assert patch.mean() == pytest.approx(electrons * gain, rel=0.02)
        assert patch.var() == pytest.approx((electrons + im.read_noise**2) * gain**2, rel=0.25)


def test_shot_noise_is_poisson_when_light_is_scarce(rig):
    """Few electrons: exact Poisson counts (integers, mean = variance); many: normal with var = λ."""
    cam = mp.Camera(rig.left.K, np.zeros(5), (200, 160))
    T = look_at_pose([0, 0, 5000], 0, 0, 0)  # marker far away: a small plate amid the background
    bg = np.full((160, 200), 0.5, np.float32)
    for alpha, exact in ((0.002, True), (0.5, False)):
        im = Imaging(alpha=alpha, gradient=0.0, vignetting=0.0, psf_sigma=0.0, read_noise=0.0, quantize=False)
        img, _ = render_view(cam, T, imaging=im, background=bg, seed=5)
        e = img[:40].astype(np.float64) * im.full_well / 255.0  # background rows, in electrons
        lam = alpha * im.exposure * im.full_well * 0.5
        assert e.mean() == pytest.approx(lam, rel=0.03)
        assert e.var() == pytest.approx(lam, rel=0.08)
        assert np.allclose(e, np.rint(e), atol=1e-3) == exact


def test_motion_kernel():
    k = motion_kernel(25, 30)
    assert k.sum() == pytest.approx(1.0)
    assert k.shape[0] == k.shape[1] >= 25
    # Its extent along the motion direction is ~25 px.
    ys, xs = np.nonzero(k > k.max() * 0.3)
    assert 20 <= np.hypot(xs.max() - xs.min(), ys.max() - ys.min()) <= 28


@pytest.mark.parametrize("length, angle", [(25, 0), (25, 130.5), (9, 77), (4.3, 12)])
def test_motion_kernel_does_not_shift_the_image(length, angle):
    k = motion_kernel(length, angle).astype(np.float64)
    n = k.shape[0]
    yy, xx = np.mgrid[:n, :n]
    # Centroid at the anchor (the middle pixel), so blur moves no edge on average.
    assert (k * xx).sum() == pytest.approx((n - 1) / 2, abs=1e-6)
    assert (k * yy).sum() == pytest.approx((n - 1) / 2, abs=1e-6)


def test_motion_blur_spreads_the_edges(rig):
    T = look_at_pose([0, 0, 500], 0, 0, 0)
    sharp, _ = render_view(rig.left, T, imaging=Imaging(noise=False), seed=0)
    blurred, _ = render_view(rig.left, T, imaging=Imaging(noise=False, motion_blur=15, motion_angle=0), seed=0)
    gx = lambda im: np.abs(np.diff(im.astype(float), axis=1)).max()  # noqa: E731
    assert gx(blurred) < 0.5 * gx(sharp)


def test_bad_inputs(rig):
    with pytest.raises(ValueError, match="in front of the camera"):
        render_view(rig.left, look_at_pose([0, 0, -100], 0, 0, 0))
    with pytest.raises(ValueError, match="background"):
        render_view(rig.left, look_at_pose([0, 0, 500], 0, 0, 0), background=np.zeros((10, 10)))
    with pytest.raises(ValueError, match="alpha"):
        Imaging(alpha=0)


def test_regression_plate_one_pixel_inside_the_image(rig):
    """A plate whose box is one pixel thin at the image border rendered without error
    (np.gradient on the 1-px box raised while training data were generated)."""
    cam = mp.Camera(rig.left.K, np.zeros(5), (64, 48))
    m = mp.Marker()
    z = 2000.0
    fx, cx = cam.K[0, 0], cam.K[0, 2]
    for u in np.arange(-2.0, 2.01, 0.25):  # where the plate's right edge lands, px
        T = look_at_pose([0, 0, z])
        T[0, 3] = (u - cx) * z / fx - m.plate[2]
        T[1, 3] = -(m.plate[1] + m.plate[3]) / 2  # plate centred vertically (y is flipped)
        img, truth = render_view(cam, T, m, Imaging(noise=False), seed=0)
        assert img.shape == (48, 64)


def test_realism_effects_change_what_they_say(rig):
    """Each effect of real recordings acts where and how it says, deterministically."""
    from markerpose.synth import realism

    T = look_at_pose([0, 0, 500], 10, 30, 0)
    base = render_view(rig.left, T, imaging=Imaging(noise=False), seed=2)[0].astype(float)
    mk = mp.Marker()

    def view(**kw):
        return render_view(rig.left, T, imaging=Imaging(noise=False, **kw), seed=2)[0].astype(float)

    # A shadow darkens part of the plate only (the background is untouched).
    shaded = view(plate_light=lambda mx, my: np.where(mx < 10.0, 0.3, 1.0))
    changed = np.abs(shaded - base) > 2
    plate = render_view(rig.left, T, imaging=Imaging(noise=False, paper=0.99, ink=0.99), seed=2)[0] != base.astype(np.uint8)
    plate = cv2.dilate(plate.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0  # the PSF's reach
    assert changed.any() and not (changed & ~plate).any()
    assert (shaded <= base + 1).all()
    # Gamma > 1 darkens mid-tones, keeps black and white; resampling and JPEG keep size and type.
    g = view(gamma=2.0)
    mid = (base > 60) & (base < 200)
    assert (g[mid] < base[mid]).all()
    for kw in ({"resample": 4.0}, {"jpeg_quality": 30}):
        out = render_view(rig.left, T, imaging=Imaging(noise=False, **kw), seed=2)[0]
        assert out.dtype == np.uint8 and out.shape == base.shape and 0 < np.abs(out - base).mean() < 10
    # Every effect draws its settings from the stated ranges, the same for the same seed.
    for name in realism.EFFECTS:
        a = realism.imaging_settings(name, np.random.default_rng(5), mk)
        b = realism.imaging_settings(name, np.random.default_rng(5), mk)
        assert a.keys() == b.keys()
        for k in a:
            if callable(a[k]):
                xy = np.random.default_rng(0).uniform(-20, 60, (2, 50))
                assert np.allclose(a[k](*xy), b[k](*xy)) and np.all((a[k](*xy) > 0) & (a[k](*xy) <= 1))
            else:
                assert a[k] == b[k]
    with pytest.raises(ValueError, match="unknown effect"):
        realism.imaging_settings("fog", np.random.default_rng(0), mk)
