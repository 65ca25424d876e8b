"""Tests of the blurred-ring model fit (markerpose.blurfit) and its use by the classical
refinement (classical.refine_blurred).

Measured while writing these tests (renderer, 25 px motion blur, rings 30-40 px in
radius): edge fit alone up to ~1.5 px off along the motion; the model fit <= 0.08 px.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from markerpose import Marker, MarkerPose, StereoRig, blurfit, synth
from markerpose import classical as C
from markerpose import geometry as geo
from markerpose.nets import default_weights

RHO = Marker().inner_diameter / Marker().outer_diameter


def _ellipse(a=30.0, b=18.0, ang=0.4, c=(60.3, 55.7)):
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    return np.array(c), R @ np.diag([1 / a**2, 1 / b**2]) @ R.T


@pytest.mark.parametrize("theta, L", [(0.3, 0.0), (1.1, 12.0), (2.7, 30.0)])
def test_blurred_disk_keeps_the_area_and_its_centroid(theta, L):
    # Blur moves no ink: the sum over a fine grid is the ellipse's area, its centroid the centre.
    c, Q = _ellipse()
    ys, xs = np.mgrid[0:120:0.25, 0:120:0.25]
    v = blurfit.blurred_disk(xs.ravel(), ys.ravel(), c, Q, theta, L, 0.8).reshape(xs.shape)
    area = v.sum() * 0.25**2
    assert area == pytest.approx(np.pi * 30 * 18, rel=2e-3)
    assert (v * xs).sum() / v.sum() == pytest.approx(c[0], abs=0.01)
    assert (v * ys).sum() / v.sum() == pytest.approx(c[1], abs=0.01)
    # Within [0, 1] up to the normal CDF's rational approximation (1.5e-7, times sigma / L).
    assert v.max() <= 1 + 1e-6 and v.min() >= -1e-6


@pytest.mark.parametrize("theta, L, sigma", [(0.3, 0.5, 0.6), (1.1, 12.0, 0.9), (0.4, 30.0, 1.4)])
def test_blurred_disk_is_its_lines_chords_over_the_box_everywhere(theta, L, sigma):
    """With bare lines, each point's value is the three Gauss-Hermite lines' chords
    overlapping the box, smoothed by sigma along it: computed here point by point, on a grid
    that holds points deep inside and far outside the blurred ellipse (the kernel settles
    those without their lines) and every point between."""
    from scipy.stats import norm

    c, Q = _ellipse()
    ys, xs = np.mgrid[10:110:1.3, 10:110:1.3]
    x, y = xs.ravel(), ys.ravel()
    got = blurfit.blurred_disk(x, y, c, Q, theta, L, sigma, smooth=0.0)
    u, n = np.array([np.cos(theta), np.sin(theta)]), np.array([-np.sin(theta), np.cos(theta)])
    G = lambda t: t * norm.cdf(t) + norm.pdf(t)  # noqa: E731
    want = np.zeros(len(x))
    for tau, w in zip(np.sqrt(3.0) * np.array([-1.0, 0.0, 1.0]), [1 / 6, 2 / 3, 1 / 6]):
        d = np.stack([x, y], 1) + tau * sigma * n - c
        A, B, Cq = u @ Q @ u, d @ Q @ u, np.einsum("ni,ij,nj->n", d, Q, d) - 1
        r = np.sqrt(np.maximum(B * B - A * Cq, 0.0))
        s1, s2 = (-B - r) / A, (-B + r) / A
        v = (G((L / 2 - s1) / sigma) - G((-L / 2 - s1) / sigma) - G((L / 2 - s2) / sigma) + G((-L / 2 - s2) / sigma)) * sigma / L
        want += w * np.where(B * B - A * Cq > 0, v, 0.0)
    assert (want > 1 - 1e-9).sum() > 100 and (want < 1e-9).sum() > 100  # both kinds of settled points
    assert np.abs(got - want).max() < 1e-6


@pytest.mark.parametrize("box", [1, 3])
def test_blurred_disk_derivatives_match_finite_differences(box):
    c, Q = _ellipse()
    ys, xs = np.mgrid[0:120:1.0, 0:120:1.0]
    x, y = xs.ravel(), ys.ravel()
    th, L, s = 0.7, 17.0, 0.9
    _, J = blurfit.blurred_disk(x, y, c, Q, th, L, s, jac=True, box=box)

    def f(c=c, Q=Q, th=th, L=L, s=s):
        return blurfit.blurred_disk(x, y, c, Q, th, L, s, box=box)

    h = 1e-5
    e = np.eye(2)
    numeric = {
        "cx": ((f(c=c + h * e[0]) - f(c=c - h * e[0])) / (2 * h), J["c"][:, 0]),
        "cy": ((f(c=c + h * e[1]) - f(c=c - h * e[1])) / (2 * h), J["c"][:, 1]),
        "L": ((f(L=L + h) - f(L=L - h)) / (2 * h), J["L"]),
        "sigma": ((f(s=s + h) - f(s=s - h)) / (2 * h), J["sigma"]),
        "theta": ((f(th=th + h) - f(th=th - h)) / (2 * h), J["theta"]),
    }
    for name, (num, ana) in numeric.items():
        # Chords tangent to the ellipse have a square-root singularity, clipped in the
        # analytic derivative: compare in norm.
        assert np.linalg.norm(ana - num) < 0.06 * np.linalg.norm(num), name


def test_a_blocks_mean_is_modelled_by_four_points_and_nearer_than_by_its_centre():
    """The block model is the mean of the point model at (+-h, +-h), h^2 = 2/3 for 3 x 3
    pixels, and it is nearer the true 3 x 3 mean of the point model than the point model
    is with any Gaussian."""
    c, Q = _ellipse()
    ys, xs = np.mgrid[0:120:1.0, 0:120:1.0]
    x, y = xs.ravel(), ys.ravel()
    th, L, s = 0.79, 9.0, 0.6
    h = blurfit.block_offset(3)
    assert h == pytest.approx(np.sqrt(2 / 3)) and blurfit.block_offset(1) == 0.0
    four = np.mean([blurfit.blurred_disk(x + dx, y + dy, c, Q, th, L, s) for dx in (-h, h) for dy in (-h, h)], axis=0)
    model = blurfit.blurred_disk(x, y, c, Q, th, L, s, box=3)
    assert np.abs(model - four).max() < 1e-12
    block = np.mean([blurfit.blurred_disk(x + dx, y + dy, c, Q, th, L, s) for dx in (-1, 0, 1) for dy in (-1, 0, 1)], axis=0)
    best = min(np.sqrt(np.mean((blurfit.blurred_disk(x, y, c, Q, th, L, g) - block) ** 2)) for g in np.linspace(0.5, 1.5, 21))
    assert np.sqrt(np.mean((model - block) ** 2)) < 0.5 * best


def test_small_blurred_rings_fit_the_same_from_any_start():
    """Far rings (15 px in radius) under 8 px of blur, from starts up to 2 px off: with the
    blocks' means modelled and the lines smoothed near the tangents, the fits agree with each
    other to a few thousandths of a pixel and with the truth to two hundredths; the model of
    the blocks' centres ends farther from the truth, where the sparse samples fall on the
    sharp edges, and bare lines (a cost with cusps) settle in different cusps."""
    rig = StereoRig.default()
    T = synth.look_at_pose([40, -30, 1400], 40, 60, 30)
    img, truth = synth.render_view(rig.left, T, imaging=synth.Imaging(alpha=0.6, motion_blur=8, motion_angle=20), seed=1)
    gray = C.to_gray(img)
    base = [geo.rect_to_cq(r) for r in _truth_rects(truth)]
    shifts = [(0, 0), (1.1, 0.4), (-0.9, 0.7), (0.5, -1.2), (-1.3, -0.8), (2.0, 1.0)]
    worst, nfev = {}, {}
    # The step counts compare derivatives taken at every iterate (frozen ones take more, cheaper steps).
    exact = {"jac_once_length": np.inf}
    variants = {"default": {}, "centres": {"block_fit": False}, "exact": exact, "bare": {**exact, "tangent_smooth": 0.0}}
    for name, conf in variants.items():
        fits = [blurfit.fit_blurred_rings(gray, [(c + np.array(d), Q) for c, Q in base], RHO, C.noise_sigma(gray), conf) for d in shifts]
        centres = np.array([[c for c, _ in f["cqs"]] for f in fits])
        spread = max(np.linalg.norm(a - b, axis=1).max() for a in centres for b in centres)
        worst[name] = (spread, np.linalg.norm(centres - truth.outer_centers, axis=2).max())
        nfev[name] = sum(f["nfev"] for f in fits)
    assert worst["default"][0] < 0.005 and worst["default"][1] < 0.02, worst
    assert worst["centres"][1] > worst["default"][1], worst
    assert worst["bare"][0] > 4 * worst["default"][0] and worst["bare"][1] > 1.5 * worst["default"][1], worst
    assert worst["exact"][0] < 0.005 and abs(worst["exact"][1] - worst["default"][1]) < 0.002, worst
    assert nfev["exact"] < 0.8 * nfev["bare"], nfev  # a smooth cost: fewer steps


def test_smoothed_tangents_leave_no_cusp_as_the_ellipse_moves():
    """A line across the motion that meets the ellipse's tangent opens a chord as a square
    root: bare lines give the model an unbounded slope there as the centre moves across the
    motion; smoothed near the tangents the slope stays bounded, and away from them the two
    models agree."""
    c, Q = _ellipse()
    th, L, sig = 0.4, 12.0, 0.7  # the motion along the ellipse's major axis
    n = np.array([-np.sin(th), np.cos(th)])
    # Samples on lines near the tangent (the minor semi-axis, 18 px, across the motion).
    pts = c + np.array([[t * np.cos(th), t * np.sin(th)] for t in np.linspace(-8, 8, 9)]) + 18.0 * n
    steps = np.arange(-0.5, 0.5, 1e-3)
    slope = {}
    for kap in (0.0, 0.5):
        v = np.array([blurfit.blurred_disk(pts[:, 0], pts[:, 1], c + d * n, Q, th, L, sig, smooth=kap) for d in steps])
        slope[kap] = np.abs(np.diff(v, axis=0)).max() / 1e-3
    assert slope[0.5] < 1.5 and slope[0.0] > 3 * slope[0.5], slope
    inner = c + 6.0 * n  # far inside: the chords are long, the lines' smoothing does not reach
    a, b = (blurfit.blurred_disk(inner[:1], inner[1:], c, Q, th, L, sig, smooth=k) for k in (0.0, 0.5))
    assert a == pytest.approx(b, abs=1e-4)
    with pytest.raises(ValueError, match="tangent_smooth"):
        blurfit.blurred_disk(inner[:1], inner[1:], c, Q, th, L, sig, smooth=1.0)


def test_the_normal_cdf_and_its_antiderivative_match_erfc():
    """The model's normal CDF (a rational tail times the density's exp) against
    math.erfc, its density exactly, and G = t Phi + phi."""
    import math

    for t in np.linspace(-7.0, 7.0, 2801):
        G, P, p = blurfit._normal(t)
        exact = 0.5 * math.erfc(-t / math.sqrt(2))
        if abs(t) < 5:
            assert abs(P - exact) < 1.5e-7, t
            assert p == pytest.approx(math.exp(-0.5 * t * t) / math.sqrt(2 * math.pi), rel=1e-14)
            assert abs(G - (t * exact + p)) < 3e-7  # the antiderivative, from the exact CDF
        else:  # the limits
            assert (G, P, p) == (max(t, 0.0), float(t > 0), 0.0)


@pytest.fixture(scope="module")
def blurred_view():
    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 720], 35, 60, 30)
    bg = synth.clutter_background((1280, 1024), np.random.default_rng(0), ring_distractors=0)
    img, truth = synth.render_view(rig.left, T, imaging=synth.Imaging(alpha=0.6, motion_blur=25, motion_angle=70), background=bg, seed=3)
    return rig, img, truth


def _truth_rects(truth):
    out = []
    for C3 in truth.outer_conics:
        A, b = C3[:2, :2], C3[:2, 2]
        c0 = -np.linalg.solve(A, b)
        out.append(geo.cq_to_rect(c0, A / -(C3[2, 2] + b @ c0)))
    return out


def _pixels_reference(prob, reach, stride, motion):
    """(x, y, v) of the pixels :meth:`blurfit._Problem.pixels` selects on its grid, by numpy
    and OpenCV: the grid's tests as whole arrays, the block means by cv2.blur of the grid's
    crop."""
    import cv2

    forms, (x0, y0, x1, y1) = prob.grid(reach, stride)  # the grid's extent is pixels()'s own
    yy, xx = np.mgrid[y0 : y1 + 1 : stride, x0 : x1 + 1 : stride]
    inside = np.zeros(xx.shape, bool)
    for c, Qx in forms:
        dx, dy = xx - c[0], yy - c[1]
        C = Qx[0, 0] * dx * dx + 2 * Qx[0, 1] * dx * dy + Qx[1, 1] * dy * dy - 1
        if motion is None:
            inside |= C <= 0
            continue
        u = np.array([np.cos(motion[0]), np.sin(motion[0])])
        Qu = Qx @ u
        B = dx * Qu[0] + dy * Qu[1]
        disc = B * B - (u @ Qu) * C
        r = np.sqrt(np.maximum(disc, 0))
        s1, s2 = (-B - r) / (u @ Qu), (-B + r) / (u @ Qu)
        inside |= (disc > 0) & (s1 <= 0.5 * motion[1]) & (s2 >= -0.5 * motion[1])
    for a, bb, c0 in [] if prob.plate is None else prob.plate:
        along = 0.5 * motion[1] * abs(a * np.cos(motion[0]) + bb * np.sin(motion[0])) if motion is not None else reach
        inside &= a * xx + bb * yy + c0 > along + blurfit.PLATE_SLACK_PX
    yi, xi = yy[inside], xx[inside]
    if prob.box == 1:
        return xi, yi, prob.gray[yi, xi].astype(np.float64)
    r = prob.box // 2
    ya, xa = max(y0 - r, 0), max(x0 - r, 0)
    crop = np.asarray(prob.gray[ya : y1 + r + 1, xa : x1 + r + 1], np.float32)
    return xi, yi, cv2.blur(crop, (prob.box, prob.box))[yi - ya, xi - xa].astype(np.float64)


@pytest.mark.parametrize("box", [1, 3, 5])
@pytest.mark.parametrize("at_border", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
def test_the_compiled_pixel_selection_is_numpys(box, at_border, dtype):
    """The compiled grid selection and block means are those of whole-array tests and
    OpenCV's box filter, with and without the motion and the plate's sides, also where the
    rings' reach passes the image's border."""
    rng = np.random.default_rng(box + 10 * at_border)
    gray = (rng.random((240, 320)) * 255).astype(dtype)
    shift = -25.0 if at_border else 60.0
    cqs = [(np.array([shift + 40.0 + 35 * j, 90.0 + 9 * j]), np.array([[1 / 14.0**2, 0.0004], [0.0004, 1 / 11.0**2]])) for j in range(3)]
    plate = np.array([[1.0, 0.0, 20.0], [-1.0, 0.0, 300.0], [0.0, 1.0, 10.0], [0.0, -1.0, 230.0]])
    for pl in (None, plate):
        prob = blurfit._Problem(gray, cqs, 0.5, 2.0, box=box, plate=pl)
        for reach, stride, motion in ((13.0, 4, None), (4.0, 3, (0.7, 23.0)), (4.0, 1, (2.9, 9.0))):
            prob.pixels(reach, stride=stride, motion=motion)
            x, y, v = _pixels_reference(prob, reach, stride, motion)
            assert len(x) > 50
            np.testing.assert_array_equal(prob.x, x)
            np.testing.assert_array_equal(prob.y, y)
            np.testing.assert_array_equal(prob.v, v)


def test_model_fit_finds_the_motion_and_the_centres(blurred_view):
    rig, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [geo.rect_to_cq(r) for r in _truth_rects(truth)]
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in start]  # off like an edge fit
    fit = blurfit.fit_blurred_rings(gray, start, RHO, C.noise_sigma(gray))
    assert fit is not None
    assert fit["length"] == pytest.approx(25.0, abs=1.0)
    assert abs(np.degrees(fit["theta"]) - 70.0) < 1.5
    err = np.linalg.norm(np.array([c for c, _ in fit["cqs"]]) - truth.outer_centers, axis=1)
    assert err.max() < 0.1, err


def test_starts_a_pixel_apart_fit_the_same_samples(blurred_view):
    """The fit's samples lie on a grid fixed in the image (multiples of the stride), not
    one that moves with the start: starts a pixel or two apart fit the same data and end
    where each other ends."""
    rig, img, truth = blurred_view
    gray = C.to_gray(img)
    base = [geo.rect_to_cq(r) for r in _truth_rects(truth)]
    ends = []
    for d in [(0.0, 0.0), (1.4, -0.7), (-0.6, 1.9), (2.2, 1.1)]:
        fit = blurfit.fit_blurred_rings(gray, [(c + np.array(d), Q) for c, Q in base], RHO, C.noise_sigma(gray))
        ends.append(np.array([c for c, _ in fit["cqs"]]))
    spread = max(np.linalg.norm(a - b, axis=1).max() for a in ends for b in ends)
    assert spread < 0.005, spread


def test_frozen_derivatives_and_a_sparser_search_end_where_the_exact_fit_does(blurred_view, monkeypatch):
    """The block model's derivatives taken once (its centres move by hundredths of a pixel)
    and the coarse search on a grid a fifth of the rings' minor semi-axis apart: the fit ends
    within a thousandth of a pixel or two of the one with derivatives at every iterate and
    the search every 4 px, and computes derivatives fewer times."""
    rig, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in (geo.rect_to_cq(r) for r in _truth_rects(truth))]
    strides = []
    pixels = blurfit._Problem.pixels
    monkeypatch.setattr(
        blurfit._Problem, "pixels", lambda self, reach, stride=1, motion=None: strides.append(stride) or pixels(self, reach, stride, motion)
    )
    fits, jacs = {}, {}
    for name, conf in {"default": {}, "exact": {"jac_once_length": np.inf, "grid_stride_frac": 0.0}}.items():
        fit = blurfit.fit_blurred_rings(gray, start, RHO, C.noise_sigma(gray), conf)
        fits[name], jacs[name] = np.array([c for c, _ in fit["cqs"]]), fit["njev"]
    assert strides[0] > 4 and strides[2] == 4  # the rings' minor semi-axes are over 25 px
    assert np.abs(fits["default"] - fits["exact"]).max() < 2e-3
    assert 0 < jacs["default"] < jacs["exact"], jacs
    assert np.linalg.norm(fits["default"] - truth.outer_centers, axis=1).max() < 0.1


def test_the_search_along_the_axes_agrees_with_the_full_grid(blurred_view, monkeypatch):
    rig, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in (geo.rect_to_cq(r) for r in _truth_rects(truth))]
    costed = []
    costs = blurfit._motion_costs
    monkeypatch.setattr(blurfit, "_motion_costs", lambda *a: (costed.append(len(a[-1])), costs(*a))[1])
    fits = {}
    for search in ("full", "axes"):
        costed.clear()
        fits[search] = blurfit.fit_blurred_rings(gray, start, RHO, C.noise_sigma(gray), conf={"grid_search": search})
        fits[search + " grid"] = sum(costed)  # the (direction, length) pairs costed
    assert fits["full grid"] == 8 * 3 and fits["axes grid"] == 8 + 2
    a, b = (np.array([c for c, _ in fits[k]["cqs"]]) for k in ("full", "axes"))
    assert np.abs(a - b).max() < 0.01
    assert fits["axes"]["length"] == pytest.approx(fits["full"]["length"], abs=0.05)
    with pytest.raises(ValueError, match="grid_search"):
        blurfit.fit_blurred_rings(gray, start, RHO, 2.0, conf={"grid_search": "random"})


def _numpy_coarse(prob, base, c):
    """The coarse search of :func:`blurfit._coarse_motion` written with the problem's numpy
    methods, one evaluation per (theta, L), the first of least cost kept (Python's min)."""

    def cost(th, L):
        p = base.copy()
        p[-3], p[-2] = th, np.log(L)
        r = prob.evaluate(p)[0]
        return float(r @ r), p

    angles, lengths = np.arange(c["grid_angles"]) * np.pi / c["grid_angles"], c["grid_lengths"]
    smooth, prob.smooth = prob.smooth, 0.0
    try:
        if c["grid_search"] == "full":
            best = min((cost(th, L) for th in angles for L in lengths), key=lambda t: t[0])
        else:
            middle = sorted(lengths)[len(lengths) // 2]
            best = min((cost(th, middle) for th in angles), key=lambda t: t[0])
            best = min([best] + [cost(best[1][-3], L) for L in lengths if L != middle], key=lambda t: t[0])
    finally:
        prob.smooth, prob._kept = smooth, None
    return best[1]


def _numpy_lm(prob, p, conf):
    """The robust Levenberg-Marquardt loop of :func:`blurfit._robust_lm` written with the
    problem's own numpy methods: the reference of the compiled loop."""
    f2 = conf["loss_scale"] ** 2
    start = prob.centers(p).copy()
    r = prob.evaluate(p, keep=True)[0]
    lam, nfev, last = 1e-3, 1, np.inf
    for _ in range(conf["max_iter"]):
        prob.w = 1 / (1 + r * r / f2)
        r, _, (H, g) = prob.evaluate(p, jac=True)
        E = float(prob.w @ (r * r))
        D = np.diag(H).copy()
        D[D <= 0] = 1.0
        nfev += 1
        while True:
            step = np.linalg.solve(H + lam * np.diag(D), -g)
            trial = p + step
            if prob.frozen is not None and np.abs(prob.centers(step)).max() > conf["jac_move"]:
                prob.frozen, prob.freeze = None, True
            try:
                rt = prob.evaluate(trial, keep=True)[0]
                Et = float(prob.w @ (rt * rt))
            except ValueError:
                Et = np.inf
            nfev += 1
            if Et < E:
                break
            lam *= 10
            if lam > 1e8:
                return p, nfev, False
        small = (
            E - Et <= conf["ftol"] * E
            or np.all(np.abs(step) <= conf["xtol"] * (np.abs(p) + conf["xtol"]))
            or np.abs(prob.centers(step)).max() <= conf["center_tol"]
        )
        move = np.abs(prob.centers(step)).max()
        if conf["center_predict"] and not small and move < last < np.inf:  # the steps to come, a geometric series
            small = move * (move / last) / (1 - move / last) <= conf["center_tol"]
        p, r, last = trial, rt, move
        if conf["max_move"] and np.linalg.norm(prob.centers(p) - start, axis=1).max() > conf["max_move"]:
            return p, nfev, True
        lam = max(lam / 10, 1e-7)
        if small:
            break
    return p, nfev, False


def test_the_predicted_stop_saves_the_confirming_step(blurred_view):
    """``center_predict``: the fit stops once the steps still to come, extrapolated from the
    last two, fall under ``center_tol``: fewer model evaluations, the same centres to well
    under that tolerance."""
    _, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in (geo.rect_to_cq(r) for r in _truth_rects(truth))]
    noise = C.noise_sigma(gray)
    fits = [blurfit.fit_blurred_rings(gray, start, RHO, noise, {"center_predict": p}) for p in (True, False)]
    assert fits[0]["nfev"] < fits[1]["nfev"]
    a, b = (np.array([c for c, _ in f["cqs"]]) for f in fits)
    assert np.abs(a - b).max() < 0.5 * blurfit.default_conf["center_tol"]
    assert np.linalg.norm(a - truth.outer_centers, axis=1).max() < 0.05


@pytest.mark.parametrize(
    "conf",
    [
        {},
        {"jac_once_length": np.inf},
        {"jac_once_length": 1.0, "jac_move": 1e-3},
        {"block_fit": False, "tangent_smooth": 0.0},
        {"max_move": 0.5},
        {"grid_search": "full"},
        {"center_predict": False},
    ],
)
def test_the_compiled_fit_is_the_numpy_loop(blurred_view, monkeypatch, conf):
    """The compiled optimiser (:func:`blurfit._lm_kernel`) and coarse search
    (:func:`blurfit._motion_costs`) against their numpy writing: the same steps (model
    evaluations, derivatives frozen and taken anew, giving up) to round-off, and the same
    state left for the covariances (the robust weights, the kept model)."""
    _, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in (geo.rect_to_cq(r) for r in _truth_rects(truth))]
    noise = C.noise_sigma(gray)
    compiled = blurfit.fit_blurred_rings(gray, start, RHO, noise, conf)
    searched = []

    def numpy_search(prob, base, c):
        searched.append((prob, base))
        return _numpy_coarse(prob, base, c)

    monkeypatch.setattr(blurfit, "_coarse_motion", numpy_search)
    monkeypatch.setattr(blurfit, "_robust_lm", _numpy_lm)
    reference = blurfit.fit_blurred_rings(gray, start, RHO, noise, conf)
    assert compiled["nfev"] == reference["nfev"] and compiled["gave_up"] == reference["gave_up"]
    assert compiled["njev"] == reference["njev"] > 0
    a, b = (np.array([np.r_[c, Q.ravel()] for c, Q in f["cqs"]]) for f in (compiled, reference))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled["center_covs"], reference["center_covs"], rtol=1e-7)
    for key in ("theta", "length", "sigma", "rms", "contrast"):
        assert compiled[key] == pytest.approx(reference[key], rel=1e-9, abs=1e-12), key
    if conf.get("max_move"):
        assert compiled["gave_up"]  # started 1 px off: the bound is met, and the loop says so
    # The coarse grid's costs (on the fit's pixels and weights, left in the problem).
    prob, base = searched[0]
    th, L = np.arange(8) * np.pi / 8, np.array([6.0, 14.0, 26.0, np.exp(12.5)])
    costs, status = blurfit._motion_costs(
        prob.x,
        prob.y,
        prob.xs,
        prob.ys,
        prob.v,
        prob.w,
        prob.noise,
        base,
        prob.k,
        prob.rho**2,
        prob.scale**2,
        th,
        np.log(L[th.argsort() % 4]),
    )
    prob.smooth, prob.block, prob._kept = 0.0, False, None  # the search's model: bare lines at the samples' centres
    for t, lL, cost in zip(th, np.log(L[th.argsort() % 4]), costs):
        p = base.copy()
        p[-3], p[-2] = t, lL
        if lL > 12:  # out of the model's range: the costs stop there, as the model raises
            with pytest.raises(ValueError):
                prob.evaluate(p)
            assert status == blurfit._BAD_START and np.isnan(cost)
            break
        r = prob.evaluate(p)[0]
        assert cost == pytest.approx(float(r @ r), rel=1e-12)
    else:
        pytest.fail("the out-of-range length was not reached")


