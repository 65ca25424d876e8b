"""Hand-eye calibration: the tracker's cameras and a robot in one frame.

Both setups are one equation, A_i X = Z B_i, for every robot pose i:

- **eye-to-hand** (cameras fixed, the marker on the gripper):
  T_base_gripper_i @ T_gripper_marker = T_base_camera @ T_camera_marker_i, so
  A_i = T_base_gripper_i, X = T_gripper_marker, Z = T_base_camera, B_i = T_camera_marker_i;
- **eye-in-hand** (cameras on the gripper, the marker fixed in the robot's world):
  T_base_gripper_i @ T_gripper_camera @ T_camera_marker_i = T_base_marker, so
  X = T_gripper_camera, Z = T_base_marker, B_i = inv(T_camera_marker_i).

Solved in two steps. ``"linear"``: the rotations from the null space of the stacked linear
system R_A R_X - R_Z R_B = 0 (each made a rotation), then the translations by linear least
squares (R_A t_X - t_Z = R_Z t_B - t_A). ``"refined"``: from there, nonlinear least squares
over both transforms of the rotation (radians times ``scale_mm``) and translation (mm)
residuals of A_i X against Z B_i, robust to a few bad pairs (soft-L1). OpenCV's
``calibrateRobotWorldHandEye`` solves the same problem, but the ``cv2`` of OpenCV 5.0.0
does not expose it to Python (opencv/opencv#29565), so it is done here with numpy and SciPy.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .geometry import POSE_ROTATION_TOL

SETUPS = ("eye-to-hand", "eye-in-hand")
METHODS = ("linear", "refined")
MIN_POSES = 6  # robot poses at least (15-25 recommended)
MIN_ROTATION_DEG = 10.0  # the robot's rotations' spread (sd) in their second-widest direction, at least


@dataclass
class HandEyeResult:
    """X and Z of A_i X = Z B_i (see the module's docstring) with their residuals.

    Attributes:
        X, Z: (4, 4) mm. Eye-to-hand: T_gripper_marker, T_base_camera; eye-in-hand:
            T_gripper_camera, T_base_marker.
        rot_res_deg, trans_res_mm: (N,) each pair's residual of A_i X against Z B_i.
        method: "linear" or "refined".
    """

    X: np.ndarray
    Z: np.ndarray
    rot_res_deg: np.ndarray
    trans_res_mm: np.ndarray
    method: str

    def summary(self) -> dict:
        return {
            "method": self.method,
            "rotation_rms_deg": float(np.sqrt(np.mean(self.rot_res_deg**2))),
            "translation_rms_mm": float(np.sqrt(np.mean(self.trans_res_mm**2))),
            "translation_max_mm": float(np.max(self.trans_res_mm)),
        }


def _project_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def residuals(A: np.ndarray, B: np.ndarray, X: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair, the rotation (degrees) and translation (mm) between A_i X and Z B_i."""
    L, Rr = A @ X, Z @ B
    rot = np.array([np.degrees(np.linalg.norm(cv2.Rodrigues(a[:3, :3] @ b[:3, :3].T)[0])) for a, b in zip(L, Rr)])
    return rot, np.linalg.norm(L[:, :3, 3] - Rr[:, :3, 3], axis=1)


def solve_linear(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(X, Z) of A_i X = Z B_i by the linear method (see the module's docstring)."""
    I3 = np.eye(3)
    rows = []
    for a, b in zip(A, B):
        # vec(R_A R_X) = (I kron R_A) vec(R_X); vec(R_Z R_B) = (R_B^T kron I) vec(R_Z) (column-major vec).
        rows.append(np.hstack([np.kron(I3, a[:3, :3]), -np.kron(b[:3, :3].T, I3)]))
    M = np.vstack(rows)
    v = np.linalg.svd(M)[2][-1]
    RX, RZ = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
    s = np.sign(np.linalg.det(RX)) * abs(np.linalg.det(RX)) ** (-1 / 3)  # the null vector's scale and sign
    RX, RZ = _project_rotation(s * RX), _project_rotation(s * RZ)
    C = np.vstack([np.hstack([a[:3, :3], -I3]) for a in A])
    d = np.concatenate([RZ @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    t = np.linalg.lstsq(C, d, rcond=None)[0]
    return _pose(RX, t[:3]), _pose(RZ, t[3:])


def solve_refined(A: np.ndarray, B: np.ndarray, X0: np.ndarray, Z0: np.ndarray, scale_mm: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(X, Z) refined from (X0, Z0) by robust nonlinear least squares (see the module's docstring)."""
    from scipy.optimize import least_squares

    def unpack(p):
        return _pose(cv2.Rodrigues(p[:3])[0], p[3:6]), _pose(cv2.Rodrigues(p[6:9])[0], p[9:12])

    def fun(p):
        X, Z = unpack(p)
        L, Rr = A @ X, Z @ B
        out = []
        for a, b in zip(L, Rr):
            out.append(cv2.Rodrigues(a[:3, :3] @ b[:3, :3].T)[0].ravel() * scale_mm)
            out.append(a[:3, 3] - b[:3, 3])
        return np.concatenate(out)

    p0 = np.concatenate([cv2.Rodrigues(X0[:3, :3])[0].ravel(), X0[:3, 3], cv2.Rodrigues(Z0[:3, :3])[0].ravel(), Z0[:3, 3]])
    res = least_squares(fun, p0, loss="soft_l1", f_scale=1.0)
    return unpack(res.x)


def rotation_spread_deg(A: np.ndarray) -> np.ndarray:
    """(3,) the robot's rotations' standard deviations along their principal directions, degrees."""
    from .pivot import rotation_spread

    return rotation_spread(A[:, :3, :3])


def hand_eye(T_base_gripper, T_camera_marker, setup: str = "eye-to-hand") -> dict[str, HandEyeResult]:
    """Both methods' :class:`HandEyeResult` (``{"linear": ..., "refined": ...}``) from
    paired robot poses (N, 4, 4, mm) and marker poses (N, 4, 4, mm).

    Raises:
        ValueError: an unknown setup, fewer than :data:`MIN_POSES` pairs, poses of
            another shape or whose rotation part is not a rotation.
    """
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {SETUPS}, got {setup!r}")
    A, Bc = np.asarray(T_base_gripper, np.float64), np.asarray(T_camera_marker, np.float64)
    for name, T in (("robot", A), ("marker", Bc)):
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"{name} poses must be (N, 4, 4), got {T.shape}")
        if not np.all(np.isfinite(T)):
            raise ValueError(f"{name} poses must be finite")
        bad = np.abs(np.einsum("nki,nkj->nij", T[:, :3, :3], T[:, :3, :3]) - np.eye(3)).max(axis=(1, 2)) > POSE_ROTATION_TOL
        if bad.any():
            raise ValueError(
                f"{int(bad.sum())} {name} pose(s) have a rotation part that is not a rotation (first: pair {int(np.argmax(bad))})"
            )
    if len(A) != len(Bc):
        raise ValueError(f"{len(A)} robot poses but {len(Bc)} marker poses: they must be paired")
    if len(A) < MIN_POSES:
        raise ValueError(f"hand-eye calibration needs at least {MIN_POSES} paired poses (15-25 recommended), got {len(A)}")
    B = Bc if setup == "eye-to-hand" else np.linalg.inv(Bc)
    X, Z = solve_linear(A, B)
    out = {"linear": HandEyeResult(X, Z, *residuals(A, B, X, Z), "linear")}
    Xr, Zr = solve_refined(A, B, X, Z)
    out["refined"] = HandEyeResult(Xr, Zr, *residuals(A, B, Xr, Zr), "refined")
    return out


def advice(T_base_gripper, n: int) -> list[str]:
    """What to change in the robot's poses for a better calibration (empty when nothing)."""
    tips = []
    spread = rotation_spread_deg(np.asarray(T_base_gripper, np.float64))
    if n < 15:
        tips.append(f"only {n} poses: use 15-25")
    if spread[1] < MIN_ROTATION_DEG:
        tips.append(
            f"the gripper turned {spread[1]:.1f}° (sd) in its second direction (at least {MIN_ROTATION_DEG:g}°): "
            "turn it about at least two different axes between poses"
        )
    return tips


def pair_by_time(t_robot: np.ndarray, t_poses: np.ndarray, tol_s: float) -> list[tuple[int, int]]:
    """(robot row, pose row) pairs: each robot row with the pose row nearest in time, kept
    when within ``tol_s`` seconds (each pose row used once)."""
    t_poses = np.asarray(t_poses, np.float64)
    order = np.argsort(t_poses)
    ts = t_poses[order]
    pairs, used = [], set()
    for i, t in enumerate(np.asarray(t_robot, np.float64)):
        j = int(np.searchsorted(ts, t))
        cand = [k for k in (j - 1, j) if 0 <= k < len(ts)]
        if not cand:
            continue
        k = min(cand, key=lambda k: abs(ts[k] - t))
        if abs(ts[k] - t) <= tol_s and order[k] not in used:
            used.add(int(order[k]))
            pairs.append((i, int(order[k])))
    return pairs


def _random_pose(rng, deg: float, mm: float, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    return _pose(cv2.Rodrigues(np.radians(deg) * rng.normal(size=3) / np.sqrt(3))[0], rng.normal(0, mm, 3) + np.asarray(offset))


def perturbed(rng: np.random.Generator, T: np.ndarray, mm: float, deg: float) -> np.ndarray:
    """``T`` (4, 4) with Gaussian noise of ``mm`` (per axis) on its translation and a
    rotation of ``deg`` (per axis) applied to it: a robot's or a tracker's reading of it."""
    return _pose(cv2.Rodrigues(np.radians(deg) * rng.normal(size=3))[0] @ T[:3, :3], T[:3, 3] + rng.normal(0, mm, 3))


def simulated(setup: str, n: int, rng: np.random.Generator, robot=(0.05, 0.01), tracker=(0.01, 0.005)) -> tuple:
    """A simulated calibration session: (X, Z, robot poses A (n, 4, 4), marker poses (n, 4, 4))
    with the robot's and the tracker's noise ((mm, degrees) per axis) on the poses; the
    gripper turned up to ~30° about random axes and moved ~200 mm, X and Z as the setup
    names them (see the module's docstring)."""
    X, Z = _random_pose(rng, 40, 50), _random_pose(rng, 40, 500)
    A = np.stack([_random_pose(rng, 30, 200, (400, 0, 300)) for _ in range(n)])
    if setup == "eye-to-hand":
        B = np.stack([np.linalg.inv(Z) @ a @ X for a in A])
    else:
        B = np.stack([np.linalg.inv(a @ X) @ Z for a in A])
    return X, Z, np.stack([perturbed(rng, a, *robot) for a in A]), np.stack([perturbed(rng, b, *tracker) for b in B])


__all__ = [
    "METHODS",
    "MIN_POSES",
    "SETUPS",
    "HandEyeResult",
    "advice",
    "hand_eye",
    "pair_by_time",
    "perturbed",
    "residuals",
    "simulated",
    "solve_linear",
    "solve_refined",
]
