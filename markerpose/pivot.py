"""Pivot calibration: a pointer's tip from a recording of the tool pivoting about it.

While the tip rests in a divot and the tool turns about it, every pose T_i = (R_i, t_i)
maps the tip (fixed in the marker frame) to the same point in the tracker's frame:

    R_i tip + t_i = pivot   for every i,   i.e.   [R_i  -I] [tip; pivot] = -t_i,

3 equations a pose, 6 unknowns: one linear least-squares problem for all poses (the
algebraic method of PLUS's fCal and SlicerIGT). Poses that do not fit (the tip slipped,
a wrong pose) are rejected by their residual |R_i tip + t_i - pivot| against a robust
scale (the median absolute deviation), and the fit repeated until no pose changes side.

The tip along an axis the tool never turned about is not determined: the rotations'
spread is checked (:data:`MIN_SPREAD_DEG` in at least two independent directions), as
is the number of poses kept (:data:`MIN_POSES`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .geometry import POSE_ROTATION_TOL

MIN_POSES = 20  # poses kept, at least
MIN_SPREAD_DEG = 5.0  # the rotations' spread (sd) in their second-widest direction, at least
REJECT_K = 3.0  # a pose is an outlier beyond this many robust sigmas of the residuals ...
REJECT_MIN_MM = 0.05  # ... and beyond this, mm (noise-free data has no scale)


@dataclass
class PivotResult:
    """What :func:`pivot_calibration` found.

    Attributes:
        tip_mm: (3,) the tip in the marker's frame, mm.
        pivot_mm: (3,) the pivot point in the poses' frame (the camera's, or a
            reference's), mm.
        rmse_mm: RMS of the kept poses' residuals |R_i tip + t_i - pivot|, mm.
        residuals_mm: (N,) every pose's residual, mm.
        inliers: (N,) bool, the poses kept.
        spread_deg: (3,) the rotations' standard deviations along their principal
            directions, widest first, degrees.
        tip_sd_mm, pivot_sd_mm: RMS 3D standard deviations of the two points from the
            least-squares fit (sqrt of the trace of their covariance), mm.
        verdict: "ok", or what is wrong ("too few poses ...", "too little rotation ...").
    """

    tip_mm: np.ndarray
    pivot_mm: np.ndarray
    rmse_mm: float
    residuals_mm: np.ndarray = field(repr=False)
    inliers: np.ndarray = field(repr=False)
    spread_deg: np.ndarray
    tip_sd_mm: float
    pivot_sd_mm: float
    verdict: str

    @property
    def ok(self) -> bool:
        return self.verdict == "ok"

    def to_dict(self) -> dict:
        """The result as plain numbers (the keys ``tip_mm``, ``pivot_mm``, ``rmse_mm`` first)."""
        return {
            "tip_mm": [float(v) for v in self.tip_mm],
            "pivot_mm": [float(v) for v in self.pivot_mm],
            "rmse_mm": float(self.rmse_mm),
            "poses": int(len(self.inliers)),
            "poses_kept": int(self.inliers.sum()),
            "spread_deg": [float(v) for v in self.spread_deg],
            "tip_sd_mm": float(self.tip_sd_mm),
            "pivot_sd_mm": float(self.pivot_sd_mm),
            "verdict": self.verdict,
        }


def _solve(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tip, pivot, (6, 6) (A^T A)^-1) of the stacked system for poses R (N, 3, 3), t (N, 3)."""
    n = len(R)
    A = np.concatenate([R, -np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = -t.reshape(-1)
    AtA = A.T @ A
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return x[:3], x[3:], np.linalg.pinv(AtA)


def rotation_spread(R: np.ndarray) -> np.ndarray:
    """(3,) standard deviations (degrees, widest first) of the rotations R (N, 3, 3) about
    their mean, along the principal directions of their rotation vectors."""
    U, _, Vt = np.linalg.svd(R.mean(0))
    mean = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    w = np.array([cv2.Rodrigues(Ri @ mean.T)[0].ravel() for Ri in R])
    ev = np.linalg.eigvalsh(np.cov(w.T) if len(w) > 1 else np.zeros((3, 3)))[::-1]
    return np.degrees(np.sqrt(np.maximum(ev, 0.0)))


def pivot_calibration(poses, max_rounds: int = 10) -> PivotResult:
    """The tip and the pivot point from poses of a tool pivoting about its tip.

    Args:
        poses: (N, 4, 4) T_frame_marker, mm (e.g. a ``markerpose track`` CSV's found rows).
        max_rounds: rounds of rejection and refit at most.
    Raises:
        ValueError: fewer than 3 poses, or poses that are not rigid transforms.
    """
    T = np.asarray(poses, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (N, 4, 4), got {T.shape}")
    if len(T) < 3:
        raise ValueError(f"a pivot calibration needs poses of the tool turning about its tip; got {len(T)} pose(s)")
    if not np.all(np.isfinite(T)):
        raise ValueError("poses must be finite")
    R, t = T[:, :3, :3], T[:, :3, 3]
    bad = np.abs(np.einsum("nki,nkj->nij", R, R) - np.eye(3)).max(axis=(1, 2)) > POSE_ROTATION_TOL
    if bad.any():
        raise ValueError(f"{int(bad.sum())} pose(s) have a rotation part that is not a rotation (first: pose {int(np.argmax(bad))})")
    keep = np.ones(len(T), bool)
    for _ in range(max_rounds):
        tip, pivot, _ = _solve(R[keep], t[keep])
        res = np.linalg.norm(R @ tip + t - pivot, axis=1)
        scale = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
        limit = max(np.median(res[keep]) + REJECT_K * scale, REJECT_MIN_MM)
        new = res <= limit
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    tip, pivot, C = _solve(R[keep], t[keep])
    res = np.linalg.norm(R @ tip + t - pivot, axis=1)
    n = int(keep.sum())
    rmse = float(np.sqrt(np.mean(res[keep] ** 2)))
    s2 = float(np.sum(res[keep] ** 2)) / max(3 * n - 6, 1)  # the residual variance per coordinate
    cov = s2 * C
    spread = rotation_spread(R[keep])
    if n < MIN_POSES:
        verdict = f"too few poses: {n} kept of {len(T)} (at least {MIN_POSES})"
    elif spread[1] < MIN_SPREAD_DEG:
        verdict = (
            f"too little rotation: the tool turned {spread[1]:.1f}° (sd) in its second direction (at least {MIN_SPREAD_DEG:g}°); "
            "tilt it both ways about the tip"
        )
    else:
        verdict = "ok"
    return PivotResult(
        tip_mm=tip,
        pivot_mm=pivot,
        rmse_mm=rmse,
        residuals_mm=res,
        inliers=keep,
        spread_deg=spread,
        tip_sd_mm=float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))),
        pivot_sd_mm=float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))),
        verdict=verdict,
    )


def pivoting_poses(tip, pivot, n: int, max_deg: float, rng: np.random.Generator, R0: np.ndarray | None = None) -> np.ndarray:
    """(n, 4, 4) poses of a tool turning about its tip (``tip`` in its frame) resting at
    ``pivot``: rotations R0 tilted up to ``max_deg`` about random axes perpendicular to
    R0's z (the shaft, as a hand pivots a pointer) and turned about it."""
    R0 = np.eye(3) if R0 is None else np.asarray(R0, np.float64)
    out = np.empty((n, 4, 4))
    for i in range(n):
        a = rng.uniform(0, 2 * np.pi)
        tilt = cv2.Rodrigues(np.radians(rng.uniform(0, max_deg)) * np.array([np.cos(a), np.sin(a), 0.0]))[0]
        spin = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(rng.uniform(-20, 20))]))[0]
        R = tilt @ R0 @ spin
        out[i] = np.eye(4)
        out[i, :3, :3] = R
        out[i, :3, 3] = np.asarray(pivot, np.float64) - R @ np.asarray(tip, np.float64)
    return out


__all__ = ["MIN_POSES", "MIN_SPREAD_DEG", "PivotResult", "pivot_calibration", "pivoting_poses", "rotation_spread"]
