"""markerpose.edges: batched edge sampling and ellipse fits give each ring what it gets alone."""

import numpy as np
import pytest

import markerpose as mp
from markerpose import classical, edges
from markerpose.geometry import rect_to_cq, ring_ellipses
from markerpose.synth import Imaging, look_at_pose, render_stereo


@pytest.mark.parametrize("seed", range(4))
def test_masked_statistics_match_numpy(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(6, 37))
    mask = rng.random((6, 37)) < 0.6
    mask[0] = False  # a row with nothing masked in
    x[1, :10] = 0.5  # ties
    mask[2] = False
    mask[2, 5] = True  # a single entry
    med = edges.masked_median(x, mask, empty=-1.0)
    for k in range(6):
        assert med[k] == (np.median(x[k][mask[k]]) if mask[k].any() else -1.0)
    for q in (0, 10, 25, 50, 75, 99, 100):
        pct = edges.masked_percentile(x, mask, q, empty=-1.0)
        for k in range(6):
            assert pct[k] == (np.percentile(x[k][mask[k]], q) if mask[k].any() else -1.0)


def test_fit_ellipses_batch_matches_single_fits():
    rng = np.random.default_rng(1)
    P, M, W, truth = np.zeros((3, 80, 2)), np.zeros((3, 80), bool), rng.uniform(0.5, 2, (3, 80)), []
    for k, n in enumerate((80, 50, 12)):
        t = rng.uniform(0, 2 * np.pi, n)
        c, a, b, th = rng.uniform(100, 500, 2), rng.uniform(20, 60), rng.uniform(10, 20), rng.uniform(0, np.pi)
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        P[k, :n] = c + (R @ np.stack([a * np.cos(t), b * np.sin(t)])).T + rng.normal(0, 0.05, (n, 2))
        M[k, :n] = True
        truth.append(c)
    cen, Q, ok = edges.fit_ellipses(P, M, W)
    assert ok.all()
    for k in range(3):
        c1, Q1 = classical.fit_ellipse(P[k][M[k]], W[k][M[k]])
        np.testing.assert_allclose(cen[k], c1, atol=1e-9)
        np.testing.assert_allclose(Q[k], Q1, rtol=1e-9)
        assert np.linalg.norm(cen[k] - truth[k]) < 0.1


def test_fit_ellipses_is_exact_on_an_ellipse_and_refuses_degenerate_points():
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    c, a, b, th = np.array([412.3, 287.9]), 55.0, 21.0, 0.7
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    ellipse = c + (R @ np.stack([a * np.cos(t), b * np.sin(t)])).T
    line = np.stack([t, 2 * t + 1], -1)  # collinear
    same = np.full((40, 2), 200.0)  # one point repeated
    P = np.stack([ellipse, line, same, ellipse])
    M = np.ones((4, 40), bool)
    M[3, 5:] = False  # five points: too few
    cen, Q, ok = edges.fit_ellipses(P, M)
    assert ok.tolist() == [True, False, False, False]
    np.testing.assert_allclose(cen[0], c, atol=1e-9)
    np.testing.assert_allclose(Q[0], R @ np.diag([1 / a**2, 1 / b**2]) @ R.T, rtol=1e-9)
    assert classical.fit_ellipse(line) is None


def _seeded_rings(blur: float):
    """The six rings of a rendered pair (blurred along 30° by ``blur`` px), each seed about a
    pixel off its ellipse, and the rendered outer centres per view."""
    rig, mk = mp.StereoRig.default(), mp.Marker()
    T = look_at_pose([10, -5, 520], 30, 40, 15)
    f = render_stereo(rig, T, imaging=Imaging(motion_blur=blur, motion_angle=30), seed=3)
    grays = [classical.to_gray(i) for i in f.images]
    rng = np.random.default_rng(0)
    rings = []
    for cam, Tv in zip(rig.cameras, (T, rig.T_right_left @ T)):
        view = []
        for (cx, cy), (w, h), ang in ring_ellipses(cam, Tv, mk.points3d, mk.outer_radius):
            rect = ((cx + rng.normal(0, 1), cy + rng.normal(0, 1)), (w * 1.03, h * 0.98), ang + 2)
            view.append(classical.Ring(np.array(rect[0]), rect, rect, 1.0, _outer_cq=rect_to_cq(rect)))
        rings.append(view)
    return rig, mk, grays, rings, [v.outer_centers for v in f.views]