def test_a_nan_pixel_fails_the_fit_without_raising(blurred_view):
    """A float32 image with a NaN beside a ring: the coarse search's costs are NaN (no
    error), and the fit then finds its levels singular: None, as the numpy loop gave."""
    _, img, truth = blurred_view
    gray = C.to_gray(img).astype(np.float32)
    cqs = [geo.rect_to_cq(r) for r in _truth_rects(truth)]
    c = cqs[0][0]
    gray[int(c[1]), int(c[0])] = np.nan
    assert blurfit.fit_blurred_rings(np.ascontiguousarray(gray), cqs, RHO, 2.0) is None


@pytest.mark.parametrize("block", [False, True])
def test_the_problems_derivatives_match_finite_differences(blurred_view, block):
    """The whole problem's model (every ring's outer and white disks, the white disk's
    offset, the shared motion and sigma, in the fit's parametrisation): each column of its
    derivatives against central differences of its values, at the samples' centres and as
    the blocks' means."""
    _, img, truth = blurred_view
    prob = blurfit._Problem(C.to_gray(img), [geo.rect_to_cq(r) for r in _truth_rects(truth)], RHO, 2.0, box=3)
    assert prob.pixels(6.0, stride=3, motion=(np.radians(70), 30.0))
    prob.block = block
    p = prob.start()
    p[-3], p[-2] = np.radians(68), np.log(22.0)
    p[5:7] = 0.3, -0.2  # the first white disk off its ring's centre
    _, J = prob.model(p, True)
    for a in range(len(p)):
        e = np.zeros(len(p))
        e[a] = 1e-5
        prob._kept = None
        numeric = (prob.model(p + e)[0] - prob.model(p - e)[0]) / 2e-5
        assert np.linalg.norm(J[:, a] - numeric) < 0.06 * np.linalg.norm(numeric) + 1e-9, a


