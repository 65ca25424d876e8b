"""Tests of the classical detector (markerpose.classical).

Two sources of images:
- ``draw_marker``: a self-contained fixture — the marker under an affine map, drawn with
  ``cv2.ellipse`` on an 8x canvas and area-averaged down (anti-aliased). Under an affine
  map the ring centres are exactly the ellipse centres.
- the package's renderer (``markerpose.synth``): ray-cast through the lens model, with
  perspective, PSF, noise and clutter; its truth has ``outer_centers`` (the imaged outer
  ellipses' centres — what the detector estimates) and ``centers`` (projected 3D centres).

Measured on this machine while writing these tests (errors in px):
- renderer, noise-free, no PSF (66 rings, 12 random poses, 350-800 mm, tilt <= 60 deg):
  subpixel=True mean 0.004 / max 0.010; subpixel=False (the paper's) mean 0.09 / max 0.20-0.40;
- renderer defaults (PSF 0.6 px, shot + read noise): subpixel=True mean 0.003 / max 0.011;
- darkness alpha 0.1: mean 0.012 / max 0.03; alpha 0.039: mean 0.022 / max 0.07.
Bounds below carry a margin of ~2-3x over those.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose import Marker, StereoRig
from markerpose import classical as C
from markerpose import geometry as geo
from markerpose.geometry import circle_conic, conic_center, epipolar_distance, plane_homography, project_conic
from markerpose.results import Detection

synth = pytest.importorskip("markerpose.synth")


# --- a self-contained fixture: affine marker drawn with cv2.ellipse --------------------------
def affine_A(scale=4.0, angle_deg=20.0, shear=0.0, squash=1.0, origin=(150.0, 260.0), mirror=False):
    """(2, 3) affine map marker mm → image px; y flipped as a camera facing the marker sees it."""
    th = np.deg2rad(angle_deg)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    flip = np.diag([1.0, 1.0 if mirror else -1.0])
    M = scale * R @ np.array([[1.0, shear], [0.0, squash]]) @ flip
    return np.column_stack([M, origin])


def _draw_rings(canvas, A, centers_mm, r_out, r_in, ss, ink, paper):
    M = A[:, :2]
    U, S, _ = np.linalg.svd(M)
    ang = np.degrees(np.arctan2(U[1, 0], U[0, 0]))
    for p in centers_mm:
        cc = (M @ p + A[:, 2] + 0.5) * ss - 0.5  # output px → canvas px (pixel centres)
        ctr = (int(round(cc[0] * 256)), int(round(cc[1] * 256)))
        for r, col in ((r_out, ink), (r_in, paper)):
            if r > 0:
                ax = (int(round(r * S[0] * ss * 256)), int(round(r * S[1] * ss * 256)))
                cv2.ellipse(canvas, ctr, ax, ang, 0, 360, int(col), -1, cv2.LINE_8, 8)


def draw_marker(size=(480, 400), A=None, marker=Marker(), ink=20, paper=200, extra=(), ss=8):
    """Anti-aliased uint8 image of the marker under the affine ``A``; returns (image, (3, 2) centres).

    ``extra``: more ring-like things, each (A, centres mm (K, 2), outer radius, inner radius;
    inner radius 0 = a dark disk).
    """
    w, h = size
    A = affine_A() if A is None else A
    canvas = np.full((h * ss, w * ss), paper, np.uint8)
    _draw_rings(canvas, A, marker.centers2d, marker.outer_radius, marker.inner_radius, ss, ink, paper)
    for A2, pts, ro, ri in extra:
        _draw_rings(canvas, A2, np.asarray(pts, float), ro, ri, ss, ink, paper)
    img = cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA)
    return img, marker.centers2d @ A[:, :2].T + A[:, 2]


POSES = [
    affine_A(),
    affine_A(3.0, 75.0, 0.2, 0.6, (200.0, 260.0)),
    affine_A(2.5, -40.0, -0.1, 0.8, (190.3, 250.7)),
]


# --- renderer fixtures (shared; the first render builds each camera's ray grid) -------------
@pytest.fixture(scope="module")
def plain_bg():
    return np.full((1024, 1280), 0.45, np.float32)


def render(rig, T, imaging=None, background=None, seed=0):
    return synth.render_stereo(rig, T, imaging=imaging or synth.Imaging(), background=background, seed=seed)


def random_pose(rng):
    z = rng.uniform(380, 780)
    pos = np.array([rng.uniform(-0.1, 0.1) * z - 12, rng.uniform(-0.08, 0.08) * z + 20, z])
    return synth.look_at_pose(pos, rng.uniform(0, 55), rng.uniform(0, 360), rng.uniform(0, 360))


@pytest.fixture(scope="module")
def ideal_frames(rig, plain_bg):
    """Noise-free, blur-free, evenly lit renders of six random poses (fixed seed)."""
    rng = np.random.default_rng(11)
    frames = []
    while len(frames) < 6:
        f = render(rig, random_pose(rng), synth.Imaging.ideal(quantize=True), plain_bg, seed=len(frames))
        if all(v.in_image.all() for v in f.views):
            frames.append(f)
    return frames


# --- helpers ----------------------------------------------------------------------------------
def test_fit_ellipse_exact_on_points():
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    a, b, th, c = 40.0, 17.0, np.deg2rad(33), np.array([512.3, 301.7])
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    pts = (R @ np.stack([a * np.cos(t), b * np.sin(t)])).T + c
    cen, Q = C.fit_ellipse(pts)
    np.testing.assert_allclose(cen, c, atol=1e-9)
    (cx, cy), (w, h), ang = geo.cq_to_rect(cen, Q)
    np.testing.assert_allclose([w, h, ang], [2 * a, 2 * b, 33.0], atol=1e-8)
    assert C.fit_ellipse(pts[:5]) is None
    assert C.fit_ellipse(np.column_stack([t, 2 * t])) is None  # collinear


def test_concentric_center_removes_perspective_bias():
    # Two concentric circles seen by a tilted camera: the ellipse centres are biased, the
    # eigenvector construction recovers the projected centre exactly.
    K = np.array([[2500.0, 0, 640], [0, 2500.0, 512], [0, 0, 1]])
    T = synth.look_at_pose(np.array([30.0, -20.0, 400.0]), tilt_deg=55, tilt_axis_deg=30)
    H = plane_homography(K, T)
    Co, Ci = project_conic(circle_conic((0, 0), 10.0), H), project_conic(circle_conic((0, 0), 4.0), H)

    def cq(Cn):
        c = conic_center(Cn)
        k = -(Cn[2, 2] + Cn[2, :2] @ c)
        return c, Cn[:2, :2] / k

    truth = (H @ [0, 0, 1])[:2] / (H @ [0, 0, 1])[2]
    assert np.linalg.norm(cq(Co)[0] - truth) > 0.1  # the bias is real at this tilt
    np.testing.assert_allclose(C.concentric_center(cq(Co), cq(Ci)), truth, atol=1e-6)


def test_noise_sigma_estimate():
    rng = np.random.default_rng(0)
    img = np.full((400, 500), 100.0, np.float32)
    cv2.circle(img, (250, 200), 80, 30.0, -1)  # edges are a minority: the median ignores them
    img += rng.normal(0, 2.0, img.shape).astype(np.float32)
    assert C.noise_sigma(img) == pytest.approx(2.0, rel=0.1)
    # Several images' estimates, two at a time: each image's own, in order.
    imgs = [np.clip(img + rng.normal(0, s, img.shape), 0, 255).astype(np.uint8) for s in (1.0, 3.0, 5.0)]
    assert C.noise_sigmas(imgs) == [C.noise_sigma(g) for g in imgs] and C.noise_sigmas([]) == []


# --- single view: the affine fixture ------------------------------------------------------------
@pytest.mark.parametrize("k", range(len(POSES)))
def test_detect_ids_and_accuracy_affine(k):
    img, truth = draw_marker(A=POSES[k])
    det = C.detect(img)
    assert isinstance(det, Detection)
    assert det.centers.shape == (3, 2) and len(det.ellipses) == 3 and 0 < det.score <= 1
    # Measured max 0.002-0.015 px (cv2.ellipse's polygon outline limits the fixture).
    np.testing.assert_allclose(det.centers, truth, atol=0.03)
    paper = C.detect(img, subpixel=False)
    np.testing.assert_allclose(paper.centers, truth, atol=0.5)
    assert np.abs(det.centers - truth).max() <= np.abs(paper.centers - truth).max()


def test_handedness_of_result():
    det = C.detect(draw_marker()[0])
    v1, v2 = det.centers[1] - det.centers[0], det.centers[2] - det.centers[0]
    assert v1[0] * v2[1] - v1[1] * v2[0] < 0  # c0 → c1 → c2 negative in a y-down image
    assert np.linalg.norm(v1) < np.linalg.norm(v2)  # c1 is the nearer neighbour


@pytest.mark.parametrize("flip", ["lr", "ud", "drawn"])
def test_mirror_image_is_rejected(flip):
    if flip == "drawn":
        img, _ = draw_marker(A=affine_A(mirror=True))
    else:
        img = draw_marker()[0]
        img = np.ascontiguousarray(img[:, ::-1] if flip == "lr" else img[::-1])
    assert C.detect(img) is None


def test_bgr_single_channel_and_float_inputs_agree():
    img, _ = draw_marker()
    det = C.detect(img)
    det_bgr = C.detect(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    det_1 = C.detect(img[..., None])
    det_f = C.detect(img.astype(np.float32))
    np.testing.assert_allclose(det_bgr.centers, det.centers, atol=1e-9)
    np.testing.assert_allclose(det_1.centers, det.centers, atol=1e-9)
    np.testing.assert_allclose(det_f.centers, det.centers, atol=1e-9)


def test_distractor_rings_and_disks():
    A = affine_A(origin=(170.0, 300.0))
    extra = [
        # single rings with the marker's own ratio, near and far, and dark disks
        (affine_A(4.0, 0.0, origin=(60.0, 60.0)), [(0, 0), (60, 0)], 10.0, 4.0),
        (affine_A(3.0, 10.0, origin=(400.0, 330.0)), [(0, 0)], 10.0, 4.0),
        (affine_A(4.0, 0.0, origin=(390.0, 90.0)), [(0, 0), (0, -30)], 9.0, 0.0),
        # a thin ring (ratio 0.85) and a ring with a tiny hole
        (affine_A(4.0, 0.0, origin=(60.0, 330.0)), [(0, 0)], 10.0, 8.5),
        (affine_A(4.0, 0.0, origin=(300.0, 40.0)), [(0, 0)], 8.0, 1.0),
    ]
    img, truth = draw_marker(size=(480, 400), A=A, extra=extra)
    rings = C.find_rings(img)
    assert 5 <= len(rings) <= 8  # the marker's 3 + the 3 single rings of marker-like ratio (± merges)
    det = C.detect(img)
    np.testing.assert_allclose(det.centers, truth, atol=0.05)


@pytest.mark.parametrize("dx, width", [(30, 7), (36, 9), (25, 5)])
def test_occluder_across_a_ring(dx, width):
    # A dark bar over the edge of c2: its dark region is no ellipse any more, so the ring
    # comes from its hole; the spoilt sector of edge points must not bend the fit.
    # Measured: 0.008-0.01 px (sub-pixel), 0.024 px (hole-predicted coarse centre).
    img, truth = draw_marker(A=affine_A(origin=(170.0, 300.0)))
    c = truth[2]
    cv2.line(img, (int(c[0] + dx), int(c[1] - 70)), (int(c[0] + dx + 20), int(c[1] + 70)), 25, width, cv2.LINE_AA)
    rings = C.find_rings(img)
    assert any(r.from_hole for r in rings)
    det = C.detect(img)
    np.testing.assert_allclose(det.centers, truth, atol=0.04)
    np.testing.assert_allclose(C.detect(img, subpixel=False).centers, truth, atol=0.1)


def test_dark_noisy_affine():
    img, truth = draw_marker()
    rng = np.random.default_rng(1)
    dark = np.clip(np.rint(img * 0.08 + rng.normal(0, 0.8, img.shape)), 0, 255).astype(np.uint8)
    assert int(dark.max()) - int(np.median(dark[dark < 5])) < 25  # contrast of ~14 grey levels
    det = C.detect(dark)
    assert det is not None
    np.testing.assert_allclose(det.centers, truth, atol=0.08)  # measured 0.011


def test_marker_free_images_give_none():
    rng = np.random.default_rng(3)
    assert C.detect(np.full((200, 300), 128, np.uint8)) is None
    assert C.detect(rng.integers(0, 256, (240, 320)).astype(np.uint8)) is None
    for k in range(3):
        bg = synth.clutter_background((640, 512), np.random.default_rng(k), ring_distractors=6)
        assert C.detect((bg * 200).astype(np.uint8)) is None
    # Two rings only.
    ext = [(affine_A(origin=(100.0, 100.0)), [(0, 0), (25, 0)], 10.0, 4.0)]
    img = np.full((300, 300), 200, np.uint8)
    canvas = cv2.resize(img, (2400, 2400), interpolation=cv2.INTER_NEAREST)
    _draw_rings(canvas, ext[0][0], np.array(ext[0][1], float), 10.0, 4.0, 8, 20, 200)
    assert C.detect(cv2.resize(canvas, (300, 300), interpolation=cv2.INTER_AREA)) is None


def test_find_rings_candidates():
    img, truth = draw_marker()
    rings = C.find_rings(img)
    assert len(rings) == 3
    for r in rings:
        assert r.center.shape == (2,) and 0 < r.score <= 1
        (cx, cy), (w, h), _ = r.outer
        assert 0.3 < min(r.inner[1]) / min(w, h) < 0.5  # inner/outer ≈ 0.4
        assert np.min(np.linalg.norm(truth - r.center, axis=1)) < 0.5
    refined = C.find_rings(img, subpixel=True)
    assert all(r.refined for r in refined)
    assert max(np.min(np.linalg.norm(truth - r.center, axis=1)) for r in refined) < 0.03


def test_find_triples_order_and_ids():
    img, truth = draw_marker()
    rings = C.find_rings(img)
    triples = C.find_triples(rings)
    assert len(triples) == 1
    cost, tri = triples[0]
    got = np.array([rings[k].center for k in tri])
    np.testing.assert_allclose(got, truth, atol=0.5)
    assert C.find_triples(rings[:2]) == []


def test_custom_marker_geometry():
    m = Marker(outer_diameter=16.0, inner_diameter=7.0, c1=(22.0, 0.0), c2=(0.0, 34.0))
    img, truth = draw_marker(A=affine_A(4.5, 130.0, origin=(330.0, 230.0)), marker=m)
    det = C.detect(img, marker=m)
    np.testing.assert_allclose(det.centers, truth, atol=0.03)
    # With the default marker's ratio 0.4 the 7/16 rings are still rings (tolerance 0.15),
    # but an isosceles marker layout does not match a 22/34 one.
    iso = Marker(c1=(40.0, 0.0), c2=(0.0, 40.0))
    assert C.detect(img, marker=iso) is None


# --- errors -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "bad, match",
    [
        (None, "is None"),
        ([[0, 1], [2, 3]], "numpy array"),
        (np.zeros((0, 0), np.uint8), "empty"),
        (np.zeros((100, 100), np.float64), "dtype float64"),
        (np.zeros((100, 100), np.int32), "dtype int32"),
        (np.zeros((100, 100), bool), "dtype bool"),
        (np.zeros((100, 100, 4), np.uint8), "4 channels"),
        (np.zeros((100, 100, 2), np.uint8), "2 channels"),
        (np.zeros((4, 100, 100, 3), np.uint8), "shape"),
        (np.zeros((8, 100), np.uint8), "too small"),
        (np.full((100, 100), np.nan, np.float32), "non-finite"),
    ],
)
def test_bad_inputs_raise(bad, match):
    with pytest.raises(ValueError, match=match):
        C.detect(bad)
    with pytest.raises(ValueError, match=match):
        C.find_rings(bad)


def test_bad_conf_raises(rig):
    img = draw_marker()[0]
    with pytest.raises(ValueError, match="unknown classical-detector settings"):
        C.detect(img, conf={"no_such_setting": 1})
    with pytest.raises(ValueError, match="edge_method"):
        C.detect(img, conf={"edge_method": "gradient"})
    with pytest.raises(ValueError, match="right image"):
        detect_stereo(img, np.zeros((100, 100, 4), np.uint8), rig)
    with pytest.raises(ValueError, match="left image is 480x400 but the rig was calibrated for 1280x1024"):
        detect_stereo(img, img, rig)


def detect_stereo(left, right, rig, subpixel=True):
    """Both views' detections of the classical detector (paper §3.4 pairing), no shape check."""
    tracker = mp.MarkerPose(rig, detector="classical", refine={"subpixel": subpixel}, verify={"max_shape_error": np.inf})
    est = tracker.estimate(left, right)
    return None if est is None else est.detections