@pytest.mark.parametrize("blur", [0.0, 20.0])
def test_a_batch_of_rings_gets_what_each_gets_alone(blur):
    """Six rings of both views refined together equal each ring refined alone (same
    neighbours), sharp and under motion blur; and they land on the true centres."""
    rig, mk, grays, rings, truth = _seeded_rings(blur)
    batch = classical.refine_views(grays, rings, mk, cameras=list(rig.cameras))
    for v in range(2):
        noise = classical.noise_sigma(grays[v])
        for k, ring in enumerate(rings[v]):
            alone = classical.refine_ring(grays[v], ring, mk, None, noise, others=rings[v], camera=rig.cameras[v])
            assert alone.refined and batch[v][k].refined
            np.testing.assert_allclose(batch[v][k].center, alone.center, atol=1e-9)
        if blur == 0:
            assert np.abs(np.array([r.center for r in batch[v]]) - truth[v]).max() < 0.05


def _profiles(seed: int):
    """Random ray profiles of three rings (S = 9, 14, 20 real samples, padded to 20 by
    repeating the last): noisy dark-to-bright steps at random places, some flat."""
    rng = np.random.default_rng(seed)
    S = np.array([9, 14, 20])
    K, N, Sm = 3, 12, 20
    lam = np.empty((K, Sm))
    for k in range(K):
        lam[k] = 1.0 + np.minimum(np.linspace(-0.3, 0.3, S[k]).tolist() + [0.3] * (Sm - S[k]), 0.3)
    dl = lam[:, 1] - lam[:, 0]
    v = np.empty((K, N, Sm))
    for k in range(K):
        edge = rng.uniform(lam[k, 0], lam[k, S[k] - 1], N)
        width = rng.uniform(0.005, 0.2, N)
        prof = 40 + 160 / (1 + np.exp((lam[k, None, : S[k]] - edge[:, None]) / width[:, None]))
        prof += rng.normal(0, 8, prof.shape)
        prof[:2] = 180 + rng.normal(0, 2, (2, S[k]))  # flat: no crossing
        v[k, :, : S[k]] = prof
        v[k, :, S[k] :] = prof[:, -1:]
    v_out = rng.normal(40, 3, (K, N))
    dd = rng.normal(160, 10, (K, N))
    r = rng.uniform(20, 60, (K, N))
    return v, v_out, dd, lam, dl, S, r, rng


@pytest.mark.parametrize("seed", range(3))
def test_ray_kernels_match_a_direct_reading(seed):
    """The compiled per-ray loops give what the definitions say, ray by ray: the 50 %
    crossing nearest the window centre, the run of 10-90 % samples around it, the
    integral of the piecewise-linear profile."""
    v, v_out, dd, lam, dl, S, r, rng = _profiles(seed)
    e, found, width = edges.crossings(v, v_out, dd, lam, dl, S, r)
    xs = (rng.uniform(0.6, 1.4, v.shape[:2]), rng.uniform(0.8, 1.2, v.shape[:2]))
    ints = edges.integral(v, v_out, dd, lam, dl, S, xs)
    assert not found[:, :2].any() and found.sum() > 20
    for k in range(3):
        grid = lam[k, : S[k]]
        for i in range(v.shape[1]):
            f = (v[k, i, : S[k]] - v_out[k, i]) / dd[k, i]
            down = [j for j in range(S[k] - 1) if f[j] >= 0.5 and f[j + 1] < 0.5]
            assert found[k, i] == bool(down)
            if down:
                j = min(down, key=lambda j: abs(j - (S[k] - 1) / 2))
                assert e[k, i] == pytest.approx(grid[j] + dl[k] * (f[j] - 0.5) / (f[j] - f[j + 1]), abs=1e-12)
                plateau = (f <= 0.1) | (f >= 0.9)
                before = max([s for s in range(j + 1) if plateau[s]], default=-1)
                after = min([s for s in range(j + 1, S[k]) if plateau[s]], default=S[k])
                assert width[k, i] == pytest.approx(max(after - before - 1, 0) * dl[k] * r[k, i], abs=1e-12)
            for x, got in zip(xs, ints):
                x = float(np.clip(x[k, i], grid[0], grid[-1]))
                pts = np.r_[grid[grid < x], x]
                fp = np.interp(pts, grid, f)
                assert got[k, i] == pytest.approx(np.sum(0.5 * (fp[1:] + fp[:-1]) * np.diff(pts)), abs=1e-9)