def test_the_normal_equations_equal_those_of_the_projected_jacobian(blurred_view):
    """evaluate() forms H and g without the variable-projection Jacobian Jr: they equal
    Jr^T W Jr and Jr^T W r computed from Jr itself, under arbitrary robust weights."""
    _, img, truth = blurred_view
    gray = C.to_gray(img)
    prob = blurfit._Problem(gray, [geo.rect_to_cq(r) for r in _truth_rects(truth)], RHO, 2.0)
    assert prob.pixels(6.0, stride=3, motion=(np.radians(70), 30.0))
    p = prob.start()
    p[-3], p[-2] = np.radians(68), np.log(22.0)
    prob.w = np.random.default_rng(1).uniform(0.05, 1.0, len(prob.v))
    r, beta, (H, g) = prob.evaluate(p, jac=True)
    R, J = prob.model(p, True)
    xs, ys, w = prob.xs, prob.ys, prob.w
    M = np.column_stack([np.ones_like(xs), xs, ys, R, R * xs, R * ys])
    Jm = J * ((beta[3] + beta[4] * xs + beta[5] * ys) / prob.noise)[:, None]
    Mw = M * w[:, None]
    Jr = Jm - M @ np.linalg.solve(Mw.T @ M, Mw.T @ Jm)
    np.testing.assert_allclose(H, Jr.T @ (Jr * w[:, None]), rtol=1e-7, atol=1e-9 * np.abs(H).max())
    np.testing.assert_allclose(g, Jr.T @ (w * r), rtol=1e-7, atol=1e-9 * np.abs(g).max())


