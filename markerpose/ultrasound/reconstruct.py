"""From tracked frames to 3D: points, a cylinder fit, a compounded volume, pose
interpolation in time."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from .probe import ProbeCalibration


def tracker_points(points_px: list, poses: list, calibration: ProbeCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Segmented pixels of each frame → 3D points in the tracker (left camera) frame.

    Args:
        points_px: per frame, (N_i, 2) pixel points.
        poses: per frame, (4, 4) ``T_left_marker`` or None (frame skipped).
        calibration: the probe calibration.
    Returns:
        (points (N, 3) mm, frame index (N,)).
    """
    if len(points_px) != len(poses):
        raise ValueError(f"{len(points_px)} frames of points but {len(poses)} poses")
    out, idx = [], []
    for k, (uv, T) in enumerate(zip(points_px, poses)):
        if T is None or uv is None or len(uv) == 0:
            continue
        pm = calibration.pixels_to_marker(uv)
        out.append(pm @ T[:3, :3].T + T[:3, 3])
        idx.append(np.full(len(pm), k))
    if not out:
        return np.zeros((0, 3)), np.zeros(0, int)
    return np.concatenate(out), np.concatenate(idx)


def sweep_normal(poses: list, calibration: ProbeCalibration) -> np.ndarray:
    """The mean image-plane normal of a sweep in the tracker frame: the axis direction of a
    tube imaged in cross-section (a better start for :func:`fit_cylinder` than the points'
    spread when the sweep is shorter than the tube is wide)."""
    n = [T[:3, :3] @ calibration.T_marker_image[:3, 2] for T in poses if T is not None]
    if not n:
        raise ValueError("no frame has a pose")
    m = np.mean(n, axis=0)
    return m / np.linalg.norm(m)


@dataclass
class CylinderFit:
    """A least-squares cylinder.

    Attributes:
        point: (3,) a point on the axis (the inliers' centroid projected onto it).
        direction: (3,) unit axis direction.
        radius: mm.
        residuals: (N,) signed distance of every input point from the surface, mm.
        inliers: (N,) bool, the points kept by the outlier rejection.
        rms: RMS residual of the inliers, mm.
    """

    point: np.ndarray
    direction: np.ndarray
    radius: float
    residuals: np.ndarray
    inliers: np.ndarray
    rms: float

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[np.argmin(np.abs(d))]
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _distances(points, point, direction):
    q = points - point
    q = q - (q @ direction)[:, None] * direction
    return np.linalg.norm(q, axis=1)


def fit_cylinder(points: np.ndarray, direction_hint: np.ndarray | None = None, reject: float = 3.0, rounds: int = 3) -> CylinderFit:
    """Fit a circular cylinder to (N, 3) points by least squares on the distance to the
    surface (a robust loss, then rounds of rejecting points beyond ``reject`` robust
    sigmas and refitting).

    Args:
        points: (N, 3) mm, N >= 10.
        direction_hint: rough axis direction; None → the points' principal direction (a
            sweep along the axis is longer than the tube is wide).
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 10:
        raise ValueError(f"need (N, 3) points with N >= 10, got shape {P.shape}")
    c0 = P.mean(0)
    if direction_hint is None:
        _, _, vt = np.linalg.svd(P - c0, full_matrices=False)
        d0 = vt[0]
    else:
        d0 = np.asarray(direction_hint, dtype=np.float64)
        d0 = d0 / np.linalg.norm(d0)
    e1, e2 = _perp_basis(d0)
    # The axis passes through the cross-section's centre, not the points' centroid (the
    # points may cover only part of the circle): start from a circle fit in the plane
    # perpendicular to the axis.
    q = np.column_stack([(P - c0) @ e1, (P - c0) @ e2])
    A = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, (q**2).sum(1), rcond=None)
    r0 = float(np.sqrt(max(sol[2] + sol[:2] @ sol[:2], 1e-6)))
    x0 = np.array([sol[0], sol[1], 0.0, 0.0, r0])

    def unpack(x):
        d = d0 + x[2] * e1 + x[3] * e2
        d /= np.linalg.norm(d)
        return c0 + x[0] * e1 + x[1] * e2, d, x[4]

    keep = np.ones(len(P), bool)
    x = x0
    for _ in range(max(rounds, 1)):

        def res(x, Q=P[keep]):
            pt, d, r = unpack(x)
            return _distances(Q, pt, d) - r

        x = least_squares(res, x, loss="soft_l1", f_scale=0.1, x_scale=[1, 1, 0.01, 0.01, 1]).x
        pt, d, r = unpack(x)
        resid = _distances(P, pt, d) - r
        sigma = 1.4826 * np.median(np.abs(resid[keep] - np.median(resid[keep])))
        new_keep = np.abs(resid - np.median(resid[keep])) <= max(reject * sigma, 1e-6)
        if new_keep.sum() < 10 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    pt, d, r = unpack(x)
    resid = _distances(P, pt, d) - r
    pt = pt + ((P[keep] - pt) @ d).mean() * d
    return CylinderFit(pt, d, float(r), resid, keep, float(np.sqrt(np.mean(resid[keep] ** 2))))


def interpolate_poses(times: np.ndarray, pose_times: np.ndarray, poses: list, max_gap_s: float = 0.2) -> list:
    """Poses at ``times`` from tracked poses at ``pose_times``: translation linear,
    rotation by spherical interpolation, between the two valid poses around each time.

    A time that falls on a valid pose's time (within a microsecond) gets that pose. A time
    outside the tracked span, or between two valid poses more than ``max_gap_s`` apart
    (the marker was lost), gets None: better no frame than a guessed one.
    """
    pt = np.asarray(pose_times, dtype=np.float64)
    valid = np.array([T is not None for T in poses])
    if len(pt) != len(poses):
        raise ValueError(f"{len(pt)} pose times but {len(poses)} poses")
    t_ok = pt[valid]
    Ts = [poses[i] for i in np.flatnonzero(valid)]
    out = []
    if len(Ts) < 2:
        return [None] * len(np.atleast_1d(times))
    if np.any(np.diff(t_ok) <= 0):
        raise ValueError("pose times must increase")
    rots = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts]))
    slerp = Slerp(t_ok, rots)
    trans = np.array([T[:3, 3] for T in Ts])
    for t in np.atleast_1d(np.asarray(times, dtype=np.float64)):
        if t < t_ok[0] or t > t_ok[-1]:
            out.append(None)
            continue
        near = int(np.argmin(np.abs(t_ok - t)))
        if abs(t_ok[near] - t) < 1e-6:
            out.append(Ts[near].copy())
            continue
        j = int(np.clip(np.searchsorted(t_ok, t, side="right") - 1, 0, len(t_ok) - 2))
        if t_ok[j + 1] - t_ok[j] > max_gap_s:
            out.append(None)
            continue
        a = (t - t_ok[j]) / (t_ok[j + 1] - t_ok[j])
        T = np.eye(4)
        T[:3, :3] = slerp([t]).as_matrix()[0]
        T[:3, 3] = (1 - a) * trans[j] + a * trans[j + 1]
        out.append(T)
    return out


@dataclass
class Volume:
    """A scalar volume on an oriented grid.

    Attributes:
        data: (nx, ny, nz) uint8, indexed [i, j, k].
        origin: (3,) tracker-frame position of voxel (0, 0, 0)'s centre, mm.
        directions: (3, 3) columns are the grid steps along i, j, k in the tracker frame,
            mm (orthogonal, each of length ``spacing``).
        filled: fraction of voxels that some pixel reached before hole filling.
    """

    data: np.ndarray
    origin: np.ndarray
    directions: np.ndarray
    filled: float = 1.0

    def world(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) voxel indices → tracker mm."""
        return np.asarray(ijk, dtype=np.float64) @ self.directions.T + self.origin