def test_default_conf_is_not_mutated():
    before = dict(C.default_conf)
    C.detect(draw_marker()[0], conf={"edge_method": "midlevel"})
    assert C.default_conf == before


# --- the renderer: accuracy, light, blur, clutter -----------------------------------------------
def test_accuracy_on_ideal_renders(rig, ideal_frames):
    err_sub, err_paper, err_conc = [], [], []
    for f in ideal_frames:
        for v in range(2):
            img, truth, cam = f.images[v], f.views[v], rig.cameras[v]
            det = C.detect(img, camera=cam)
            paper = C.detect(img, subpixel=False)
            assert det is not None and paper is not None
            err_sub.append(np.linalg.norm(det.centers - truth.outer_centers, axis=1))
            err_paper.append(np.linalg.norm(paper.centers - truth.outer_centers, axis=1))
            conc = C.detect(img, camera=cam, conf={"center": "concentric"})
            err_conc.append(np.linalg.norm(conc.centers - truth.centers, axis=1))
    e, p, cc = map(np.concatenate, (err_sub, err_paper, err_conc))
    # Measured (these 6 frames): sub-pixel mean 0.004 / max 0.01; paper 0.09 / 0.3;
    # concentric vs projected 3D centres mean 0.007 / max 0.02.
    assert e.max() < 0.025 and e.mean() < 0.01
    assert p.max() < 0.8
    assert e.mean() < 0.2 * p.mean()
    assert cc.max() < 0.05