def _numpy_lag_inflation(x, y, stride, r):
    """The residuals' lag-one correlation inflation written with numpy: a NaN grid of the
    samples, then each axis's neighbouring pairs where both are set."""
    ix, iy = np.round((x - x.min()) / stride).astype(int), np.round((y - y.min()) / stride).astype(int)
    grid = np.full((iy.max() + 1, ix.max() + 1), np.nan)
    grid[iy, ix] = r
    f = 1.0
    for a, b in ((grid[:, 1:], grid[:, :-1]), (grid[1:], grid[:-1])):
        both = np.isfinite(a) & np.isfinite(b)
        if both.sum() >= 10:
            rho = np.clip((a[both] * b[both]).sum() / np.sqrt((a[both] ** 2).sum() * (b[both] ** 2).sum()), 0.0, 0.9)
            f *= (1 + rho) / (1 - rho)
    return f


@pytest.mark.parametrize("smooth", [0.0, 0.6, 0.97])
def test_the_compiled_correlation_inflation_is_numpys(blurred_view, smooth):
    """The covariances' inflation for residuals correlated between neighbouring samples
    (:func:`blurfit._correlation_inflation`, compiled) against its numpy writing, on the
    fit's own grid of samples (holes between the rings, a ragged border) and on residuals
    from white (no inflation but chance) to strongly correlated (clipped at rho 0.9)."""
    _, img, truth = blurred_view
    prob = blurfit._Problem(C.to_gray(img), [geo.rect_to_cq(r) for r in _truth_rects(truth)], RHO, 2.0)
    assert prob.pixels(6.0, stride=3, motion=(np.radians(70), 30.0))
    rng = np.random.default_rng(4)
    # A misfit that spans many samples (a slow wave over the grid) in white noise.
    r = smooth * 3.0 * np.sin(prob.x / 15.0 + prob.y / 25.0) + (1 - smooth) * rng.normal(size=len(prob.x))
    got = blurfit._correlation_inflation(prob, r)
    assert got == pytest.approx(_numpy_lag_inflation(prob.x, prob.y, 3.0, r), rel=1e-12)
    assert got >= 1.0
    if smooth > 0.9:
        assert got > 15.0  # (1 + 0.9) / (1 - 0.9) per axis at the clip
    # Too few pairs along both axes: no inflation.
    assert blurfit._correlation_inflation(prob, np.where(np.arange(len(r)) < 8, r, np.nan)) == 1.0


