"""Stereo matching of stage-1 candidates by the marker's 3D shape (markerpose.matching)."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.classical import refine_points
from markerpose.geometry import ring_ellipses, rotation_angle, signed_areas, view_poses
from markerpose.stages.match import matched_triples, side_lengths, stereo_triples, transfer, view_triples
from markerpose.synth import look_at_pose


def _project(rig, T, pts_marker):
    X = pts_marker @ T[:3, :3].T + T[:3, 3]
    return rig.project(X)  # (2, N, 2)


def _cands(pix, scores):
    return np.column_stack([pix, scores])


def test_side_lengths_of_the_default_marker():
    np.testing.assert_allclose(side_lengths(mp.Marker().points3d), [25.0, 40.0, np.hypot(25, 40)])


@pytest.mark.parametrize("seed", range(5))
def test_finds_the_marker_among_decoys_in_id_order(rig, seed):
    rng = np.random.default_rng(seed)
    m = mp.Marker()
    T = look_at_pose(
        [rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(380, 750)], rng.uniform(0, 50), rng.uniform(0, 360), rng.uniform(0, 360)
    )
    true = _project(rig, T, m.points3d)
    # Decoys: random 3D points near the marker (seen in both views, on their epipolar
    # lines) and image points with no partner; stage-1 noise of ~1 px on the true ones.
    decoys3d = T[:3, 3] + rng.uniform(-80, 80, (6, 3))
    dec = rig.project(decoys3d)
    noise = rng.normal(0, 1.0, (2, 3, 2))
    left = np.vstack([true[0] + noise[0], dec[0], rng.uniform(0, 1280, (4, 2))])
    right = np.vstack([true[1] + noise[1], dec[1], rng.uniform(0, 1280, (4, 2))])
    order_l, order_r = rng.permutation(len(left)), rng.permutation(len(right))
    sl = rng.uniform(0.1, 0.9, len(left))
    sl[:3] = 0.3  # the marker's rings do not score best
    found = stereo_triples(rig, _cands(left[order_l], sl[order_l]), _cands(right[order_r], sl[order_r]), m.points3d)
    assert found, "the marker was not matched"
    pl, pr, score = found[0]
    assert np.abs(pl - true[0]).max() < 5 and np.abs(pr - true[1]).max() < 5  # right points, c0 c1 c2
    assert 0 < score <= 0.3
    assert all(f[2] <= score for f in found)


@pytest.mark.parametrize("seed", range(4))
def test_a_subsets_triples_are_the_full_sets_that_it_holds(rig, seed):
    """The triples of a subset of the candidates (another tool's rings taken out) are, in
    the same order and to the bit, those of all the candidates that use none of the
    removed ones: what each tool's detection takes from one matching per call."""
    rng = np.random.default_rng(seed)
    m = mp.Marker()
    views = [[], []]
    for _ in range(3):  # three markers of one layout and decoys: many triples, ties of order
        T = look_at_pose([rng.uniform(-80, 80), rng.uniform(-60, 60), rng.uniform(450, 700)], rng.uniform(0, 40), rng.uniform(0, 360), 0)
        for v, p in enumerate(_project(rig, T, m.points3d)):
            views[v].append(p + rng.normal(0, 0.5, p.shape))
    decoys = rig.project(np.array([0, 0, 560.0]) + rng.uniform(-90, 90, (6, 3)))
    left, right = (np.vstack(views[v] + [decoys[v]]) for v in (0, 1))
    cl, cr = _cands(left, rng.uniform(0.2, 0.9, len(left))), _cands(right, rng.uniform(0.2, 0.9, len(right)))
    pl, pr, score, il, ir = matched_triples(rig, cl, cr, m.points3d)
    assert len(score) >= 3 and np.all(np.diff(score) <= 0)
    np.testing.assert_array_equal(pl, cl[il, :2])
    for removed in (rng.choice(len(cl), 3, replace=False), np.arange(3), np.arange(len(cl) - 2)):
        keep_l = np.ones(len(cl), bool)
        keep_l[removed] = False
        keep_r = rng.random(len(cr)) > 0.2
        want = stereo_triples(rig, cl[keep_l], cr[keep_r], m.points3d, max_triples=99)
        ok = keep_l[il].all(1) & keep_r[ir].all(1)
        assert len(want) == ok.sum()
        for (a, b, sc), x, y, z in zip(want, pl[ok], pr[ok], score[ok]):
            np.testing.assert_array_equal(a, x)
            np.testing.assert_array_equal(b, y)
            assert sc == z


def test_rejects_wrong_shape_and_mirror_image(rig):
    m = mp.Marker()
    T = look_at_pose([0, 0, 500], 20, 30, 0)
    # A triangle 30 % too large: no triple.
    big = _project(rig, T, 1.3 * m.points3d)
    assert stereo_triples(rig, _cands(big[0], np.full(3, 0.9)), _cands(big[1], np.full(3, 0.9)), m.points3d) == []
    # The mirror image (same side lengths, other handedness): no triple.
    mirror = m.points3d * np.array([-1.0, 1.0, 1.0])
    mir = _project(rig, T, mirror)
    assert stereo_triples(rig, _cands(mir[0], np.full(3, 0.9)), _cands(mir[1], np.full(3, 0.9)), m.points3d) == []
    # The true marker with the same scores is found.
    ok = _project(rig, T, m.points3d)
    assert len(stereo_triples(rig, _cands(ok[0], np.full(3, 0.9)), _cands(ok[1], np.full(3, 0.9)), m.points3d)) == 1


def test_needs_three_matched_candidates(rig):
    m = mp.Marker()
    T = look_at_pose([0, 0, 500], 0, 0, 0)
    p = _project(rig, T, m.points3d)
    assert stereo_triples(rig, _cands(p[0][:2], np.ones(2)), _cands(p[1], np.ones(3)), m.points3d) == []
    assert stereo_triples(rig, np.zeros((0, 3)), np.zeros((0, 3)), m.points3d) == []
    # Right-view points off their epipolar lines (shifted 40 px vertically): no match.
    assert stereo_triples(rig, _cands(p[0], np.ones(3)), _cands(p[1] + [0, 40], np.ones(3)), m.points3d) == []


def _ellipses(rig, T, m, view):
    """The rings' outer ellipses in one view (RotatedRects fitted to the projected rims)."""
    import cv2

    Tv = T if view == 0 else rig.T_right_left @ T
    t = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    out = []
    for c in m.points3d:
        rim = c + m.outer_radius * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
        pix = rig.cameras[view].project(rim @ Tv[:3, :3].T + Tv[:3, 3])
        out.append(cv2.fitEllipse(pix.astype(np.float32)))
    return out


@pytest.mark.parametrize("view", [0, 1])
@pytest.mark.parametrize("seed", range(3))
def test_transfer_puts_the_rings_where_the_other_view_sees_them(rig, view, seed):
    rng = np.random.default_rng(seed)
    m = mp.Marker()
    # Steep, as where transfer is needed: 45-60° to the look-at axis.
    T = look_at_pose(
        [rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(400, 700)], rng.uniform(45, 60), rng.uniform(0, 360), rng.uniform(0, 360)
    )
    true = _project(rig, T, m.points3d)
    preds = transfer(
        rig, view, view_poses(rig.cameras[view], true[view], _ellipses(rig, T, m, view), m.points3d, m.outer_radius), m.points3d
    )
    assert 1 <= len(preds) <= 2
    # The ellipses' shapes pick the right one of P3P's poses: it comes first, with the
    # marker's pose in the other view and so its rings' ellipses there.
    np.testing.assert_allclose(preds[0][0], true[1 - view], atol=0.05)
    T_other = T if view == 1 else rig.T_right_left @ T
    np.testing.assert_allclose(preds[0][1][:3, 3], T_other[:3, 3], atol=0.05)
    for (c, ax, _ang), (c2, ax2, _ang2) in zip(
        ring_ellipses(rig.cameras[1 - view], preds[0][1], m.points3d, m.outer_radius), _ellipses(rig, T, m, 1 - view)
    ):
        np.testing.assert_allclose(c, c2, atol=0.05)
        np.testing.assert_allclose(sorted(ax), sorted(ax2), atol=0.1)
    # Without ellipses the right pose is still among P3P's solutions.
    preds = transfer(rig, view, view_poses(rig.cameras[view], true[view], None, m.points3d, m.outer_radius), m.points3d, max_poses=4)
    assert min(np.abs(p - true[1 - view]).max() for p, _ in preds) < 0.05


def test_view_triples_names_the_marker_by_its_layout(rig):
    m = mp.Marker()
    T = look_at_pose([0, 0, 500], 30, 40, 25)
    p = _project(rig, T, m.points3d)[0]
    rng = np.random.default_rng(1)
    decoys = rng.uniform(0, 1000, (4, 2))
    cand = _cands(np.vstack([decoys[:2], p[::-1], decoys[2:]]), np.full(7, 0.5))
    found = view_triples(cand, m.centers2d, max_triples=3)
    assert len(found) == 3
    np.testing.assert_allclose(found[0][0], p)  # c0, c1, c2 in order, whatever the input order
    assert all(f[1] <= found[0][1] for f in found)
    # The mirror image of the marker is never named.
    mirror = p * [-1, 1] + [1280, 0]
    assert all(np.abs(f[0] - mirror).max() > 1 for f in view_triples(_cands(mirror, np.ones(3)), m.centers2d, max_triples=5))
    assert view_triples(_cands(p[:2], np.ones(2)), m.centers2d) == []


def test_layout_orders_keeps_every_marker_like_order_and_view_triples_the_best(rig):
    """layout_orders: every order of every triple with the marker's handedness and ratio,
    the true order among them; view_triples: each set once, in its best order, best first."""
    from markerpose.stages.match import best_per_set, layout_orders

    m = mp.Marker()
    p = _project(rig, look_at_pose([0, 0, 500], 30, 40, 25), m.points3d)[0]
    decoys = np.random.default_rng(4).uniform(0, 1000, (3, 2))
    cand = _cands(np.vstack([p[::-1], decoys]), np.linspace(0.9, 0.4, 6))
    pts, score, sets = layout_orders(cand, m.centers2d)
    assert pts.shape == (len(score), 3, 2) and sets.shape == score.shape
    assert (signed_areas(pts) < 0).all()
    assert min(np.abs(q - p).max() for q in pts) < 1e-9
    assert len(np.unique(sets)) < len(sets)  # some triple with more than one order
    best = best_per_set(score, sets)
    assert len(best) == len(np.unique(sets)) and (np.diff(score[best]) <= 0).all()
    for k in best:  # the best of its set
        assert score[k] == score[sets == sets[k]].max()
    found = view_triples(cand, m.centers2d, max_triples=None)
    assert [f[1] for f in found] == pytest.approx(list(score[best]))
    # A lower ratio bound lets steeper (or more wrongly ordered) triples in.
    assert len(layout_orders(cand, m.centers2d, 0.1)[1]) >= len(score)


def test_transfer_of_degenerate_triples_gives_finite_points_or_none(rig):
    # Regression: a degenerate P3P solution once gave NaN points, which crashed the refinement.
    m = mp.Marker()
    for pts in ([[100, 100], [200, 200], [300, 300]], [[100, 100]] * 3, [[600, 500], [601, 500], [600, 501]]):
        for view in (0, 1):
            poses = view_poses(rig.cameras[view], np.array(pts, float), None, m.points3d, m.outer_radius)
            for p, T in transfer(rig, view, poses, m.points3d, max_poses=4):
                assert p.shape == (3, 2) and np.isfinite(p).all() and T.shape == (4, 4)
    with pytest.raises(ValueError, match="finite"):
        refine_points(np.zeros((64, 64), np.uint8), np.full((3, 2), np.nan), m)


def test_view_poses_tell_one_plate_from_rings_that_do_not_share_one(rig):
    m = mp.Marker()
    T = look_at_pose([10, -20, 550], 40, 70, 10)
    true = _project(rig, T, m.points3d)[0]
    ells = _ellipses(rig, T, m, 0)
    poses = view_poses(rig.left, true, ells, m.points3d, m.outer_radius)
    assert poses and poses[0][0] < 0.005
    np.testing.assert_allclose(poses[0][1][:3, 3], T[:3, 3], atol=0.05)  # mm
    assert rotation_angle(poses[0][1][:3, :3], T[:3, :3]) < np.deg2rad(0.05)
    # The same centres with ellipses turned 60°: three rings that no plate pose explains.
    turned = [(c, ax, a + 60.0) for c, ax, a in ells]
    assert view_poses(rig.left, true, turned, m.points3d, m.outer_radius)[0][0] > 0.1


def test_view_triples_agrees_with_a_loop_over_triples():
    """The vectorised search equals the plain loop: per set of three candidates its best
    ID order, sets ranked by score (ties in candidate order)."""
    import itertools

    from markerpose.geometry import layout_ratio, signed_area

    layout = mp.Marker().centers2d
    rng = np.random.default_rng(5)
    for n in (0, 3, 5, 8, 10):
        cand = np.column_stack([rng.uniform(0, 320, (n, 2)), np.sort(rng.uniform(0.01, 1, n))[::-1]])
        if n >= 5:
            cand[:3, :2] = [[100, 150], [140, 160], [88, 90]]  # the marker's triangle, c0 c1 c2
        ref = {}
        for trio in itertools.combinations(range(min(n, 8)), 3):
            for perm in itertools.permutations(trio):
                p = cand[list(perm), :2]
                r = layout_ratio(p, layout)
                if signed_area(p) < 0 and r >= 0.35:
                    s = np.prod(cand[list(perm), 2]) ** (1 / 3) * r
                    if s > ref.get(trio, (None, -1.0))[1]:
                        ref[trio] = (p, s)
        ref = sorted(ref.values(), key=lambda f: -f[1])
        got = view_triples(cand, layout, max_triples=None)
        assert len(got) == len(ref) and (n < 5 or len(got) > 0)
        for (p, s), (q, t) in zip(got, ref):
            np.testing.assert_array_equal(p, q)
            assert s == pytest.approx(t, rel=1e-12)


def test_stereo_triples_agrees_with_a_loop_over_triples(rig):
    """The vectorised matching returns what a plain loop over every (c0, c1, c2) of matched
    candidates returns, in the same order: a view given twice (many matches) and a pair
    with the marker among decoys."""
    from markerpose.geometry import epipolar_distance, signed_area, triangulate

    def loop(cl, cr, model, etol, stol, top):
        I, J = np.nonzero(epipolar_distance(rig, cl[:, :2], cr[:, :2]) <= etol)
        X = triangulate(rig, cl[I, :2], cr[J, :2])
        front = (X[:, 2] > 0) & (rig.to_right(X)[:, 2] > 0)
        I, J, X = I[front], J[front], X[front]
        L = side_lengths(model)
        found = []
        for a in range(len(X)):
            for b in range(len(X)):
                for c in range(len(X)):
                    e = [abs(np.linalg.norm(X[p] - X[q]) - L[k]) / L[k] for k, (p, q) in enumerate(((a, b), (a, c), (b, c)))]
                    if max(e) > stol or len({I[a], I[b], I[c]}) < 3 or len({J[a], J[b], J[c]}) < 3:
                        continue
                    pl, pr = cl[I[[a, b, c]], :2], cr[J[[a, b, c]], :2]
                    if signed_area(pl) >= 0 or signed_area(pr) >= 0:
                        continue
                    s = np.exp(0.5 * np.mean(np.log(cl[I[[a, b, c]], 2]) + np.log(cr[J[[a, b, c]], 2])))
                    found.append((pl, pr, s * (1 - max(e) / stol)))
        found.sort(key=lambda f: -f[2])
        return found[:top]

    rng = np.random.default_rng(7)
    m = mp.Marker()
    T = look_at_pose([5, -10, 600], 35, 60, 20)
    true = _project(rig, T, m.points3d)
    dec = rig.project(T[:3, 3] + rng.uniform(-60, 60, (7, 3)))
    left = _cands(np.vstack([true[0], dec[0]]), rng.uniform(0.1, 0.9, 10))
    right = _cands(np.vstack([true[1], dec[1]]), rng.uniform(0.1, 0.9, 10))
    for cl, cr, etol, stol in ((left, right, 20.0, 0.35), (left, left.copy(), 60.0, 0.6)):
        want = loop(cl, cr, m.points3d, etol, stol, 50)
        got = stereo_triples(rig, cl, cr, m.points3d, etol, stol, 50)
        assert len(got) == len(want) > 0
        for (a, b, s), (c, d, t) in zip(got, want):
            np.testing.assert_allclose(a, c)
            np.testing.assert_allclose(b, d)
            assert s == pytest.approx(t, rel=1e-9)