def test_without_camera_distortion_costs_little(rig, ideal_frames):
    # Fitting in distorted pixels (no camera given) is off by up to ~0.08 px near the image
    # borders of a 12 mm lens; the IDs are the same.
    f = ideal_frames[0]
    a = C.detect(f.images[0], camera=rig.left)
    b = C.detect(f.images[0])
    assert np.abs(a.centers - b.centers).max() < 0.15


@pytest.mark.parametrize(
    "imaging, tol",
    [
        # Measured max errors: 0.005, 0.021, 0.017, 0.008, 0.023 px.
        ({}, 0.02),  # PSF, shot + read noise, gradient, vignetting
        ({"alpha": 0.1}, 0.06),  # dark: paper ~17 grey levels
        ({"alpha": 0.06}, 0.08),
        ({"motion_blur": 6.0, "motion_angle": 45.0}, 0.03),
        ({"motion_blur": 9.0, "motion_angle": 0.0}, 0.03),
        ({"motion_blur": 12.0, "motion_angle": 135.0, "alpha": 0.3}, 0.08),
    ],
)
def test_realistic_renders(rig, imaging, tol):
    rng = np.random.default_rng(21)
    T = random_pose(rng)
    f = render(rig, T, synth.Imaging(**imaging), seed=5)
    assert all(v.in_image.all() for v in f.views)
    for v in range(2):
        det = C.detect(f.images[v], camera=rig.cameras[v])
        assert det is not None, f"view {v} not detected with {imaging}"
        err = np.linalg.norm(det.centers - f.views[v].outer_centers, axis=1)
        assert err.max() < tol, (imaging, err)