def test_a_pixel_cap_samples_sparser_and_still_fits(blurred_view, monkeypatch):
    """Above ``max_pixels`` the fit samples a sparser grid: fewer pixels, the same answer
    to a fraction of a pixel (what keeps a large decoy from costing seconds)."""
    _, img, truth = blurred_view
    gray = C.to_gray(img)
    start = [(c + np.array([0.8, -0.6]), Q) for c, Q in (geo.rect_to_cq(r) for r in _truth_rects(truth))]
    used = []
    lm = blurfit._robust_lm

    def counted(prob, p, conf):
        used.append(len(prob.v))
        return lm(prob, p, conf)

    monkeypatch.setattr(blurfit, "_robust_lm", counted)
    full = blurfit.fit_blurred_rings(gray, start, RHO, C.noise_sigma(gray))
    capped = blurfit.fit_blurred_rings(gray, start, RHO, C.noise_sigma(gray), conf={"max_pixels": used[0] // 3})
    assert used[2] <= used[0] // 3 < used[0] == used[1]  # each fit's two stages (the blocks' centres, then means) on its pixels
    err = np.linalg.norm(np.array([c for c, _ in capped["cqs"]]) - truth.outer_centers, axis=1)
    assert err.max() < 0.2, err
    assert full is not None


def test_a_start_that_missed_the_rings_is_given_up_by_the_move_bound(blurred_view, monkeypatch):
    """``max_move``: a fit whose centres wander beyond it stops early with None (a start
    that missed the rings); from a close start the bound changes nothing."""
    _, img, truth = blurred_view
    gray = C.to_gray(img)
    cqs = [geo.rect_to_cq(r) for r in _truth_rects(truth)]
    close = [(c + np.array([0.8, -0.6]), Q) for c, Q in cqs]
    free = blurfit.fit_blurred_rings(gray, close, RHO, C.noise_sigma(gray))
    bounded = blurfit.fit_blurred_rings(gray, close, RHO, C.noise_sigma(gray), conf={"max_move": 6.0})
    np.testing.assert_array_equal(np.array([c for c, _ in free["cqs"]]), np.array([c for c, _ in bounded["cqs"]]))
    calls = []
    lm = blurfit._robust_lm

    def counted(prob, p, conf):
        out = lm(prob, p, conf)
        calls.append(out)
        return out

    # Started 8 px off, the fit must move farther than 2 px: the optimiser itself gives up,
    # and says so, with a centre beyond the bound where it stopped.
    off = [(c + np.array([8.0, 0.0]), Q) for c, Q in cqs]
    monkeypatch.setattr(blurfit, "_robust_lm", counted)
    stopped = blurfit.fit_blurred_rings(gray, off, RHO, C.noise_sigma(gray), conf={"max_move": 2.0})
    assert calls[0][2] and stopped["gave_up"] and not free["gave_up"]
    moved = np.linalg.norm(np.array([c for c, _ in stopped["cqs"]]) - np.array([c for c, _ in off]), axis=1)
    assert moved.max() > 2.0


def test_detections_report_the_motion_blur():
    """``Detection.blur_px``: the blur length the blurred-ring fit found, in both views of
    a blurred pair; 0 for a sharp pair (no model fit ran)."""
    from markerpose import MarkerPose

    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 700], 30, 60, 30)
    tracker = MarkerPose(rig)
    for blur in (25.0, 0.0):
        f = synth.render_stereo(rig, T, imaging=synth.Imaging(alpha=0.6, motion_blur=blur, motion_angle=110), seed=4)
        est = tracker.estimate(*f.images)
        assert est is not None
        for d in est.detections:
            assert d.blur_px == (pytest.approx(blur, abs=1.5) if blur else 0.0)


