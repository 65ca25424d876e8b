"""Track: on a video stream, the previous frames are the prior.

From the last three poses a constant-acceleration model predicts the marker's pose in the
new frame (:func:`predict`); the rings' outer ellipses under that pose
(:func:`~markerpose.geometry.ring_ellipses`) seed the sub-pixel edge fit in both views
directly — no stage 1, no EllipSegNet. The result passes the usual verification
(every centre edge-fitted, epipolar distances, plate check, the marker's shape) and a
quality gate on the reprojection error; otherwise the frame is detected cold.
"""

from __future__ import annotations

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


__all__ = ["default_conf", "inside", "predict"]