def test_cluttered_background_with_ring_distractors(rig):
    # The clutter holds single rings with the marker's ratio and dark disks.
    T = synth.look_at_pose(np.array([-15.0, 10.0, 600.0]), 35, 60, 200)
    bg = synth.clutter_background((1280, 1024), np.random.default_rng(8), ring_distractors=6)
    f = render(rig, T, background=bg, seed=2)
    for v in range(2):
        det = C.detect(f.images[v], camera=rig.cameras[v])
        np.testing.assert_allclose(det.centers, f.views[v].outer_centers, atol=0.05)


# --- stereo -------------------------------------------------------------------------------------
def paste_fake_marker(img, origin, scale=4.5, angle=-15.0):
    """Draw a second, perfect-looking marker into a copy of ``img`` (in its own paper patch)."""
    out = img.copy()
    A = affine_A(scale, angle, origin=(110.0, 230.0))
    patch, fake = draw_marker(size=(300, 300), A=A, ink=10, paper=int(np.percentile(img, 95)))
    x0, y0 = origin
    out[y0 : y0 + 300, x0 : x0 + 300] = patch
    return out, fake + [x0, y0]


def test_stereo_picks_the_epipolar_consistent_triple(rig):
    T = synth.look_at_pose(np.array([-40.0, 60.0, 620.0]), 40, 100, 30)
    f = render(rig, T, seed=4)
    truth = [v.outer_centers for v in f.views]
    assert truth[1][:, 0].max() < 800  # the fake goes to the right of the real marker
    right, fake = paste_fake_marker(f.images[1], (920, 80))
    # The fake is a better marker than the real one, so one view alone takes it ...
    single = C.detect(right, camera=rig.right)
    np.testing.assert_allclose(single.centers, fake, atol=0.1)
    assert np.diag(epipolar_distance(rig, truth[0], fake)).max() > 20  # ... and it is off the epipolar lines
    # ... but the pair of views rejects it.
    pair = detect_stereo(f.images[0], right, rig)
    assert pair is not None
    for v in range(2):
        np.testing.assert_allclose(pair[v].centers, truth[v], atol=0.03)
    d = np.diag(epipolar_distance(rig, pair[0].centers, pair[1].centers))
    assert d.max() < 0.1  # measured ~0.01 px


