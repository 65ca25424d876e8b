"""The paper's robot-arm experiments (§5.1), rendered in the synthetic stereo world.

Displacement: the end effector moves 10 mm at a time through 20 positions; the
distance between consecutive positions of each centre gives 19 x 3 = 57
measurements (Table 1), and d(c0,c1), d(c0,c2) over the 20 frames (Table 2).
Rotation: 7 frames 5° apart give 6 angles by ``arccos((tr(R1^T R2) - 1)/2)``
(Table 3) and the centre distances over the 7 frames (Table 4).

Because the frames are rendered, we also know the true pose of every frame and
report what the paper could not: absolute translation and rotation errors and
the pixel error of the centres. A frame where the marker is not found counts as
a failure (reported, never dropped).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..geometry import rotation_about_axis, rotation_angle
from ..marker import Marker
from ..synth import Imaging, clutter_background, look_at_pose, render_stereo

# The paper's published numbers (real images, Basler 1280x1024, EPSON C3 arm).
PAPER = {
    "displacement": {"MarkerPose": (0.0461, 0.0544, 0.1164), "Classical": (0.0446, 0.0508, 0.1086)},
    "displacement_d01": {"MarkerPose": (0.1315, 0.1326, 0.1692), "Classical": (0.1558, 0.1569, 0.1833)},
    "displacement_d02": {"MarkerPose": (0.2976, 0.2982, 0.3257), "Classical": (0.3435, 0.3448, 0.4107)},
    "rotation": {"MarkerPose": (0.0322, 0.0413, 0.0687), "Classical": (0.1107, 0.1290, 0.2317)},
    "rotation_d01": {"MarkerPose": (0.1537, 0.1548, 0.1896), "Classical": (0.1315, 0.1416, 0.2150)},
    "rotation_d02": {"MarkerPose": (0.2639, 0.2642, 0.2867), "Classical": (0.3001, 0.3011, 0.3387)},
}


@dataclass
class RobotScene:
    """Where the robot holds the marker and how it moves (left-camera frame, mm, degrees)."""

    start: tuple = (-60.0, -15.0, 480.0)  # c0 at the first displacement frame
    direction: tuple = (0.72, 0.12, 0.68)  # the end effector's x axis as seen by the cameras
    step: float = 10.0
    n_positions: int = 20
    tilt: float = 25.0  # of the marker plate
    tilt_axis: float = 60.0
    roll: float = 10.0
    rot_center: tuple = (0.0, 0.0, 560.0)  # c0 at the first rotation frame
    rot_axis: tuple = (0.15, -0.9, 0.4)  # the wrist axis
    rot_pivot: tuple = (20.0, 15.0, 30.0)  # pivot offset from c0, mm (the tool is not at the wrist)
    rot_step: float = 5.0
    n_rotations: int = 7

    def displacement_poses(self) -> list[np.ndarray]:
        d = np.asarray(self.direction, float)
        d /= np.linalg.norm(d)
        T0 = look_at_pose(self.start, self.tilt, self.tilt_axis, self.roll)
        poses = []
        for k in range(self.n_positions):
            T = T0.copy()
            T[:3, 3] = T0[:3, 3] + k * self.step * d
            poses.append(T)
        return poses

    def rotation_poses(self) -> list[np.ndarray]:
        T0 = look_at_pose(self.rot_center, self.tilt, self.tilt_axis, self.roll)
        pivot = T0[:3, 3] + np.asarray(self.rot_pivot, float)
        poses = []
        for k in range(self.n_rotations):
            Rk = rotation_about_axis(self.rot_axis, np.deg2rad(k * self.rot_step))
            T = np.eye(4)
            T[:3, :3] = Rk @ T0[:3, :3]
            T[:3, 3] = Rk @ (T0[:3, 3] - pivot) + pivot
            poses.append(T)
        return poses


@dataclass
class Sequence:
    """Rendered frames of one experiment."""

    name: str
    poses: list
    frames: list = field(default_factory=list)


def render_sequences(
    rig: StereoRig, scene: RobotScene, marker: Marker, imaging: Imaging, seed=0, progress: bool = True, which=("displacement", "rotation")
):
    """Render the displacement and rotation sequences (or those in ``which``) over one
    static cluttered lab background. The background and the noise depend on ``seed``
    only, so the same seed at another ``imaging`` gives the same scene, darker or blurred.

    Returns:
        (sequences, seconds): the sequences, and the render time of each stereo pair.
    """
    rng = np.random.default_rng(seed)
    size = rig.left.image_size
    backgrounds = (clutter_background(size, rng), clutter_background(size, rng))
    poses = {"displacement": scene.displacement_poses, "rotation": scene.rotation_poses}
    seqs = [Sequence(name, poses[name]()) for name in which]
    total = sum(len(s.poses) for s in seqs)
    seconds = []
    with tqdm(total=total, desc="render", unit="pair", disable=not progress) as bar:
        for s in seqs:
            for T in s.poses:
                t0 = time.perf_counter()
                f = render_stereo(rig, T, marker, imaging, backgrounds, rng)
                seconds.append(time.perf_counter() - t0)
                for v in f.views:
                    if not v.in_image.all():
                        raise ValueError(f"{s.name}: a ring leaves the image; adjust the RobotScene")
                s.frames.append(f)
                bar.update()
    return seqs, seconds


def error_stats(err) -> dict:
    """MAE, RMS and max (the paper's ℓ∞) of the finite errors, plus how many are missing."""
    e = np.asarray(err, dtype=np.float64)
    ok = np.isfinite(e)
    if not ok.any():
        return {"mae": np.nan, "rms": np.nan, "max": np.nan, "n": 0, "failed": int(e.size)}
    a = np.abs(e[ok])
    return {
        "mae": float(a.mean()),
        "rms": float(np.sqrt((a**2).mean())),
        "max": float(a.max()),
        "n": int(ok.sum()),
        "failed": int((~ok).sum()),
    }


def evaluate(tracker, seqs, scene: RobotScene, marker: Marker, name: str = "", progress: bool = True) -> dict:
    """Run one tracker (one preset) over the sequences and compute every metric."""
    ests = {}
    total = sum(len(s.frames) for s in seqs)
    with tqdm(total=total, desc=f"track {name}".strip(), unit="pair", disable=not progress) as bar:
        for s in seqs:
            ests[s.name] = []
            for f in s.frames:
                ests[s.name].append(tracker.estimate(*f.images))
                bar.update()
    nan3 = np.full((3, 3), np.nan)
    out = {}
    d01_ref = np.linalg.norm(marker.points3d[1] - marker.points3d[0])
    d02_ref = np.linalg.norm(marker.points3d[2] - marker.points3d[0])
    for s in seqs:
        E = ests[s.name]
        X = np.stack([e.points3d if e is not None else nan3 for e in E])  # (F, 3, 3)
        d01 = np.linalg.norm(X[:, 1] - X[:, 0], axis=1) - d01_ref
        d02 = np.linalg.norm(X[:, 2] - X[:, 0], axis=1) - d02_ref
        res = {"found": int(sum(e is not None for e in E)), "frames": len(E)}
        if s.name == "displacement":
            steps = np.linalg.norm(X[1:] - X[:-1], axis=2)  # (F-1, 3) per centre
            res["measured"] = steps.tolist()
            res["metrics"] = error_stats((steps - scene.step).ravel())
        else:
            ang = []
            for a, b in zip(E[:-1], E[1:]):
                ang.append(np.rad2deg(rotation_angle(a.R, b.R)) if a is not None and b is not None else np.nan)
            res["measured"] = ang
            res["metrics"] = error_stats(np.asarray(ang) - scene.rot_step)
        res["d01"] = error_stats(d01)
        res["d02"] = error_stats(d02)
        # Absolute errors against ground truth (failures are inf).
        t_err, r_err, px_err = [], [], []
        for e, f in zip(E, s.frames):
            T_gt = f.T_left_marker
            if e is None:
                t_err.append(np.inf)
                r_err.append(np.inf)
                px_err.extend([np.inf] * 6)
                continue
            t_err.append(float(np.linalg.norm(e.t - T_gt[:3, 3])))
            r_err.append(float(np.rad2deg(rotation_angle(e.R, T_gt[:3, :3]))))
            gt = np.stack([v.centers for v in f.views])
            px_err.extend(np.linalg.norm(e.centers - gt, axis=2).ravel().tolist())
        res["abs"] = {"translation_mm": _summary(t_err), "rotation_deg": _summary(r_err), "center_px": _summary(px_err)}
        out[s.name] = res
    return out


def _summary(x) -> dict:
    """Median, mean, max of finite values and the count of failures (inf)."""
    a = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(a)
    if not ok.any():
        return {"median": np.inf, "mean": np.inf, "max": np.inf, "failed": int(a.size)}
    return {"median": float(np.median(a[ok])), "mean": float(a[ok].mean()), "max": float(a[ok].max()), "failed": int((~ok).sum())}
