"""Renderer of several tools in one stereo pair: each tool's truth, painter's order, coverage."""

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose.synth import Imaging, look_at_pose, render_stereo, render_tools
from markerpose.tools import tool_set

SIZE = (640, 512)
BG = np.full(SIZE[::-1], 0.5, np.float32)
APART = (look_at_pose([-40, 0, 600], 10, 30, 0), look_at_pose([40, 10, 600], 10, 30, 0))  # side by side, no overlap
# B nearer, its plate's right edge through A's c0 and c2 in the left view (the right view sees them apart).
OVERLAP = (look_at_pose([0, 0, 650]), look_at_pose([-65, 30, 450]))


@pytest.fixture(scope="module")
def small_rig(rig) -> mp.StereoRig:
    """The default rig at half resolution (640 x 512): the same views, a quarter of the pixels."""

    def half(cam):
        K = cam.K.copy()
        K[:2] *= 0.5
        K[:2, 2] -= 0.25  # pixel centres: (u + 0.5) / 2 - 0.5
        return mp.Camera(K, cam.dist, SIZE)

    return mp.StereoRig(half(rig.left), half(rig.right), rig.R, rig.t)


@pytest.fixture(scope="module")
def tools():
    return tool_set(2)


def _plate_pixels(cam: mp.Camera, T: np.ndarray, marker: mp.Marker) -> np.ndarray:
    """The plate's projected corners filled (its edges straight: within a pixel of the true outline)."""
    P = marker.plate_corners3d @ T[:3, :3].T + T[:3, 3]
    out = np.zeros(SIZE[::-1], np.uint8)
    cv2.fillConvexPoly(out, np.rint(cam.project(P)).astype(np.int32), 1)
    return out.astype(bool)


def test_one_tool_renders_as_render_stereo(small_rig, tools):
    """The same seed, the same draws: one tool is bit for bit render_stereo's frame, noise included."""
    a = render_stereo(small_rig, APART[0], tools[0], seed=5)
    b = render_tools(small_rig, [(tools[0], APART[0])], seed=5)
    assert list(b.truths) == ["tool1"]
    truth = b.truths["tool1"]
    for x, y, va, vb in zip(a.images, b.images, a.views, truth.views):
        np.testing.assert_array_equal(x, y)
        for key in ("T_cam_marker", "centers", "outer_conics", "inner_conics", "outer_centers", "mask", "in_image"):
            np.testing.assert_array_equal(getattr(va, key), getattr(vb, key))
    assert truth.fully_visible and np.all(truth.visible == 1.0)


def test_each_tool_has_its_single_render_truth(small_rig, tools):
    """Two tools apart: each one's truth is its single render's, and away from the other plate
    (beyond the PSF's reach) the pixels are its single render's too (noise off, so the rng
    draws only the clutter, the same in both)."""
    im = Imaging(noise=False)
    both = render_tools(small_rig, list(zip(tools, APART)), imaging=im, seed=3)
    assert list(both.truths) == ["tool1", "tool2"]
    for k, (marker, T) in enumerate(zip(tools, APART)):
        alone = render_stereo(small_rig, T, marker, imaging=im, seed=3)
        truth = both.truths[marker.name]
        assert truth.marker is marker and truth.fully_visible
        np.testing.assert_array_equal(truth.T_left_marker, T)
        other_marker, other_T = tools[1 - k], APART[1 - k]
        for v, (cam, view, ref) in enumerate(zip(small_rig.cameras, truth.views, alone.views)):
            np.testing.assert_array_equal(view.centers, ref.centers)
            np.testing.assert_array_equal(view.outer_conics, ref.outer_conics)
            np.testing.assert_array_equal(view.mask, ref.mask)
            To = other_T if v == 0 else small_rig.T_right_left @ other_T
            near_other = cv2.dilate(_plate_pixels(cam, To, other_marker).astype(np.uint8), np.ones((11, 11), np.uint8)) > 0
            assert (~near_other).mean() > 0.8
            np.testing.assert_array_equal(both.images[v][~near_other], alone.images[v][~near_other])