def test_stereo_none_when_one_view_lacks_the_marker(rig):
    T = synth.look_at_pose(np.array([0.0, 20.0, 560.0]), 20, 0, 0)
    f = render(rig, T, seed=6)
    assert detect_stereo(*f.images, rig) is not None
    empty = np.full_like(f.images[1], 90)
    assert detect_stereo(f.images[0], empty, rig) is None
    # A fake marker alone in the right view is not epipolar-consistent either.
    fake_only, _ = paste_fake_marker(empty, (900, 300))
    assert C.detect(fake_only) is not None
    assert detect_stereo(f.images[0], fake_only, rig) is None


def test_stereo_subpixel_false_is_the_paper_configuration(rig):
    T = synth.look_at_pose(np.array([10.0, 10.0, 500.0]), 30, 45, 10)
    f = render(rig, T, seed=9)
    paper = detect_stereo(*f.images, rig, subpixel=False)
    sub = detect_stereo(*f.images, rig)
    for v in range(2):
        e_p = np.linalg.norm(paper[v].centers - f.views[v].outer_centers, axis=1)
        e_s = np.linalg.norm(sub[v].centers - f.views[v].outer_centers, axis=1)
        assert e_p.max() < 0.8 and e_s.max() < 0.03


# --- sub-pixel centres near rough points (the neural detector's refinement) ----------------
def test_refine_points_matches_the_classical_fit():
    rig = StereoRig.default()
    T = synth.look_at_pose([15, -20, 600], 40, 75, 220)
    img, truth = synth.render_view(rig.left, T, seed=21)
    rough = truth.centers + np.random.default_rng(0).uniform(-5, 5, (3, 2))
    centers, found, ellipses = C.refine_points(img, rough, camera=rig.left)
    assert found.all() and all(e is not None for e in ellipses)
    np.testing.assert_allclose(centers, truth.outer_centers, atol=0.03)
    full = C.detect(img, camera=rig.left)
    np.testing.assert_allclose(centers, full.centers, atol=1e-3)  # same edges; the iterations stop within refine_tol