def test_sampled_rays_are_bilinear_samples_and_their_plateaus():
    """Ray samples are :func:`edges.bilinear`'s, clipped at the border, with the mean of
    each ray's first and last m samples."""
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (40, 50), dtype=np.uint8)
    lam = np.tile(np.r_[np.linspace(0.5, 1.5, 11), 1.5, 1.5], (2, 1))
    lam[1, 9:] = lam[1, 8]  # the second ring has 9 real samples
    S, m = np.array([11, 9]), np.array([3, 2])
    cen = np.array([[25.0, 20.0], [45.0, 5.0]])  # the second ring's rays leave the image
    t = rng.uniform(0, 2 * np.pi, (2, 16))
    ux, uy = 10 * np.cos(t), 8 * np.sin(t)
    v, v_in, v_out = np.empty((2, 16, 13)), np.empty((2, 16)), np.empty((2, 16))
    edges._sample_rays(img, np.arange(2), cen[:, 0].copy(), cen[:, 1].copy(), ux, uy, lam, S, m, v, v_in, v_out)
    X = cen[:, 0, None, None] + ux[..., None] * lam[:, None, :]
    Y = cen[:, 1, None, None] + uy[..., None] * lam[:, None, :]
    want = edges.bilinear(img, X, Y)[0]
    np.testing.assert_array_equal(v, want)
    for k in range(2):
        np.testing.assert_allclose(v_in[k], want[k, :, : m[k]].mean(1), rtol=1e-12)
        np.testing.assert_allclose(v_out[k], want[k, :, S[k] - m[k] : S[k]].mean(1), rtol=1e-12)


def test_plane_levels_match_a_direct_reading():
    """The robust plateau planes: the median, then twice the rays within max(3 MAD,
    floor) of the current fit, least squares with the ridge on the gradient; a row with
    fewer than six such rays keeps what it had."""
    rng = np.random.default_rng(11)
    K, N = 4, 40
    xy = rng.uniform(-30, 30, (K, N, 2)) + [100, 50]
    center = np.tile([100.0, 50.0], (K, 1))
    values = 80 + 0.8 * (xy[..., 0] - 100) - 0.3 * (xy[..., 1] - 50) + rng.normal(0, 2, (K, N))
    values[:, :5] += 60  # an occluder's rays
    use = rng.random((K, N)) < 0.9
    use[3] = False
    use[3, :5] = True  # too few rays for a plane
    scale, floor = np.full(K, 20.0), np.full(K, 3.0)
    got = edges.plane_levels(xy, values, use, center, scale, floor)
    for k in range(K):
        A = np.column_stack([np.ones(N), xy[k] - center[k]])
        coef = np.array([np.median(values[k][use[k]]), 0.0, 0.0])
        for _ in range(2):
            res = values[k] - A @ coef
            sel = use[k] & (np.abs(res) <= max(3 * 1.4826 * np.median(np.abs(res[use[k]])), floor[k]))
            if sel.sum() < 6:
                break
            ridge = sel.sum() * (0.15 * scale[k]) ** 2 * np.diag([0.0, 1.0, 1.0])
            coef = np.linalg.solve(A[sel].T @ A[sel] + ridge, A[sel].T @ values[k][sel])
        np.testing.assert_allclose(got[k], A @ coef, rtol=0, atol=1e-9)
    assert np.abs(got[0] - (80 + 0.8 * (xy[0, :, 0] - 100) - 0.3 * (xy[0, :, 1] - 50))).max() < 3  # the occluder ignored