def test_refinement_under_heavy_blur_beats_the_edge_fit(blurred_view):
    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    edge, ok_e, _ = C.refine_ellipses(img, rects, camera=rig.left, conf={"blur_fit": False})
    model, ok_m, _ = C.refine_ellipses(img, rects, camera=rig.left)
    e_edge = np.linalg.norm(edge - truth.outer_centers, axis=1)
    e_model = np.linalg.norm(model - truth.outer_centers, axis=1)
    assert ok_m.all() and e_model.max() < 0.1, e_model
    assert e_model.max() < e_edge.max(), (e_model, e_edge)


def _fit_moving(monkeypatch, ring, by, gave_up=False):
    """blurfit.fit_blurred_rings, with ring ``ring``'s fitted centre moved by ``by`` px."""
    fit = blurfit.fit_blurred_rings

    def moved(*args, **kwargs):
        out = fit(*args, **kwargs)
        c, Q = out["cqs"][ring]
        out["cqs"][ring] = (c + np.array([by, 0.0]), Q)
        return {**out, "gave_up": gave_up}

    monkeypatch.setattr(blurfit, "fit_blurred_rings", moved)


@pytest.mark.parametrize("by, gave_up", [(4.0, False), (7.0, True)])
def test_a_blur_fit_that_disagrees_with_the_edge_fit_refines_no_ring(blurred_view, monkeypatch, by, gave_up):
    # Under heavy blur the edge fit can be pixels off along the motion; when the blur
    # model puts an edge-fitted ring farther from it than the bound (or goes that far and
    # gives up), neither fit is kept: the rings come back unrefined rather than at the
    # edge fit's centres (a wrong pose). Every path that refines rings says so.
    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    _, ok, _ = C.refine_ellipses(img, rects, camera=rig.left)
    assert ok.all()
    _fit_moving(monkeypatch, 1, by, gave_up)
    _, ok, _ = C.refine_ellipses(img, rects, camera=rig.left)
    assert not ok.any()
    _, found, _ = C.refine_points(img, truth.outer_centers, Marker(), camera=rig.left)
    assert not found.any()
    gray = C.to_gray(img)
    rings = C.refine_views(
        [gray],
        [[C.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=geo.rect_to_cq(r)) for r in rects]],
        Marker(),
        C.default_conf,
        [C.noise_sigma(gray)],
        [rig.left],
    )[0]
    det = C.refine_triple(gray, rings, (0, 1, 2), 0.0, Marker(), True, {}, C.noise_sigma(gray), rig.left)
    assert not det.refined.any()


def test_wide_edges_the_blur_fit_may_not_check_refine_no_ring(blurred_view):
    # The fit is due (edges smeared to the black band's width) but the detection's budget
    # of fits is spent, or the ring-evidence gate refuses the rings: the edge fit alone is
    # not trusted under that much blur, so no ring counts as refined.
    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    for limits in (C.BlurLimits(budget=C.FitBudget(0)), C.BlurLimits(gate=lambda gray, centres: False)):
        _, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, limits=limits)
        assert not ok.any(), limits
    budget = C.FitBudget(1)  # one fit left: it runs, and refines the rings
    _, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, limits=C.BlurLimits(budget=budget))
    assert ok.all() and budget.left == 0


def test_the_views_blur_fits_side_by_side_give_each_views_own(blurred_view):
    """refine_ellipses_views runs two views' blurred-ring fits at once: each view's rings
    are, to the bit, what its fit alone gives; the budget goes to the views in their
    order (one fit left: the first view's rings refine, the second's are not trusted)."""
    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    flipped = np.ascontiguousarray(img[:, ::-1])
    rects_flipped = [((1279 - c[0], c[1]), axes, -ang) for c, axes, ang in rects]
    views = C.refine_ellipses_views([img, flipped], [rects, rects_flipped], detail=True)
    for got, (im, r) in zip(views, ((img, rects), (flipped, rects_flipped))):
        alone = C.refine_ellipses_views([im], [r], detail=True)[0]
        assert got[1].all() and got[3] > 20
        for a, b in zip(got[:2] + got[3:4], alone[:2] + alone[3:4]):
            np.testing.assert_array_equal(a, b)
    budget = C.FitBudget(1)
    views = C.refine_ellipses_views([img, flipped], [rects, rects_flipped], limits=C.BlurLimits(budget=budget))
    assert views[0][1].all() and not views[1][1].any() and budget.left == 0


@pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped weights")
def test_a_detection_without_blur_fits_left_gives_no_pose_under_heavy_blur():
    # The same 25 px-blurred pair: found with the default budget of blurred-ring fits;
    # with none left, its wide edges are not trusted, and no pose comes back (with why).
    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 720], 35, 60, 30)
    frame = synth.render_stereo(rig, T, imaging=synth.Imaging(alpha=0.6, motion_blur=25, motion_angle=70), seed=3)
    est = MarkerPose(rig).estimate(*frame.images)
    assert est is not None and np.linalg.norm(est.t - T[:3, 3]) < 0.05 and min(d.blur_px for d in est.detections) > 20
    tracker = MarkerPose(rig, refine={"max_blur_fits": 0})
    assert tracker.estimate(*frame.images) is None
    assert "not refined" in tracker.why and "could not run" in tracker.why