def test_refine_points_keeps_a_point_with_no_ring():
    rig = StereoRig.default()
    T = synth.look_at_pose([0, 0, 600], 20, 0, 0)
    img, truth = synth.render_view(rig.left, T, seed=2)
    rough = truth.centers.copy()
    rough[2] = [60.0, 60.0]  # nowhere near a ring
    centers, found, _ = C.refine_points(img, rough, camera=rig.left)
    assert found.tolist() == [True, True, False]
    np.testing.assert_array_equal(centers[2], rough[2])


@pytest.mark.parametrize("shift,grow", [(0.0, 1.0), (1.5, 1.06), (-1.5, 0.94)])
def test_refine_ellipses_from_rough_ellipses(shift, grow):
    """Ellipses ~1.5 px and ~6 % off (as fitted to a network's mask) are refitted on the
    image's edges to the true centres; None and hopeless seeds are reported, not guessed."""
    A = POSES[1]
    img, truth = draw_marker(A=A)
    exact = C.detect(img)
    assert exact is not None
    rough = [((cx + shift, cy - shift), (w * grow, h * grow), ang) for (cx, cy), (w, h), ang in exact.ellipses]
    centers, ok, ellipses = C.refine_ellipses(img, rough)
    assert ok.all() and len(ellipses) == 3
    assert np.abs(centers - truth).max() < 0.05, centers - truth
    centers, ok, _ = C.refine_ellipses(img, [rough[0], None, ((20.0, 20.0), (30.0, 30.0), 0.0)])
    assert ok.tolist() == [True, False, False]
    assert np.isnan(centers[1]).all() and np.abs(centers[0] - truth[0]).max() < 0.05


