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

import math

import numpy as np

from . import jit
from .camera import StereoRig, undistort_point
from .geometry import fundamental_matrix, triangulate_ideal
from .jit import compiled
from .uncertainty import H_PX, point_covariances

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
    centres = np.ascontiguousarray(est.centers, np.float64)
    X = np.ascontiguousarray(est.points3d, np.float64)
    model = np.ascontiguousarray(model, np.float64)
    out = np.empty(2)
    cams = rig.cameras
    if _statistics(
        centres,
        covs,
        cams[0].K,
        cams[0].dist,
        cams[1].K,
        cams[1].dist,
        F,
        rig.P1,
        rig.P2,
        X,
        model,
        conf["epipolar_px"],
        conf["scale"],
        out,
    ):
        return float(out[0]), float(out[1])
    return _statistics_numpy(rig, est, covs, model, conf, F)  # a centre the compiled undistortion refused


def _statistics_numpy(rig, est, covs: np.ndarray, model: np.ndarray, conf: dict, F: np.ndarray) -> tuple[float, float]:
    """:func:`statistics` in numpy (:meth:`~markerpose.camera.Camera.undistort_points` and
    :func:`~markerpose.uncertainty.point_covariances`, with their fallbacks)."""
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


@compiled
def _ideal(u, v, K, dist):  # pragma: no cover - compiled
    """The ideal pixel of the distorted pixel (u, v) and whether the undistortion converged."""
    x, y, ok = undistort_point(u, v, K, dist)
    return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 0] * x + K[1, 1] * y + K[1, 2], ok


@compiled
def _statistics(c, covs, K1, d1, K2, d2, F, P1, P2, X, model, epi_px, scale, out):  # pragma: no cover - compiled
    """:func:`statistics`' arithmetic in one call (``c`` (2, N, 2) the views' centres, ``covs``
    (2, N, 2, 2) theirs, ``X`` the pose's points): ``out`` = (z_epipolar, z_scale); False where
    an undistortion did not converge (the numpy path then takes over). The points'
    covariances as :func:`~markerpose.uncertainty.point_covariances`: the triangulation
    moved by ``H_PX`` in each of a point's four pixel coordinates."""
    N = c.shape[1]
    ul, ur = np.empty((5 * N, 2)), np.empty((5 * N, 2))
    for case in range(5):  # none, then the left x, left y, right x, right y moved
        for i in range(N):
            lu, lv, ru, rv = c[0, i, 0], c[0, i, 1], c[1, i, 0], c[1, i, 1]
            if case == 1:
                lu += H_PX
            elif case == 2:
                lv += H_PX
            elif case == 3:
                ru += H_PX
            elif case == 4:
                rv += H_PX
            a, b, ok1 = _ideal(lu, lv, K1, d1)
            e, f, ok2 = _ideal(ru, rv, K2, d2)
            if not (ok1 and ok2):
                return False
            ul[case * N + i, 0], ul[case * N + i, 1] = a, b
            ur[case * N + i, 0], ur[case * N + i, 1] = e, f
    # Epipolar: each right centre's signed distance from its left centre's line.
    num = den = 0.0
    for i in range(N):
        l0 = F[0, 0] * ul[i, 0] + F[0, 1] * ul[i, 1] + F[0, 2]
        l1 = F[1, 0] * ul[i, 0] + F[1, 1] * ul[i, 1] + F[1, 2]
        l2 = F[2, 0] * ul[i, 0] + F[2, 1] * ul[i, 1] + F[2, 2]
        norm = math.sqrt(l0 * l0 + l1 * l1)
        d = (l0 * ur[i, 0] + l1 * ur[i, 1] + l2) / norm
        n0, n1 = l0 / norm, l1 / norm
        c00 = covs[0, i, 0, 0] + covs[1, i, 0, 0]
        c01 = covs[0, i, 0, 1] + covs[1, i, 0, 1]
        c11 = covs[0, i, 1, 1] + covs[1, i, 1, 1]
        var = n0 * n0 * c00 + 2 * n0 * n1 * c01 + n1 * n1 * c11 + epi_px * epi_px
        num += d / var
        den += 1 / var
    out[0] = num / math.sqrt(den)
    # Scale: the triangulated rings' size over the marker's, and its variance.
    T = np.empty((5 * N, 3))
    triangulate_ideal(P1, P2, ul, ur, T)
    mx, mm = np.zeros(3), np.zeros(3)
    for i in range(N):
        for a in range(3):
            mx[a] += X[i, a] / N
            mm[a] += model[i, a] / N
    S2 = Sm = q = 0.0
    for i in range(N):
        dx = X[i] - mx
        dm = model[i] - mm
        S2 += dx @ dx
        Sm += dm @ dm
        for v in range(2):  # dx^T J_v C_v J_v^T dx, J_v the point's derivatives by view v's pixel
            g0 = g1 = 0.0
            for a in range(3):
                g0 += dx[a] * (T[(1 + 2 * v) * N + i, a] - T[i, a]) / H_PX
                g1 += dx[a] * (T[(2 + 2 * v) * N + i, a] - T[i, a]) / H_PX
            q += g0 * g0 * covs[v, i, 0, 0] + 2 * g0 * g1 * covs[v, i, 0, 1] + g1 * g1 * covs[v, i, 1, 1]
    log_s = 0.5 * math.log(S2 / Sm)
    out[1] = log_s / math.sqrt(q / (S2 * S2) + scale * scale)
    return True


class RigCheck:
    """Follows the statistics of every pose fed to :meth:`update` (see the module's docstring).

    Args:
        rig: the stereo rig the poses were solved with.
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, rig, conf: dict | None = None):
        self.rig, self.conf = rig, {**default_conf, **(conf or {})}
        jit.warm_up(warm_up)  # compiled now, not at a stream's first pose
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


_WARM = False


def warm_up() -> None:
    """Compile the statistics' kernel (or load it from numba's cache) once per process."""
    global _WARM
    if not _WARM:
        rig = StereoRig.default()  # the argument types of a real call (the cached F is read-only)
        X = np.array([[0.0, 0, 500], [25, 0, 500], [0, 40, 500]])
        c = np.ascontiguousarray(np.stack(rig.project(X)), np.float64)
        covs = np.tile(np.eye(2) * 1e-4, (2, 3, 1, 1))
        cams = rig.cameras
        _statistics(
            c,
            covs,
            cams[0].K,
            cams[0].dist,
            cams[1].K,
            cams[1].dist,
            fundamental_matrix(rig),
            rig.P1,
            rig.P2,
            X,
            X - X[0],
            0.1,
            0.001,
            np.empty(2),
        )
        _WARM = True


__all__ = ["RigCheck", "default_conf", "statistics", "warm_up"]
