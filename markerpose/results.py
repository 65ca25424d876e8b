"""What the detectors and the pipeline return."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Detection:
    """The marker in one view.

    Attributes:
        centers: (3, 2) sub-pixel centres of c0, c1, c2 (ordered by ID) in the
            input image's own (distorted) pixel coordinates: the centres of the fitted
            outer ellipses (one view cannot correct their perspective bias; a stereo
            :class:`Estimate` does).
        ellipses: optional per-ring ellipse as OpenCV RotatedRect tuples
            ((cx, cy), (w, h), angle_deg), ordered by ID.
        score: detector-specific confidence (higher is better).
        refined: (3,) bool, which centres are sub-pixel (None: all of them).
        blur_px: the motion blur's length (px) that the blurred-ring model fit found in
            this view; 0 where that fit did not run (sharp edges) or its result was not
            kept (see :func:`markerpose.classical.refine_blurred`).
    """

    centers: np.ndarray
    ellipses: list | None = None
    score: float = 1.0
    refined: np.ndarray | None = None
    blur_px: float = 0.0

    def __post_init__(self):
        if self.refined is None:
            self.refined = np.ones(3, bool)


@dataclass
class Estimate:
    """The marker's pose from a stereo pair.

    Attributes:
        T: (4, 4) T_left_marker, mm.
        points3d: (3, 3) c0, c1, c2 in the left-camera frame, mm.
        centers: (2, 3, 2) [view][id][x, y] sub-pixel centres in the input images: with
            bias correction (the default), where the rings' 3D centres project; without
            it, the fitted ellipses' centres (``detections[k].centers``).
        detections: the two views' :class:`Detection` (the fitted ellipses' centres).
        residual_px: RMS distance (px) of the six centres from the marker's centres
            projected under the pose.
        source: how it was obtained: "detected" (cold detection).
    """

    T: np.ndarray
    points3d: np.ndarray
    centers: np.ndarray
    detections: tuple = field(default=(), repr=False)
    residual_px: float | None = None
    source: str = "detected"

    @property
    def R(self) -> np.ndarray:
        """(3, 3) rotation of T_left_marker."""
        return self.T[:3, :3]

    @property
    def t(self) -> np.ndarray:
        """(3,) translation of T_left_marker, mm (the position of c0)."""
        return self.T[:3, 3]


def relative_poses(found: dict[str, Estimate], reference: str) -> dict[str, np.ndarray]:
    """T_reference_tool (4, 4, mm) of every tool in ``found`` (``{name: Estimate}``, as
    :meth:`markerpose.MarkerPose.track_all` returns it) other than ``reference``: each
    tool's pose in the frame of the reference tool seen in the same pair. ``{}`` when
    the reference is not in ``found``: a tool is never reported relative to a reference
    that was not seen."""
    if reference not in found:
        return {}
    inv = np.linalg.inv(found[reference].T)
    return {name: inv @ est.T for name, est in found.items() if name != reference}


__all__ = ["Detection", "Estimate", "relative_poses"]