def _lmeds_reference(P, mask, cen, Q, min_px, n_subsets=40):
    """lmeds_inliers written plainly with numpy: every subset's median, then the best."""
    t, off = edges._radial_offsets(P, cen, Q)
    X = np.stack([np.ones_like(t), np.cos(t), np.sin(t), np.cos(2 * t), np.sin(2 * t)], axis=2)
    keep = mask.copy()
    for k in range(len(mask)):
        n = int(mask[k].sum())
        meds, coefs = [], []
        for sub in edges._subsets(n, n_subsets):
            A = X[k, sub]
            if not abs(np.linalg.det(A)) > 1e-6:
                continue
            coefs.append(np.linalg.solve(A, off[k, sub]))
            meds.append(np.median(np.abs(off[k, :n] - X[k, :n] @ coefs[-1])))
        if meds:
            b = int(np.argmin(meds))
            sigma = 1.4826 * (1 + 5.0 / max(n - 5, 1)) * meds[b]
            keep[k] = mask[k] & (np.abs(off[k] - X[k] @ coefs[b]) <= max(2.5 * sigma, min_px))
    return keep


@pytest.mark.parametrize("seed", range(3))
def test_the_least_median_screen_matches_a_plain_numpy_one(seed):
    """Rings' edge points with noise, a spoilt sector on one and outliers: the compiled
    screen (which skips subsets that cannot beat the best) keeps what numpy's plain one
    keeps, and drops the spoilt sector."""
    rng = np.random.default_rng(seed)
    K, N = 4, 120
    P, mask = np.zeros((K, N, 2)), np.zeros((K, N), bool)
    cen, Q = rng.uniform(100, 400, (K, 2)), np.zeros((K, 2, 2))
    for k, n in enumerate((120, 77, 40, 13)):
        a, b = rng.uniform(20, 50), rng.uniform(10, 20)
        Q[k] = np.diag([1 / a**2, 1 / b**2])
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        r = 1 + rng.normal(0, 0.003, n)
        P[k, :n] = cen[k] + np.stack([a * r * np.cos(t), b * r * np.sin(t)], 1)
        mask[k, :n] = True
    P[0, 10:30] += (P[0, 10:30] - cen[0]) * 0.1  # an occluder's sector, 10 % outside
    P[1, rng.choice(77, 8, replace=False)] += rng.normal(0, 5, (8, 2))
    cen_start = cen + rng.normal(0, 0.3, (K, 2))  # near the ellipses, as the edge fit's frame
    keep = edges.lmeds_inliers(P, mask, cen_start, Q, {"outlier_min_px": 0.15})
    np.testing.assert_array_equal(keep, _lmeds_reference(P, mask, cen_start, Q, 0.15))
    assert not keep[0, 10:30].any() and keep[0, 40:].mean() > 0.9


def test_the_least_median_screen_matches_numpy_on_many_small_rings():
    """Small rings of 12 to 15 points, odd and even counts, heavy outliers: where the
    skipping rule could be off by one, the chosen subsets would differ from numpy's."""
    rng = np.random.default_rng(7)
    K, N = 200, 15
    n = rng.integers(12, 16, K)
    t = rng.uniform(0, 2 * np.pi, (K, N))
    r = 30 * (1 + rng.normal(0, 0.01, (K, N))) + np.where(rng.random((K, N)) < 0.3, rng.normal(0, 3, (K, N)), 0)
    P = np.stack([200 + r * np.cos(t), 150 + 0.6 * r * np.sin(t)], -1)
    mask = np.arange(N)[None] < n[:, None]
    cen, Q = np.tile([200.0, 150.0], (K, 1)), np.tile(np.diag([1 / 30**2, 1 / 18**2]), (K, 1, 1))
    keep = edges.lmeds_inliers(P, mask, cen, Q, {"outlier_min_px": 0.15})
    np.testing.assert_array_equal(keep, _lmeds_reference(P, mask, cen, Q, 0.15))