def test_a_seed_without_edges_that_goes_astray_keeps_the_edge_fit(blurred_view, monkeypatch):
    # A ring the edge fit gave up on has no edge-fitted centre to disagree with: when only
    # its seed moves far, the rings the edge fit refined keep their centres.
    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    gray = C.to_gray(img)
    rings = C.refine_views(
        [gray],
        [[C.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=geo.rect_to_cq(r)) for r in rects]],
        Marker(),
        C.default_conf,
        [C.noise_sigma(gray)],
        [rig.left],
    )[0]
    assert all(r.refined for r in rings)
    rings[2] = replace(rings[2], refined=False)
    _fit_moving(monkeypatch, 2, 4.0)
    out = C.refine_blurred(gray, rings, Marker(), noise=C.noise_sigma(gray))
    assert [r.refined for r in out] == [True, True, False] and not any(r._rejected for r in out)
    assert all(np.array_equal(a.center, b.center) for a, b in zip(out, rings))


def test_sharp_images_keep_the_edge_fit():
    # Without blur the model fit does not run: identical results with it switched off.
    rig = StereoRig.default()
    T = synth.look_at_pose([0, 0, 600], 30, 20, 10)
    img, truth = synth.render_view(rig.left, T, imaging=synth.Imaging(motion_blur=6, motion_angle=20), seed=1)
    rects = _truth_rects(truth)
    a, _, _ = C.refine_ellipses(img, rects, camera=rig.left)
    b, _, _ = C.refine_ellipses(img, rects, camera=rig.left, conf={"blur_fit": False})
    np.testing.assert_array_equal(a, b)
    # Nor does a spent budget of fits matter there: the edge fit stands.
    c, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, limits=C.BlurLimits(budget=C.FitBudget(0)))
    assert ok.all()
    np.testing.assert_array_equal(a, c)


def test_blurred_rings_stop_their_edge_passes_early_and_keep_their_centres(blurred_view, monkeypatch):
    """Edges wider than the blur fit's threshold take at most ``blur_fit_edge_passes``
    edge-fit passes (the blurred-ring fit refits those rings): the centres come out as
    without the limit, since each takes the lens correction of its own fitted ellipse,
    not of the edge points the passes left (biased along the motion)."""
    from markerpose import edges

    rig, img, truth = blurred_view
    rects = _truth_rects(truth)
    calls = []
    edge_points = edges.edge_points
    monkeypatch.setattr(edges, "edge_points", lambda *a, **k: calls.append(1) or edge_points(*a, **k))
    out = {}
    for passes in (0, 1, 2):
        calls.clear()
        conf = {"blur_fit_edge_passes": passes, "blur_fit_motion_passes": 0}  # wide edges' limit alone
        cen, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, conf=conf)
        assert ok.all()
        out[passes] = (cen, len(calls))
    assert out[1][1] == 2 and out[2][1] == 3 and out[0][1] > 6, out  # the first, coarse pass and the full ones
    for passes in (1, 2):
        np.testing.assert_allclose(out[passes][0], out[0][0], atol=2e-3)
        assert np.linalg.norm(out[passes][0] - truth.outer_centers, axis=1).max() < 0.05


def test_motion_blur_stops_the_edge_passes_where_the_blur_fit_takes_the_rings(blurred_view, monkeypatch):
    """Edges under ``blur_fit_width`` but long motion blur (``blur_fit_long_*``: wide in px,
    a good part of the ring, uneven around it) go to the blurred-ring fit as well, so their
    edge passes stop after ``blur_fit_motion_passes``; where the widths are too even for that
    rule (a stricter ``blur_fit_long_even``) the edge fit is kept and runs to convergence.
    The first of those passes is the coarse one (``blur_fit_motion_coarse``), whose fit
    other wide edges discard: the model's fit settles from there as from a full pass."""
    from markerpose import edges

    rig = StereoRig.default()
    T = synth.look_at_pose([0, 0, 650], 20, 40, 10)
    img, truth = synth.render_view(rig.left, T, imaging=synth.Imaging(alpha=0.6, motion_blur=18, motion_angle=30), seed=2)
    rects = _truth_rects(truth)
    calls, edge_points = [], edges.edge_points

    def spy(*a, **k):
        out = edge_points(*a, **k)
        calls.append((out[4] / edges._semi_axes(a[3]).min(1), out[4], out[7]))  # widths / minor, widths px, evenness
        return out

    monkeypatch.setattr(edges, "edge_points", spy)
    centres = []
    for coarse in (True, False):
        calls.clear()
        cen, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, conf={"blur_fit_motion_coarse": coarse})
        ratio, px, even = calls[-1]
        assert np.all((0.3 < ratio) & (ratio < 0.4)) and px.min() > 7.5 and even.max() < 0.6, calls[-1]  # the long-blur rule's case
        assert ok.all() and len(calls) == (1 if coarse else 2)  # the coarse pass kept, or it and one full one
        assert np.linalg.norm(cen - truth.outer_centers, axis=1).max() < 0.05
        centres.append(cen)
    assert np.abs(centres[0] - centres[1]).max() < 0.01
    calls.clear()
    _, ok, _ = C.refine_ellipses(img, rects, camera=rig.left, conf={"blur_fit_long_even": 0.4})
    assert ok.all() and len(calls) > 2
    # Edges wider than blur_fit_width take blur_fit_motion_passes where uneven as motion
    # blur's, but blur_fit_edge_passes where even enough to be, say, a soft focus, which the
    # model's box misfits (here: the 25 px blur's edges, with blur_fit_long_even under
    # their evenness).
    rig, img, truth = blurred_view
    counts = []
    for conf in ({}, {"blur_fit_long_even": 0.3}):
        calls.clear()
        _, ok, _ = C.refine_ellipses(img, _truth_rects(truth), camera=rig.left, conf=conf)
        ratio, _, even = calls[-1]
        assert ok.all() and ratio.min() > 0.4 and 0.3 < even.min() < 0.6, calls[-1]
        counts.append(len(calls))
    # (a ring whose edges are less even than the rest stops a pass later)
    assert counts[0] <= 2 + C.default_conf["blur_fit_motion_passes"] < counts[1] == 1 + C.default_conf["blur_fit_edge_passes"], counts


def test_a_fitted_ellipses_lens_correction_is_the_edge_fits_on_sharp_rings():
    # A sharp ring's edge fit refits its undistorted edge points: the centre of its
    # ellipse's own points, undistorted and refitted, is the same.
    rig = StereoRig.default()
    T = synth.look_at_pose([-110, -40, 600], 35, 20, 10)  # towards a corner: the lens bends more
    img, truth = synth.render_view(rig.left, T, seed=4)
    seeds = [C.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=geo.rect_to_cq(r)) for r in _truth_rects(truth)]
    rings = C.refine_views([C.to_gray(img)], [seeds], Marker(), {**C.default_conf, "blur_fit": False}, [1.0], [rig.left])[0]
    assert all(r.refined for r in rings)
    ideal = C._ideal_centres([r._outer_cq for r in rings], rig.left)
    shift = np.linalg.norm(np.array([r.center for r in rings]) - np.array([r._outer_cq[0] for r in rings]), axis=1)
    assert shift.min() > 0.01, shift  # the correction is not nothing here
    np.testing.assert_allclose(ideal, [r.center for r in rings], atol=1e-3)


