"""Track: on a video stream, the previous frames are the prior.

From the last three poses a constant-acceleration model predicts the marker's pose in the
new frame (:func:`predict`); the rings' outer ellipses under that pose
(:func:`~markerpose.geometry.ring_ellipses`) seed the sub-pixel edge fit in both views
directly — no stage 1, no EllipSegNet. The result passes the usual verification
(every centre edge-fitted, epipolar distances, plate check, the marker's shape) and a
quality gate on the reprojection error; otherwise the frame is detected cold, first with
stage 1 looking only around where the marker was predicted (``near_margin``), then in the
whole images.

While the marker is lost, a pair that has not changed since the last cold detection that
found nothing (:func:`changed`: no block of either view moved beyond its noise) is not
detected again: a still scene costs a comparison, not a detection, and the marker coming
into view is a change. A cold detection still runs every ``lost_refresh`` frames.
"""

from __future__ import annotations

import cv2
import numpy as np

default_conf = {
    "max_residual_px": 0.5,  # quality gate: RMS reprojection error of the six centres, px
    "margin_px": 2.0,  # predicted rings must lie this far inside both images
    "one_pass_move": 0.15,  # px: a ring's edge fit from its predicted ellipse stops after
    #                         one pass when that pass moved it less than this (a still or
    #                         slow marker: the prediction was close), else it iterates to
    #                         convergence as a cold detection's does
    "noise_every": 30,  # tracked frames between estimates of the images' noise (the edge
    #                     fit's contrast floor); a cold detection also renews it
    "near_margin": 0.5,  # when the prior fails: stage 1 first looks only this many predicted
    #                      marker extents beyond the predicted marker in each view (0: the
    #                      whole images at once), then in the whole images
    "lost_change": 6.0,  # while lost: a block mean that moved more than this many times the
    #                      blocks' noise (and a grey level) since the last cold detection is
    #                      a change, and the pair is detected cold (0: every lost pair is)
    "lost_block": 8,  # ... px, the side of those blocks
    "lost_refresh": 30,  # ... frames: a cold detection at least this often even without change
}


def predict(history: list) -> np.ndarray:
    """The next T_left_marker (4, 4) from the last one, two or three: the last pose, then
    constant velocity (the last frame-to-frame motion applied once more), then constant
    acceleration (that motion changed once more as it last changed). A hand's motion turns
    within a few frames: under constant velocity the prediction overshoots each turn by
    the motion's change per frame, and the edge fit then needs more passes."""
    if len(history) < 2:
        return history[-1]
    last = history[-1]
    step = last @ np.linalg.inv(history[-2])
    if len(history) >= 3:
        step = (step @ np.linalg.inv(history[-2] @ np.linalg.inv(history[-3]))) @ step
    return step @ last


def inside(ellipses: list, size: tuple, margin: float) -> bool:
    """Whether every ellipse (RotatedRect) lies inside an image of ``size`` (w, h) with a margin."""
    w, h = size
    for (cx, cy), (a, b), _ in ellipses:
        r = max(a, b) / 2 + margin
        if not (r <= cx <= w - 1 - r and r <= cy <= h - 1 - r):
            return False
    return True


def blocks(gray: np.ndarray, side: int) -> np.ndarray:
    """The image's means (float32 grey levels) over ``side`` x ``side`` blocks tiling it
    from the top left (a last partial row or column of pixels is left out), exact: from
    the integral image."""
    side = min(int(side), *gray.shape)
    s = cv2.integral(gray)[::side, ::side]
    return ((s[1:, 1:] - s[:-1, 1:] - s[1:, :-1] + s[:-1, :-1]) / float(side * side)).astype(np.float32)


def changed(before: np.ndarray, after: np.ndarray, k: float, level: float = 1.0, scene: float = 2.0) -> bool:
    """Whether block means (:func:`blocks`) moved beyond their noise between two frames:
    some block by more than ``k`` times the blocks' noise plus ``level`` grey levels.

    The noise is the differences' own robust spread (their median absolute value, as a
    sigma): a marker or a hand coming into view moves a minority of the blocks, and the
    cameras' noise, correlated across pixels or not, sets the spread of the rest. When
    the median block itself moved by more than ``scene`` grey levels (the light, the
    camera or most of the scene changed, or noise too strong to tell), that is a change
    too."""
    d = np.abs(after - before)
    med = float(np.median(d))
    return bool(med > scene or d.max() > k * 1.4826 * med + level)


def check_conf(conf: dict) -> dict:
    """``conf`` with its values checked (``ValueError`` naming the key)."""
    if float(conf["near_margin"]) < 0:
        raise ValueError(f"near_margin must be >= 0 (0: no near look), got {conf['near_margin']!r}")
    if float(conf["lost_change"]) < 0:
        raise ValueError(f"lost_change must be >= 0 (0: no gate), got {conf['lost_change']!r}")
    if int(conf["lost_block"]) < 1:
        raise ValueError(f"lost_block must be >= 1 px, got {conf['lost_block']!r}")
    if int(conf["lost_refresh"]) < 1:
        raise ValueError(f"lost_refresh must be >= 1 frame, got {conf['lost_refresh']!r}")
    return conf


__all__ = ["blocks", "changed", "check_conf", "default_conf", "inside", "predict"]