def test_spd2_closed_forms_agree_with_numpy():
    """The 2 x 2 closed forms the edge fit uses (square root, its inverse, eigenvalues)
    equal numpy's eigendecomposition on well- and ill-conditioned matrices."""
    from markerpose.geometry import sqrtm_spd

    rng = np.random.default_rng(3)
    A = rng.normal(size=(500, 2, 2))
    Q = A @ A.transpose(0, 2, 1) + np.logspace(-6, 0, 500)[:, None, None] * np.eye(2)
    for power in (0.5, -0.5):
        M, eig = edges._spd2(Q, power)
        np.testing.assert_allclose(M, sqrtm_spd(Q, power), rtol=1e-9, atol=1e-12 * np.abs(M).max())
        np.testing.assert_allclose(eig, np.linalg.eigvalsh(Q), rtol=1e-9)


def _rings_and_lines(rng, K: int, N: int, outliers: bool) -> tuple:
    """K point sets (K, N, 2) of 8 to N points, valid first (mask (K, N)): every third nearly a
    line or a parabola (its reduced scatter matrix's eigenvalues complex), the others noisy
    rings, with ``outliers`` an eighth of their points thrown off."""
    P, mask = np.zeros((K, N, 2)), np.zeros((K, N), bool)
    t = np.linspace(0, 2 * np.pi, N, endpoint=False)
    for k in range(K):
        n = int(rng.integers(8, N))
        if k % 3 == 2:  # nearly a line or a parabola
            x = rng.normal(size=n) * 20
            P[k, :n] = np.column_stack([x, (0.5 * x if k % 2 else x**2 / 40) + rng.normal(size=n) * 1e-9])
        else:
            a, b = rng.uniform(15, 40), rng.uniform(10, 15)
            P[k, :n] = (
                np.column_stack([a * np.cos(t[:n]), b * np.sin(t[:n])]) + rng.normal(scale=0.05, size=(n, 2)) + rng.uniform(0, 100, 2)
            )
            if outliers:
                P[k, : n // 8] += rng.normal(scale=3, size=(n // 8, 2))
        mask[k, :n] = True
    return P, mask


def test_compiled_robust_fit_equals_numpy_and_falls_back_on_complex_eigenvalues():
    """fit_robust (compiled, ring by ring) gives numpy's batched result exactly, with and
    without the least-median screen, also for point sets whose reduced scatter matrix has
    complex eigenvalues (nearly a parabola or a line): numba's eig refuses those and they
    take numpy's path."""
    rng = np.random.default_rng(1)
    K, N = 12, 40
    P, mask = _rings_and_lines(rng, K, N, outliers=True)
    W = rng.uniform(0.5, 2, (K, N))
    c = {"outlier_k": 3.0, "outlier_min_px": 0.15}
    frame = (P[:, :8].mean(1), np.tile(np.eye(2) / 400, (K, 1, 1)))
    fallback = np.empty(K, bool)
    cnt = mask.sum(1)
    idx = np.stack([edges._subsets(int(n), 40) for n in cnt])
    edges._robust_rows(
        P,
        mask,
        W,
        cnt >= 12,
        frame[0],
        edges._spd2(frame[1], 0.5)[0],
        idx,
        3.0,
        0.15,
        edges._S1,
        edges._S2,
        edges._S3,
        np.empty((K, 2)),
        np.empty((K, 2, 2)),
        np.empty(K, bool),
        np.empty((K, N), bool),
        fallback,
    )
    assert fallback.any() and not fallback.all()
    for fr in (None, frame):
        for got, want in zip(edges.fit_robust(P, mask, c, fr, W), edges._fit_robust_numpy(P, mask, c, fr, W)):
            if got.dtype == bool:
                np.testing.assert_array_equal(got, want)
            else:  # numba's eig and numpy's may come from different LAPACK builds
                np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_compiled_conic_eigenvectors_equal_numpys_also_where_eigenvalues_are_complex():
    """fit_ellipses takes each reduced scatter matrix's eigenvectors from the compiled eig
    where its eigenvalues are real and from numpy's where they are not (nearly a line or a
    parabola): the fits are numpy's batched ones, and a set that is no ellipse is refused."""
    rng = np.random.default_rng(4)
    K, N = 12, 40
    P, mask = _rings_and_lines(rng, K, N, outliers=False)
    W = rng.uniform(0.5, 2, (K, N))
    m, sc, mu = np.empty((K, 2)), np.empty(K), np.empty((K, len(edges._MOMENTS)))
    edges._scatter(P, W, mask, m, sc, mu)
    valid = (mask.sum(1) >= 6) & (sc > 0)
    M, T = np.empty((K, 3, 3)), np.empty((K, 3, 3))
    edges._reduced_scatter(mu, edges._S1, edges._S2, edges._S3, valid, M, T)
    complex_eig = np.array([np.iscomplex(np.linalg.eigvals(M[k])).any() for k in range(K)])
    assert complex_eig.any() and not complex_eig.all()
    want_c, want_Q = np.empty((K, 2)), np.empty((K, 2, 2))
    edges._ellipse_from_conic(np.ascontiguousarray(np.real(np.linalg.eig(M)[1])), T, m, sc, valid, want_c, want_Q)
    cen, Q, ok = edges.fit_ellipses(P, mask, W)
    np.testing.assert_array_equal(ok, valid)
    assert ok[~complex_eig].all()
    np.testing.assert_allclose(cen[ok], want_c[ok], rtol=1e-9, atol=1e-9)  # numba's and numpy's LAPACK builds may differ
    np.testing.assert_allclose(Q[ok], want_Q[ok], rtol=1e-9, atol=1e-15)


def _passes(monkeypatch) -> list:
    """Records, per call of edges.edge_points, how many ellipses it sampled and how many rays each had."""
    calls, real = [], edges.edge_points

    def counted(grays, view, cen, Q, half, dark, c, *rest):
        calls.append((len(cen), c["edge_spacing"]))
        return real(grays, view, cen, Q, half, dark, c, *rest)

    monkeypatch.setattr(edges, "edge_points", counted)
    return calls


def test_a_coarse_first_pass_and_the_predicted_stop_land_where_full_passes_do(monkeypatch):
    """From seeds a pixel off, a first pass on coarse rays and the stop predicted from the
    last two moves give the same centres as full passes to a converged stop (within the
    stopping tolerance), in fewer ray samples; and both land on the true centres."""
    rig, mk, grays, rings, truth = _seeded_rings(0.0)
    calls = _passes(monkeypatch)
    old = classical.refine_views(
        grays, rings, mk, {"first_pass_spacing": 0.0, "refine_predict": False, "rescreen_frac": -1.0}, cameras=list(rig.cameras)
    )
    full = list(calls)
    calls.clear()
    new = classical.refine_views(grays, rings, mk, cameras=list(rig.cameras))
    assert calls[0] == (6, classical.default_conf["first_pass_spacing"]) and all(
        s == classical.default_conf["edge_spacing"] for _, s in calls[1:]
    )
    assert sum(n for n, _ in calls[1:]) < sum(n for n, _ in full)  # fewer full-density ellipse passes
    for v in range(2):
        a, b = np.array([r.center for r in old[v]]), np.array([r.center for r in new[v]])
        assert np.abs(a - b).max() < 0.01
        assert np.abs(b - truth[v]).max() < 0.05


def test_a_coarse_first_pass_is_discarded_on_blurred_edges(monkeypatch):
    """Under heavy blur the coarse pass's fit is not taken (wide edges need every ray): the
    full passes start from the seeds and give exactly what they give without it."""
    rig, mk, grays, rings, _ = _seeded_rings(25.0)
    calls = _passes(monkeypatch)
    plain = classical.refine_views(grays, rings, mk, {"first_pass_spacing": 0.0, "blur_fit": False}, cameras=list(rig.cameras))
    n_plain = len(calls)
    coarse = classical.refine_views(grays, rings, mk, {"blur_fit": False}, cameras=list(rig.cameras))
    assert len(calls) - n_plain == n_plain + 1  # the coarse pass, then the same full passes
    for v in range(2):
        for a, b in zip(plain[v], coarse[v]):
            assert a.refined == b.refined
            np.testing.assert_array_equal(a.center, b.center)


def _screens(monkeypatch) -> list:
    """Records, per call of edges.fit_robust, which ellipses it screened by least median."""
    calls, real = [], edges.fit_robust

    def recorded(P, mask, c, frame=None, weights=None, screen=None):
        calls.append(np.ones(len(mask), bool) if screen is None else np.array(screen, bool))
        return real(P, mask, c, frame, weights, screen)

    monkeypatch.setattr(edges, "fit_robust", recorded)
    return calls


def test_a_close_seed_is_screened_only_where_its_first_fit_rejects_points(monkeypatch):
    """Seeds known to be close (a tracker's prediction: refine_first_tol > 0) take their
    first fit without the least-median screen: on clean rings one pass and the centres of
    a screened fit; where an occluder spoils a sector of one ring, that ring alone gets a
    screened pass after, and lands where a fit screened from the start does."""
    rig, mk = mp.StereoRig.default(), mp.Marker()
    T = look_at_pose([10, -5, 520], 30, 40, 15)
    f = render_stereo(rig, T, imaging=Imaging(), seed=3)
    grays = [classical.to_gray(i) for i in f.images]
    rings = []
    for cam, Tv in zip(rig.cameras, (T, rig.T_right_left @ T)):
        rects = ring_ellipses(cam, Tv, mk.points3d, mk.outer_radius)
        rings.append([classical.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=rect_to_cq(r)) for r in rects])
    close = {"refine_first_tol": 0.15}
    calls = _screens(monkeypatch)
    screened = classical.refine_views(grays, rings, mk, {**close, "close_seed_screen": True}, cameras=list(rig.cameras))
    calls.clear()
    plain = classical.refine_views(grays, rings, mk, close, cameras=list(rig.cameras))
    assert len(calls) == 1 and not calls[0].any()  # one pass, no screen
    for v in range(2):
        a, b = np.array([r.center for r in screened[v]]), np.array([r.center for r in plain[v]])
        assert np.abs(a - b).max() < 1e-3
    # An occluder's straight edge across the outer edge of c0 in the left view.
    (cx, cy), (w, h), _ = rings[0][0].outer
    r = 0.5 * max(w, h)
    spoilt = [g.copy() for g in grays]
    spoilt[0][int(cy - 0.4 * r) : int(cy + 0.4 * r), int(cx + 0.8 * r) : int(cx + 1.4 * r)] = 20.0
    calls.clear()
    screened = classical.refine_views(spoilt, rings, mk, {**close, "close_seed_screen": True}, cameras=list(rig.cameras))
    calls.clear()
    plain = classical.refine_views(spoilt, rings, mk, close, cameras=list(rig.cameras))
    assert not calls[0].any() and len(calls) >= 2 and calls[1].tolist() == [True]  # c0 of the left view alone, screened
    assert np.linalg.norm(plain[0][0].center - screened[0][0].center) < 0.02
    assert np.linalg.norm(plain[0][0].center - f.views[0].outer_centers[0]) < 0.1