def test_fit_refuses_rings_outside_the_image():
    gray = np.full((100, 100), 200.0, np.float32)
    far = (np.array([500.0, 500.0]), np.eye(2) / 30**2)
    assert blurfit.fit_blurred_rings(gray, [far, far, far], RHO, 2.0) is None


def test_pipeline_option_switches_the_blur_fit():
    # MarkerPose(rig, refine={"blur_fit": False}) keeps the edge fit; the default refits: closer to the truth.
    from markerpose import MarkerPose

    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 700], 30, 60, 30)
    f = synth.render_stereo(rig, T, imaging=synth.Imaging(alpha=0.6, motion_blur=25, motion_angle=110), seed=4)
    err = {}
    for on in (True, False):
        est = MarkerPose(rig, detector="classical", refine={"blur_fit": on}).estimate(*f.images)
        assert est is not None
        err[on] = max(np.linalg.norm(d.centers - v.outer_centers, axis=1).max() for d, v in zip(est.detections, f.views))
    assert err[True] < 0.15 and err[True] < err[False], err


def test_the_blocks_setting_reaches_the_blurred_ring_fit(monkeypatch):
    """refine={"blur_blocks": False} fits the samples' centres alone (the former model): the
    same motion found, the centres apart by a few hundredths of a pixel."""
    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 700], 30, 60, 30)
    f = synth.render_stereo(rig, T, imaging=synth.Imaging(alpha=0.6, motion_blur=25, motion_angle=110), seed=4)
    seen, fit = [], blurfit.fit_blurred_rings
    monkeypatch.setattr(blurfit, "fit_blurred_rings", lambda *a: (seen.append(a[4]["block_fit"]), fit(*a))[1])
    est = {on: MarkerPose(rig, refine={"blur_blocks": on}).estimate(*f.images) for on in (True, False)}
    assert seen and set(seen) == {True, False}
    assert all(d.blur_px == pytest.approx(25, abs=2) for e in est.values() for d in e.detections)
    moved = max(np.abs(a.centers - b.centers).max() for a, b in zip(est[True].detections, est[False].detections))
    assert 0 < moved < 0.1


def test_the_tangents_setting_reaches_the_blurred_ring_fit(monkeypatch):
    """refine={"blur_tangents": False} fits with bare lines across the motion."""
    rig = StereoRig.default()
    T = synth.look_at_pose([10, -10, 700], 30, 60, 30)
    f = synth.render_stereo(rig, T, imaging=synth.Imaging(alpha=0.6, motion_blur=25, motion_angle=110), seed=4)
    seen, fit = [], blurfit.fit_blurred_rings
    monkeypatch.setattr(blurfit, "fit_blurred_rings", lambda *a: (seen.append(a[4].get("tangent_smooth")), fit(*a))[1])
    est = {on: MarkerPose(rig, refine={"blur_tangents": on}).estimate(*f.images) for on in (True, False)}
    assert set(seen) == {None, 0.0}
    moved = max(np.abs(a.centers - b.centers).max() for a, b in zip(est[True].detections, est[False].detections))
    assert 0 < moved < 0.1


@pytest.mark.parametrize("damage", ["dark occluder", "bright strip"])
def test_damaged_blurred_rings_give_flags_or_right_centres(blurred_view, damage):
    # Something across a blurred ring: a ring is either flagged as not refined or its
    # centre is right (the robust weights let the model ignore what it cannot explain).
    rig, img, truth = blurred_view
    im = img.copy()
    cx, cy = truth.outer_centers[0]
    if damage == "dark occluder":
        im[:, : int(cx)] = np.minimum(im[:, : int(cx)], 30)
    else:
        im[int(cy) - 60 : int(cy) + 60, int(cx) - 10 : int(cx) + 10] = 250
    centers, ok, _ = C.refine_ellipses(im, _truth_rects(truth), camera=rig.left)
    err = np.linalg.norm(centers - truth.outer_centers, axis=1)
    assert ok.any()
    assert np.all(err[ok] < 0.15), (ok, err)


def test_a_tracker_is_compiled_before_its_first_frame():
    """Constructing the pipeline compiles (or loads) the compiled kernels, so that a live
    stream's first frames, sharp or blurred, do not stall on it (a fresh process: in this
    one other tests have run them already)."""
    import subprocess
    import sys

    code = """
import numba
import markerpose as mp
from markerpose import blurfit, camera, classical, edges, evidence, geometry, keypoints, rigcheck
inner = ("_select", "_normal", "_median", "sorted_stat", "_bilinear", "_step32", "_nan_stat32", "_unit32", "_lu_solve", "_lu_solve_det", "_real_eigvecs", "_add_disk_row", "_plane_normal_equations", "_eliminate3", "_disk_kernel", "_smooth_sqrt", "_cholesky", "_cholesky_solve", "_centre_step",
         "distort_point", "undistort_point", "_undistort_pairs", "_least_singular_vector", "triangulate_ideal", "_ideal", "_symmetric_drop",
         "_ray_frame", "_normalisers", "_first_look", "_neighbours", "_plate_rays", "_compact", "_ray_levels", "_ray_edges", "_shared_covs")  # called only from other kernels, compiled into them
kernels = [v for m in (edges, camera, geometry, blurfit, classical, rigcheck, keypoints, evidence) for name, v in vars(m).items()
           if isinstance(v, numba.core.registry.CPUDispatcher) and name not in inner]
before = any(k.signatures for k in kernels)
rig = mp.StereoRig.default()
tracker = mp.MarkerPose(rig)
built = [len(k.signatures) for k in kernels]
from markerpose.synth import Imaging, look_at_pose, render_stereo
T = look_at_pose([0, 0, 560], 30, 45, 10)
for blur in (0.0, 20.0):
    images = render_stereo(rig, T, imaging=Imaging(motion_blur=blur), seed=1).images
    tracker.estimate(*images)
    tracker.track(*images)
    tracker.track(*images)
added = [k.py_func.__name__ for k, n in zip(kernels, built) if len(k.signatures) != n]
print(len(kernels), before, all(built), ",".join(added) or "-")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True).stdout
    n, before, after, added = out.split()
    assert int(n) >= 10 and before == "False" and after == "True"
    assert added == "-", f"compiled only at a frame, not when the pipeline was built: {added}"


def test_a_read_only_install_without_a_home_still_runs():
    """Where numba finds nowhere to write its cache (a read-only install, no writable
    home: here forced by a locator that never applies), the loops compile per process
    instead of failing at import."""
    import os
    import subprocess
    import sys

    code = """
import numpy as np
import markerpose as mp
from markerpose import edges
mp.MarkerPose(mp.StereoRig.default())
print(edges.masked_median(np.array([[3.0, 1.0, 2.0]]), np.ones((1, 3), bool))[0])
"""
    env = {**os.environ, "NUMBA_CACHE_LOCATOR_CLASSES": "numba.core.caching.IPythonCacheLocator"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["2.0"]
