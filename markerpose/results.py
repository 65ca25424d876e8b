"""What the detectors and the pipeline return."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

# A pose whose origin's RMS 3D error at one standard deviation (``Estimate.sd_mm``) exceeds
# this is of "low accuracy": the tracker's claim is sub-0.1 mm.
LOW_ACCURACY_MM = 0.1
STATUSES = ("ok", "low accuracy", "outside the calibrated volume", "unrated", "rig changed")


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
        center_cov: (3, 2, 2) the centres' covariances, px^2, from their own fits (NaN
            where a centre was not edge-fitted), or None where no fit gave any.
    """

    centers: np.ndarray
    ellipses: list | None = None
    score: float = 1.0
    refined: np.ndarray | None = None
    blur_px: float = 0.0
    center_cov: np.ndarray | None = field(default=None, repr=False)

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
        cov: (6, 6) covariance of (tx, ty, tz) mm, the marker's origin in the left-camera
            frame, and (wx, wy, wz) rad, the rotation error ``R_true @ R_est.T`` as a
            rotation vector in the left-camera frame (:mod:`markerpose.uncertainty`); None
            where a centre has no covariance (the paper's contour centres). Computed on
            first access.
        rig_warning: with ``track()``, the rig check's reason once it has fired (a camera
            moved since calibration, :mod:`markerpose.rigcheck`), else None.
    """

    T: np.ndarray
    points3d: np.ndarray
    centers: np.ndarray
    detections: tuple = field(default=(), repr=False)
    residual_px: float | None = None
    source: str = "detected"
    # (3, 2) the right view's centres as measured where ``track(..., times=...)`` moved them
    # to the left view's time (``detections[1]`` holds the moved ones); None otherwise.
    right_measured: np.ndarray | None = field(default=None, repr=False, compare=False)
    _context: tuple | None = field(default=None, repr=False, compare=False)  # (rig, model, pose method) for cov
    rig_warning: str | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def cov(self) -> np.ndarray | None:
        if self._context is None or len(self.detections) != 2 or any(d is None or d.center_cov is None for d in self.detections):
            return None
        from .uncertainty import pose_covariance

        rig, model, method = self._context
        covs = np.stack([d.center_cov for d in self.detections])
        return pose_covariance(rig, model, self.T, self.points3d, self.centers, covs, method)

    @property
    def sd_mm(self) -> float:
        """The marker origin's RMS 3D error at one standard deviation, mm (sqrt of the
        trace of ``cov``'s translation block; NaN without ``cov``)."""
        from .uncertainty import sd_mm

        return sd_mm(self.cov, self.T)

    @property
    def sd_deg(self) -> float:
        """The RMS rotation error at one standard deviation, degrees (NaN without ``cov``)."""
        from .uncertainty import sd_deg

        return sd_deg(self.cov)

    def status(self, max_sd_mm: float = LOW_ACCURACY_MM, point=None) -> str:
        """The pose's rating: "rig changed" where the rig check has fired (``rig_warning``);
        else "outside the calibrated volume" where a ring centre lies
        outside the rig's calibrated volume enlarged by 10 % of its size
        (:meth:`markerpose.camera.StereoRig.in_volume`; never where the rig has none); else
        "unrated" without a covariance (the paper's contour centres); else "low accuracy"
        where the RMS 3D error at one standard deviation (of the origin, or of ``point`` in
        the marker's frame, e.g. a tip) exceeds ``max_sd_mm``; else "ok"."""
        if self.rig_warning is not None:
            return "rig changed"
        if self._context is not None and not self._context[0].in_volume(self.points3d):
            return "outside the calibrated volume"
        if self.cov is None:
            return "unrated"
        sd = self.sd_mm if point is None else self.point_sd_mm(point)
        return "ok" if sd <= max_sd_mm else "low accuracy"

    def point_sd_mm(self, point) -> float:
        """The RMS 3D error at one standard deviation of a point fixed to the marker
        (``point`` (3,) mm in the marker's frame, e.g. a tool's tip), mm."""
        from .uncertainty import sd_mm

        return sd_mm(self.cov, self.T, point)

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


def relative_covariances(found: dict[str, Estimate], reference: str) -> dict[str, np.ndarray | None]:
    """The (6, 6) covariance of each T_reference_tool of :func:`relative_poses` (translation
    mm, rotation vector rad, in the reference's frame; :func:`markerpose.uncertainty.relative_covariance`),
    None where either pose has none; ``{}`` without the reference."""
    from .uncertainty import relative_covariance

    if reference not in found:
        return {}
    ref = found[reference]
    return {
        name: None if ref.cov is None or est.cov is None else relative_covariance(ref.T, ref.cov, est.T, est.cov)
        for name, est in found.items()
        if name != reference
    }


__all__ = ["LOW_ACCURACY_MM", "STATUSES", "Detection", "Estimate", "relative_covariances", "relative_poses"]