def test_plate_lines_measure_the_distance_inside_a_quadrilateral():
    corners = np.array([[10.0, 20.0], [110.0, 20.0], [110.0, 80.0], [10.0, 80.0]])
    for order in (corners, corners[::-1]):  # either way round
        L = edges.plate_lines(order)
        d = np.array([[60.0, 50.0], [12.0, 50.0], [60.0, 90.0]]) @ L[:, :2].T + L[:, 2]
        assert d.min(axis=1) == pytest.approx([30.0, 2.0, -10.0])


def test_the_plate_sides_follow_the_rings_pose():
    """Through the pose of the rings' centres and ellipses, the sides pass within 2 px of
    the projected plate corners (the ellipses' centres are not their circles' projected
    centres: a pixel at the far corner), tilted or not; the affine map of the centres alone
    is that close only in a frontal view."""
    rig, mk = mp.StereoRig.default(), mp.Marker(margin=3.0)
    for T, tol_affine in ((look_at_pose([0.0, 0.0, 560.0]), 0.5), (look_at_pose([30.0, -20.0, 450.0], 45, 30, 20), None)):
        rects = ring_ellipses(rig.left, T, mk.points3d, mk.outer_radius)
        rings = [classical.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=rect_to_cq(r)) for r in rects]
        corners = rig.left.project(mk.plate_corners3d @ T[:3, :3].T + T[:3, 3])
        for camera, tol in ((rig.left, 2.0), (None, tol_affine)):
            if tol is None:
                continue
            L = classical.plate_sides(rings, mk, camera)
            d = corners @ L[:, :2].T + L[:, 2]  # each corner lies on its two sides
            assert max(abs(d[i, i]) for i in range(4)) < tol and max(abs(d[i, i - 1]) for i in range(4)) < tol
    assert classical.plate_sides(rings[:2], mk) is None and classical.plate_sides([rings[0], None, rings[2]], mk) is None


