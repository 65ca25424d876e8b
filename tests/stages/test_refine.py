"""The refine stage (markerpose.stages.refine): rings' edges fitted from points or predicted ellipses."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.frame import Frame
from markerpose.geometry import ring_ellipses
from markerpose.stages import refine
from markerpose.synth import Imaging, look_at_pose, render_stereo


@pytest.fixture(scope="module")
def scene(rig):
    T = look_at_pose([5, -10, 520], 35, 50, 20)
    return T, render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=7)


def test_layout_ellipses_are_the_rings_a_triple_implies(rig, scene):
    T, f = scene
    marker = mp.Marker()
    refiner = refine.Refiner(refine.default_conf, marker, neural=False)
    rects = refiner.layout_ellipses(f.views[0].centers)
    truth = ring_ellipses(rig.left, T, marker.points3d, marker.outer_radius)
    assert len(rects) == 3
    for (c, axes, _), centre, (_, true_axes, _) in zip(rects, f.views[0].centers, truth):
        np.testing.assert_allclose(c, centre)
        np.testing.assert_allclose(sorted(axes), sorted(true_axes), rtol=0.1)  # affine: perspective across the plate is small
    assert refiner.layout_ellipses(np.array([[0.0, 0.0], [10.0, 10.0], [20.0, 20.0]])) is None  # collinear: no ellipse


def test_predicted_ellipses_refine_to_the_true_centres_in_both_views(rig, scene):
    T, f = scene
    refiner = refine.Refiner(refine.default_conf, mp.Marker(), neural=False)
    marker = mp.Marker()
    predicted = []
    for cam, T_view in zip(rig.cameras, (T, rig.T_right_left @ T)):
        shifted = T_view.copy()
        shifted[:3, 3] += [0.6, -0.4, 0.0]  # a prior half a millimetre off
        predicted.append(ring_ellipses(cam, shifted, marker.points3d, marker.outer_radius))
    frame = Frame(list(f.images))
    found = refiner.from_ellipses(frame, frame.grays, list(rig.cameras), predicted, 1.0)
    for det, view in zip(found, f.views):
        assert det is not None and det.refined.all()
        assert np.abs(det.centers - view.outer_centers).max() < 0.05  # px
    # A prediction that misses the rings altogether finds none of them.
    far = [[((x + 300.0, y), axes, a) for (x, y), axes, a in view] for view in predicted]
    assert refiner.from_ellipses(Frame(list(f.images)), list(f.images), list(rig.cameras), far, 1.0, False) == [None, None]


def test_the_blur_gates_of_cold_and_tracked_fits_are_each_their_own(rig):
    """Edges about a third of the minor semi-axis wide (19 px of blur at 560 mm along
    c0 -> c1): with ``blur_width`` 0.3 a cold detection's fit refits them under the blur
    model while a tracker's (``track_blur_width`` 0.4) keeps the edge fit; both within
    0.05 px of the truth. One gate for both gives one behaviour. By default the cold fit
    refits them too (edges over 7.5 px wide: ``blur_long_px``), the tracker's does not;
    without that rule both keep the edge fit."""
    T = look_at_pose([0.0, 0.0, 560.0])
    marker = mp.Marker()
    f = render_stereo(rig, T, imaging=Imaging(alpha=0.7, motion_blur=19.0, motion_angle=0.0), seed=3)
    predicted = [ring_ellipses(cam, Tv, marker.points3d, marker.outer_radius) for cam, Tv in zip(rig.cameras, (T, rig.T_right_left @ T))]
    blur = {}
    cases = {
        "early": {"blur_width": 0.3},
        "one gate": {"blur_width": 0.3, "track_blur_width": 0.3},
        "default": {},
        "no long rule": {"blur_long_px": 0.0},
    }
    for name, conf in cases.items():
        refiner = refine.Refiner({**refine.default_conf, **conf}, marker, neural=False)
        for tracked in (False, True):
            frame = Frame(list(f.images))
            found = refiner.from_ellipses(frame, frame.grays, list(rig.cameras), predicted, 1.0, tracked=tracked)
            assert all(d is not None and np.abs(d.centers - v.outer_centers).max() < 0.05 for d, v in zip(found, f.views))
            blur[name, tracked] = [d.blur_px for d in found]
    assert min(blur["early", False]) > 15 and blur["early", True] == [0.0, 0.0], blur
    assert min(blur["one gate", True]) > 15, blur
    assert min(blur["default", False]) > 15 and blur["default", True] == [0.0, 0.0], blur
    assert blur["no long rule", False] == blur["no long rule", True] == [0.0, 0.0], blur
