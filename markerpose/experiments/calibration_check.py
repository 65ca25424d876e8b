"""The calibration procedure checked on rendered images of a known rig
(``markerpose calibrate --rendered N``).

- :func:`rendered_pairs`: stereo pairs of the circle grid held as by hand, rendered with
  :func:`markerpose.synth.render_target_view`;
- :func:`check`: a calibration against the rig that rendered its images.

The calibration itself (:func:`markerpose.calibration.calibrate`) is the one real pairs
go through.
"""

from __future__ import annotations

import numpy as np

from ..calibration import Calibration, CircleGrid
from ..camera import StereoRig
from ..geometry import rotation_angle
from ..synth import look_at_pose, render_target_view


def rendered_pairs(rig: StereoRig, grid: CircleGrid, n: int = 21, seed: int = 0, imaging=None):
    """``n`` rendered stereo pairs of ``grid`` held where both cameras see all of it:
    380–750 mm away, tilted up to 45° about any axis, turned any way in its plane
    (what a calibration session by hand gives). Returns (pairs, poses T_left_grid)."""
    rng = np.random.default_rng(seed)
    c = grid.points3d.mean(0)
    w, h = rig.left.image_size
    pairs, poses = [], []
    while len(pairs) < n:
        z = rng.uniform(380, 750)
        T = look_at_pose(
            [rng.uniform(-0.12, 0.12) * z - 0.12 * (z - 560), rng.uniform(-0.12, 0.12) * z, z],
            rng.uniform(0, 45),
            rng.uniform(0, 360),
            rng.uniform(0, 360),
        )
        T[:3, 3] -= T[:3, :3] @ c
        X = grid.points3d @ T[:3, :3].T + T[:3, 3]
        uv = rig.project(X)
        margin = 3 * grid.radius * rig.left.K[0, 0] / z + 5
        if not np.all((uv[..., 0] > margin) & (uv[..., 0] < w - margin) & (uv[..., 1] > margin) & (uv[..., 1] < h - margin)):
            continue
        T_right = rig.T_right_left @ T
        pairs.append(tuple(render_target_view(cam, Tc, grid, imaging, seed=rng) for cam, Tc in ((rig.left, T), (rig.right, T_right))))
        poses.append(T)
    return pairs, poses


def check(rig: StereoRig, cal: Calibration) -> dict:
    """A calibration against the rig that rendered its images: focal lengths (relative),
    principal points (px), baseline (mm), rotation between the cameras (deg)."""
    out = {}
    for name, a, b in (("left", rig.left, cal.rig.left), ("right", rig.right, cal.rig.right)):
        out[f"f_{name}_rel_error"] = float(np.max(np.abs(np.diag(b.K)[:2] / np.diag(a.K)[:2] - 1)))
        out[f"c_{name}_px_error"] = float(np.linalg.norm(b.K[:2, 2] - a.K[:2, 2]))
    out["baseline_mm_error"] = float(abs(np.linalg.norm(cal.rig.t) - np.linalg.norm(rig.t)))
    out["t_mm_error"] = float(np.linalg.norm(cal.rig.t - rig.t))
    out["R_deg_error"] = float(np.degrees(rotation_angle(cal.rig.R, rig.R)))
    return out


__all__ = ["check", "rendered_pairs"]