@pytest.mark.parametrize("margin", [3.0, 2.0])
def test_a_tight_plate_on_a_dark_ground_does_not_pull_the_blurred_rings(margin):
    """A plate cut 2-3 mm beyond the rings on a dark ground, blurred 19-21 px along c0 -> c1:
    what lies beyond the plate reaches into the rings' outer edges. Taken in by the edge
    fit (kept there under the blur gate 0.4 alone), it pulls c0 and c1 apart by a quarter
    of a pixel or more; with the plate's edge left out (its rays, and the blurred-ring fit,
    which takes over there, its pixels) the distance c0-c1 in each view is within 0.05 px
    and every centre within 0.1 px. Edges this wide (over 7.5 px) go to the blurred-ring
    fit at the gate 0.3 by default, so even where the plate is not known the distance is
    within 0.1 px at 21 px."""
    rig, mk = mp.StereoRig.default(), mp.Marker(margin=margin)
    T = look_at_pose([0.0, 0.0, 560.0])
    ground = tuple(np.full(c.image_size[::-1], 0.05, np.float32) for c in rig.cameras)
    ells = [ring_ellipses(cam, Tv, mk.points3d, mk.outer_radius) for cam, Tv in zip(rig.cameras, (T, rig.T_right_left @ T))]
    for L in (19.0, 21.0):
        f = render_stereo(rig, T, mk, Imaging(alpha=0.7, motion_blur=L, motion_angle=0.0), ground, seed=5)
        d01, worst = {}, {}
        for name, conf in (
            ("edge fit, plate taken in", {"plate_edge": False, "blur_fit_long_px": 0.0}),
            ("default", {}),
            ("plate unknown", {"plate_edge": False}),
        ):
            out = classical.refine_ellipses_views(f.images, ells, mk, conf, list(rig.cameras))
            assert all(o[1].all() for o in out)
            d01[name] = max(
                abs(np.linalg.norm(o[0][1] - o[0][0]) - np.linalg.norm(v.outer_centers[1] - v.outer_centers[0]))
                for o, v in zip(out, f.views)
            )
            worst[name] = max(np.abs(o[0] - v.outer_centers).max() for o, v in zip(out, f.views))
        assert d01["edge fit, plate taken in"] > 0.25 and d01["default"] < 0.05 and worst["default"] < 0.1, (L, d01)
        if L == 21.0:
            assert d01["plate unknown"] < 0.1, d01