def test_nearer_plate_hides_the_farther_ring(small_rig, tools):
    """B nearer and over half of A's c0 and c2 in the left view: those rings are partly
    hidden there (visible about a half, the mask cut to what is seen), A is not fully
    visible, B is; the right view sees both whole."""
    A, B = tools
    f = render_tools(small_rig, [(A, OVERLAP[0]), (B, OVERLAP[1])], imaging=Imaging.ideal(), background=BG)
    a, b = f.truths["tool1"], f.truths["tool2"]
    assert b.fully_visible and np.all(b.visible == 1.0)
    assert not a.fully_visible
    assert a.visible.shape == (2, 3)
    assert np.all((a.visible[0, [0, 2]] > 0.3) & (a.visible[0, [0, 2]] < 0.7))
    assert a.visible[0, 1] == 1.0 and np.all(a.visible[1] == 1.0)
    assert all(v.in_image.all() for v in a.views)
    alone = render_stereo(small_rig, OVERLAP[0], A, imaging=Imaging.ideal(), background=BG)
    cover = _plate_pixels(small_rig.left, OVERLAP[1], B)
    for i in range(3):
        ring, seen = alone.views[0].mask == i + 1, a.views[0].mask == i + 1
        assert not (seen & ~ring).any()  # the mask only loses pixels
        assert seen.sum() / ring.sum() == a.visible[0, i]
        # The filled corners agree with the exact coverage to the column of pixels that
        # OpenCV's fill adds along its edge (one column is ~0.03 of a 38 px ring).
        assert (ring & ~cover).sum() / ring.sum() == pytest.approx(a.visible[0, i], abs=0.05)
    np.testing.assert_array_equal(a.views[1].mask, alone.views[1].mask)


def test_painters_order_nearer_plate_wins(small_rig, tools):
    """Where B's plate lies over A's ring band, the pixels are B's (paper), not A's ink; the
    order is by depth, not by the order of the poses."""
    A, B = tools
    im = Imaging.ideal()
    f = render_tools(small_rig, [(A, OVERLAP[0]), (B, OVERLAP[1])], imaging=im, background=BG)
    g = render_tools(small_rig, [(B, OVERLAP[1]), (A, OVERLAP[0])], imaging=im, background=BG)
    for x, y in zip(f.images, g.images):
        np.testing.assert_array_equal(x, y)
    img_a = render_stereo(small_rig, OVERLAP[0], A, imaging=im, background=BG).images[0]
    img_b = render_stereo(small_rig, OVERLAP[1], B, imaging=im, background=BG).images[0]
    inside_b = cv2.erode(_plate_pixels(small_rig.left, OVERLAP[1], B).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    ink, paper = 255 * im.exposure * im.ink, 255 * im.exposure * im.paper
    hidden_ink = inside_b & (np.abs(img_a - ink) < 1) & (np.abs(img_b - paper) < 1)
    assert hidden_ink.sum() > 100
    np.testing.assert_array_equal(f.images[0][inside_b], img_b[inside_b])
    np.testing.assert_allclose(f.images[0][hidden_ink], paper, atol=1)


def test_ring_cut_by_the_image_border(small_rig, tools):
    """A ring across the image's edge is seen in part (not in the image), one wholly outside not at all."""
    f = render_tools(small_rig, [(tools[0], look_at_pose([-150, 0, 500]))], imaging=Imaging.ideal(), background=BG)
    t = f.truths["tool1"]
    assert not t.fully_visible and not t.views[0].in_image.any()
    assert t.visible[0, 0] == 0.0 and t.visible[0, 2] == 0.0
    assert 0.5 < t.visible[0, 1] < 0.95


def test_duplicate_names_are_refused(small_rig, tools):
    with pytest.raises(ValueError, match="tool1"):
        render_tools(small_rig, [(tools[0], APART[0]), (tools[0], APART[1])])
    with pytest.raises(ValueError, match="tool2.*in front of the camera"):
        render_tools(small_rig, [(tools[0], APART[0]), (tools[1], look_at_pose([0, 0, -100]))])
