"""Rig check: the marker's known geometry, frame after frame, checks the calibration.

A camera bumped, turned or refocused after calibration still gives poses, wrong by as much
as the change (a view shifted sideways reads as another depth), with a small reprojection
residual. Two statistics of every tracked pose tell:

- **epipolar**: each ring's right-view centre's signed distance from the epipolar line of
  its left-view centre (ideal pixels). A turn or shift across the epipolar lines moves it
  off, the same way for every ring and frame.
- **scale**: the log of the triangulated rings' size over the marker's. A shift along the
  epipolar lines changes the disparity, so the depth and the marker's apparent size.

Each is divided by its standard deviation, from the centres' covariances
(:attr:`markerpose.results.Detection.center_cov`) plus a tolerance for the calibration's
own error (``epipolar_px``, ``scale``), and followed by a two-sided CUSUM (drift ``k``,
threshold ``h``): a persistent shift of a few sigma fires within frames, noise of a
stable rig almost never. Once fired the check stays fired (the rig must be recalibrated,
or :meth:`RigCheck.reset` called).
"""

from __future__ import annotations

import numpy as np

from .geometry import fundamental_matrix
from .uncertainty import point_covariances

default_conf = {
    "epipolar_px": 0.1,  # the calibration's own epipolar error a stable rig may show, px
    "scale": 0.001,  # ... and its scale error (relative)
    "k": 0.5,  # CUSUM drift, sigmas
    "h": 12.0,  # CUSUM threshold, sigmas
}


def statistics(rig, est, model: np.ndarray, conf: dict, F: np.ndarray | None = None) -> tuple[float, float] | None:
    """(z_epipolar, z_scale) of one pose (see the module's docstring), or None where its
    centres have no covariances."""
    dets = est.detections
    if len(dets) != 2 or any(d is None or d.center_cov is None for d in dets):
        return None
    covs = np.stack([d.center_cov for d in dets])
    if not np.all(np.isfinite(covs)):
        return None
    F = fundamental_matrix(rig) if F is None else F  # computed once per rig state
    ul = rig.left.undistort_points(est.centers[0])
    ur = rig.right.undistort_points(est.centers[1])
    lines = ul @ F[:, :2].T + F[:, 2]  # epipolar lines in the right view
    norm = np.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2)
    d = (lines[:, 0] * ur[:, 0] + lines[:, 1] * ur[:, 1] + lines[:, 2]) / norm
    n = lines[:, :2] / norm[:, None]
    c2 = covs[0] + covs[1]
    var = n[:, 0] ** 2 * c2[:, 0, 0] + 2 * n[:, 0] * n[:, 1] * c2[:, 0, 1] + n[:, 1] ** 2 * c2[:, 1, 1] + conf["epipolar_px"] ** 2
    z_e = float(np.sum(d / var) / np.sqrt(np.sum(1 / var)))
    X = np.asarray(est.points3d, np.float64)
    dx, dm = X - X.mean(0), model - model.mean(0)
    S2 = float(np.sum(dx * dx))
    log_s = 0.5 * np.log(S2 / float(np.sum(dm * dm)))
    cx = point_covariances(rig, est.centers, covs)
    var_s = float(np.einsum("ni,nij,nj->", dx, cx, dx)) / S2**2 + conf["scale"] ** 2
    return z_e, float(log_s / np.sqrt(var_s))


class RigCheck:
    """Follows the statistics of every pose fed to :meth:`update` (see the module's docstring).

    Args:
        rig: the stereo rig the poses were solved with.
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, rig, conf: dict | None = None):
        self.rig, self.conf = rig, {**default_conf, **(conf or {})}
        self.reset()

    def reset(self) -> None:
        """Forget what was seen (after recalibrating, or for another rig state)."""
        self.sums = np.zeros(4)  # CUSUM epipolar +, -, scale +, -
        self.frames = 0
        self.fired: str | None = None  # why the check fired, or None
        self.fired_at: int | None = None

    def update(self, est, model: np.ndarray) -> str | None:
        """Feed one pose (``model``: its marker's ring centres, ``Marker.points3d``); the
        reason once the check has fired (from that pose on), else None."""
        if self.fired is not None:
            return self.fired
        z = statistics(self.rig, est, model, self.conf)
        if z is None:
            return None
        self.frames += 1
        k = self.conf["k"]
        ze, zs = z
        self.sums = np.maximum(0.0, self.sums + np.array([ze - k, -ze - k, zs - k, -zs - k]))
        if self.sums.max() > self.conf["h"]:
            which = int(np.argmax(self.sums))
            what = (
                "the views' centres left their epipolar lines"
                if which < 2
                else f"the marker is triangulated {'larger' if which == 2 else 'smaller'} than it is"
            )
            self.fired = (
                f"rig check: {what} (z {ze:+.1f} epipolar, {zs:+.1f} scale): a camera moved, turned or refocused "
                "since calibration; recalibrate (markerpose calibrate)"
            )
            self.fired_at = self.frames
        return self.fired


__all__ = ["RigCheck", "default_conf", "statistics"]