@pytest.mark.parametrize(("imaging", "uneven"), [({"motion_blur": 14.0, "motion_angle": 30}, True), ({"psf_sigma": 2.5}, False)])
def test_the_edge_widths_tell_motion_blur_from_defocus(imaging, uneven):
    """Motion blur widens the edges along the motion only: their 10-90 % widths' 25th
    percentile is well under their 75th (the edges across the motion stay sharp). Defocus
    widens every edge alike: the two are near each other. The rings of both views, refined."""
    rig, mk = mp.StereoRig.default(), mp.Marker()
    T = look_at_pose([10, -5, 520], 30, 40, 15)
    f = render_stereo(rig, T, imaging=Imaging(**imaging), seed=3)
    grays = [classical.to_gray(i) for i in f.images]
    rings = [
        [classical.Ring(np.array(r[0]), r, r, 1.0, _outer_cq=rect_to_cq(r)) for r in ring_ellipses(cam, Tv, mk.points3d, mk.outer_radius)]
        for cam, Tv in zip(rig.cameras, (T, rig.T_right_left @ T))
    ]
    refined = [r for view in classical.refine_views(grays, rings, mk, cameras=list(rig.cameras)) for r in view]
    assert all(r.refined for r in refined)
    even = np.array([r._edge_even for r in refined])
    assert (even < 0.55).all() if uneven else (even > 0.7).all(), even.round(2)
