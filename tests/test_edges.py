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
    med = edges.masked_median(x, mask, empty=-1.0)
    pct = edges.masked_percentile(x, mask, 75, empty=-1.0)
    for k in range(6):
        want_med = np.median(x[k][mask[k]]) if mask[k].any() else -1.0
        want_pct = np.percentile(x[k][mask[k]], 75) if mask[k].any() else -1.0
        assert med[k] == want_med and pct[k] == want_pct


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


@pytest.mark.parametrize("blur", [0.0, 20.0])
def test_a_batch_of_rings_gets_what_each_gets_alone(blur):
    """Six rings of both views refined together equal each ring refined alone (same
    neighbours), sharp and under motion blur; and they land on the true centres."""
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
    batch = classical.refine_views(grays, rings, mk, cameras=list(rig.cameras))
    for v in range(2):
        noise = classical.noise_sigma(grays[v])
        for k, ring in enumerate(rings[v]):
            alone = classical.refine_ring(grays[v], ring, mk, None, noise, others=rings[v], camera=rig.cameras[v])
            assert alone.refined and batch[v][k].refined
            np.testing.assert_allclose(batch[v][k].center, alone.center, atol=1e-9)
        if blur == 0:
            assert np.abs(np.array([r.center for r in batch[v]]) - f.views[v].outer_centers).max() < 0.05