def compound(
    images: list, poses: list, calibration: ProbeCalibration, voxel_mm: float = 0.3, fill_iterations: int = 3, progress: bool = False
) -> Volume:
    """Pixel-nearest-neighbour compounding of tracked frames into a volume, then hole
    filling: empty voxels take the mean of their filled neighbours (3×3×3), repeated
    ``fill_iterations`` times. The grid is aligned with the sweep (its principal axes), so
    an oblique sweep does not waste memory on an axis-aligned box.
    """
    from scipy import ndimage

    if voxel_mm <= 0:
        raise ValueError(f"voxel_mm must be > 0, got {voxel_mm}")
    frames = [(im, T) for im, T in zip(images, poses) if T is not None]
    if not frames:
        raise ValueError("no frame has a pose")
    h, w = frames[0][0].shape[:2]
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    cpts = np.concatenate([calibration.pixels_to_marker(corners) @ T[:3, :3].T + T[:3, 3] for _, T in frames])
    c = cpts.mean(0)
    _, _, vt = np.linalg.svd(cpts - c, full_matrices=False)
    R = vt.T  # columns: principal axes
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
    local = (cpts - c) @ R
    lo, hi = local.min(0), local.max(0)
    shape = np.ceil((hi - lo) / voxel_mm).astype(int) + 1
    if np.prod(shape) > 400e6:
        raise ValueError(f"volume of {tuple(shape)} voxels is too large; raise voxel_mm")
    acc = np.zeros(int(np.prod(shape)), np.float64)
    cnt = np.zeros(int(np.prod(shape)), np.float64)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    pm = calibration.pixels_to_marker(uv)
    it = frames
    if progress:
        from tqdm import tqdm

        it = tqdm(frames, desc="compound", unit="frame", leave=False)
    for im, T in it:
        X = pm @ T[:3, :3].T + T[:3, 3]
        ijk = np.rint(((X - c) @ R - lo) / voxel_mm).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < shape), axis=1)
        flat = np.ravel_multi_index(ijk[ok].T, shape)
        vals = im.reshape(-1)[ok].astype(np.float64)
        acc += np.bincount(flat, vals, minlength=acc.size)
        cnt += np.bincount(flat, minlength=cnt.size)
    acc = acc.reshape(shape)
    cnt = cnt.reshape(shape)
    filled = float((cnt > 0).mean())
    vol = np.where(cnt > 0, acc / np.maximum(cnt, 1), 0.0)
    have = cnt > 0
    for _ in range(fill_iterations):
        s = ndimage.uniform_filter(np.where(have, vol, 0.0), 3, mode="constant")
        n = ndimage.uniform_filter(have.astype(np.float64), 3, mode="constant")
        grow = (~have) & (n > 0)
        vol[grow] = s[grow] / n[grow]
        have = have | grow
    origin = c + R @ lo
    return Volume(np.clip(np.rint(vol), 0, 255).astype(np.uint8), origin, R * voxel_mm, filled)


__all__ = ["CylinderFit", "Volume", "compound", "fit_cylinder", "interpolate_poses", "sweep_normal", "tracker_points"]
