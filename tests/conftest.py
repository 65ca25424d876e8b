"""Fixtures shared by the test modules."""

import pytest

import markerpose as mp


@pytest.fixture(scope="session")
def rig() -> mp.StereoRig:
    """The simulated paper-like rig (its cameras' ray grids are built once and shared)."""
    return mp.StereoRig.default()


def _drawn_rings(img, centers, outer, inner, ring_value, inside_value):
    """Draw filled rings (anti-aliased) into ``img`` in place: outer disks of ``ring_value``
    with inner disks of ``inside_value``, radii in px."""
    import cv2

    for x, y in centers:
        cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), int(round(outer * 16)), ring_value, -1, cv2.LINE_AA, shift=4)
        cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), int(round(inner * 16)), inside_value, -1, cv2.LINE_AA, shift=4)


@pytest.fixture
def drawn_rings():
    """The ring drawing helper (:func:`_drawn_rings`)."""
    return _drawn_rings