def test_edge_weights_steady_the_centre_under_motion_blur():
    # (The edge fit alone: the blurred-ring model fit that replaces it here is tested in
    # test_blurfit.py.) 25 px blur on small rings: the smeared edges along the motion are noisy; weighting
    # the edge points by (contrast / width)^2 must not do worse than equal weights over
    # noise seeds (fixed), and the centres stay well within a pixel.
    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 760], 25, 60, 30)
    bg = synth.clutter_background((1280, 1024), np.random.default_rng(0), ring_distractors=0)
    errs = {True: [], False: []}
    for seed in range(6):
        img, truth = synth.render_view(
            rig.left, T, imaging=synth.Imaging(alpha=0.7, motion_blur=25, motion_angle=70), background=bg, seed=seed
        )
        for w in (True, False):
            det = C.detect(img, conf={"edge_weights": w, "blur_fit": False}, camera=rig.left)
            assert det is not None
            errs[w].append(np.linalg.norm(det.centers - truth.outer_centers, axis=1))
    rms = {w: float(np.sqrt(np.mean(np.square(errs[w])))) for w in errs}
    assert rms[True] < rms[False] and rms[True] < 0.5, rms


def test_blur_fit_leaves_rings_whose_sizes_do_not_fit_their_spacing():
    """The blurred-ring fit runs only for three ellipses the size their spacing implies."""
    from markerpose.classical import _sizes_fit_spacing
    from markerpose.geometry import ring_ellipses
    from markerpose.synth import look_at_pose

    rig = StereoRig.default()
    m = Marker()
    T = look_at_pose([0, 0, 500], 50, 30, 60)
    cqs = []
    for (cx, cy), (w, h), ang in ring_ellipses(rig.left, T, m.points3d, m.outer_radius):
        a, b = w / 2, h / 2
        R = np.array([[np.cos(np.deg2rad(ang)), -np.sin(np.deg2rad(ang))], [np.sin(np.deg2rad(ang)), np.cos(np.deg2rad(ang))]])
        cqs.append((np.array([cx, cy]), R @ np.diag([1 / a**2, 1 / b**2]) @ R.T))
    assert _sizes_fit_spacing(cqs, m, 1.5)
    big = [(c, Q / 4.0) for c, Q in cqs[:1]] + cqs[1:]  # one ring twice as large
    assert not _sizes_fit_spacing(big, m, 1.5)
    assert not _sizes_fit_spacing([(c, Q * 9.0) for c, Q in cqs], m, 1.5)  # all three a third


