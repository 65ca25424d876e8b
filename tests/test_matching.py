"""Stereo matching of stage-1 candidates by the marker's 3D shape (markerpose.matching)."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.matching import side_lengths, stereo_triples
from markerpose.synth import look_at_pose


@pytest.fixture(scope="module")
def rig():
    return mp.StereoRig.default()


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
    T = look_at_pose([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(380, 750)], rng.uniform(0, 50), rng.uniform(0, 360), rng.uniform(0, 360))
    true = _project(rig, T, m.points3d)
    # Decoys: random 3D points near the marker (seen in both views, on their epipolar
    # lines) and image points with no partner; stage-1 noise of ~1 px on the true ones.
    decoys3d = (T[:3, 3] + rng.uniform(-80, 80, (6, 3)))
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