@pytest.mark.parametrize(
    ("minor", "width", "plate", "even", "due"),
    [
        (30.0, 13.0, False, 0.4, True),  # over 0.4 of the minor semi-axis
        (30.0, 13.0, False, 0.8, True),  # ... whatever blurred the edges
        (30.0, 10.0, False, 0.4, True),  # a third of it and 10 px wide, sharp across the motion: long blur
        (30.0, 10.0, False, 0.8, False),  # ... but as wide all round: defocus, not motion
        (13.0, 4.4, False, 0.4, False),  # a third of a small one, but 4.4 px: short blur (or a shadow's edge)
        (30.0, 8.0, False, 0.4, False),  # 7.5 px wide but under 0.3 of the minor semi-axis
        (30.0, 8.0, True, 0.4, True),  # ... where the plate's edge reached the rays, half the fractions
    ],
)
def test_the_blur_fit_is_due_for_wide_edges_or_long_blur(minor, width, plate, even, due):
    """The blurred-ring fit's gate: edges wider than ``blur_fit_width`` (0.4) of the smallest
    minor semi-axis, or ``blur_fit_long_width`` (0.3) of it where they are also
    ``blur_fit_long_px`` (7.5 px) wide and uneven around the rings (their widths' 25th
    percentile at most ``blur_fit_long_even`` (0.6) of their 75th); both fractions halved
    where the plate's blurred edge reached the edge fit's rays. Without the long-blur rule
    only the first."""
    marker = Marker()
    scale = minor / marker.outer_radius  # px per mm: circles of this radius, their sizes fitting their spacing
    Q = np.eye(2) / minor**2
    rings = [
        C.Ring(
            c,
            ((0, 0), (2 * minor, 2 * minor), 0),
            ((0, 0), (minor, minor), 0),
            1.0,
            refined=True,
            _outer_cq=(c, Q),
            _edge_width=width,
            _edge_even=even,
            _plate_reached=plate,
        )
        for c in (np.array(marker.centers2d) * scale + 500.0)
    ]
    c = C._merge_conf(None)
    assert C._blur_fit_due(rings, marker, c) is due
    assert C._blur_fit_due(rings, marker, {**c, "blur_fit_long_even": 1.0}) is (
        due or (width >= 7.5 and width >= (0.15 if plate else 0.3) * minor)
    )
    without = C._blur_fit_due(rings, marker, {**c, "blur_fit_long_px": 0.0})
    assert without is (width >= (0.2 if plate else 0.4) * minor)


@pytest.mark.parametrize("shape", [(1024, 1280), (960, 1280), (480, 640)])
def test_the_quarter_inputs_pass_counts_the_noise_estimates_residuals(shape):
    """Where the input is the image's exact quarter, making it also counts the residuals on
    the noise estimate's grid (its stride 4 at 1280x1024 and 1280x960): the histogram
    classical.noise_sigma counts, its sigma the same; the input is unchanged; another
    size leaves the counts zero."""
    from markerpose import classical, keypoints
    from markerpose.images import RESIDUAL_BINS

    rng = np.random.default_rng(3)
    gray = np.clip(rng.normal(120, 9, shape) + np.linspace(0, 80, shape[1])[None], 0, 255).astype(np.uint8)
    gray[100:180, 200:330] //= 3  # an edge or two
    size = (shape[1] // 4, shape[0] // 4)
    counts = np.zeros(RESIDUAL_BINS, np.int64)
    small, scale = keypoints.to_input(gray, size, counts)
    np.testing.assert_array_equal(small, keypoints.to_input(gray, size)[0])
    want = np.zeros(RESIDUAL_BINS, np.int64)
    classical._residual_histogram(gray, 4, want)
    np.testing.assert_array_equal(counts, want)
    if classical.noise_stride(shape) == 4:
        assert classical.noise_from_residuals(counts) == classical.noise_sigma(gray)
    other = np.zeros(RESIDUAL_BINS, np.int64)
    keypoints.to_input(gray, (size[0] - 8, size[1] - 8), other)  # not the exact quarter: nothing counted
    assert not other.any()
