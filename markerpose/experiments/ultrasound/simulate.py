"""A simulated freehand acquisition: a probe carrying the marker plate, swept by hand
along a tube in a water bath, watched by the stereo rig; and a cross-wire calibration
session with the same probe. :func:`write_simulated_recording` writes both as a user's
rig would record them (``markerpose ultrasound simulate``).

Frames: the phantom frame has x along the tube's axis and z pointing down (depth); the
probe images the tube in cross-section (image z along the phantom's x). The rig sees the
marker from above, about half a metre away.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ...camera import StereoRig
from ...geometry import rotation_about_axis
from ...synth import look_at_pose, render_stereo
from ...ultrasound.probe import ProbeCalibration, invert, rigid
from .bmode import Transducer, crosswire_phantom, simulate_bmode, tube_phantom

# Image axes expressed in the marker frame for a probe held under the plate: lateral
# along the marker's x, depth away from the cameras (−z), the image normal along y.
_R_MARKER_IMAGE = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
# Image axes in the phantom frame for a cross-section of the tube (axis along x).
_R_PHANTOM_IMAGE = np.column_stack([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])


def _rot_xyz(deg) -> np.ndarray:
    a = np.deg2rad(np.asarray(deg, dtype=np.float64))
    return rotation_about_axis([1, 0, 0], a[0]) @ rotation_about_axis([0, 1, 0], a[1]) @ rotation_about_axis([0, 0, 1], a[2])


@dataclass(frozen=True)
class ProbeSetup:
    """The probe, where it is held and where the rig sees it.

    Attributes:
        transducer: ultrasound imaging settings.
        lever_mm: depth of the transducer face below the plate (marker −z).
        mount_error_deg: misalignment of the image plane against the nominal mount
            (rotations about the marker's x, y, z): what the calibration has to find.
        depth_mm: depth of the tube's axis below the transducer face.
        distance_mm: distance of the marker from the left camera at mid-sweep.
        tilt_deg: tilt of the marker plate away from fronto-parallel.
    """

    transducer: Transducer = field(default_factory=Transducer)
    lever_mm: float = 110.0
    mount_error_deg: tuple = (2.0, -3.0, 1.5)
    depth_mm: float = 18.0
    distance_mm: float = 520.0
    tilt_deg: float = 25.0

    def T_marker_image(self) -> np.ndarray:
        """The true image → marker transform."""
        w, _ = self.transducer.extent_mm
        R = _rot_xyz(self.mount_error_deg) @ _R_MARKER_IMAGE
        # The image's lateral centre under the middle of the plate.
        return rigid(R, [7.5 - w / 2, 20.0, -self.lever_mm])

    def nominal_image_pose(self, x_mm: float = 0.0) -> np.ndarray:
        """T_phantom_image of a cross-section at ``x_mm`` along the tube, centred on it."""
        w, _ = self.transducer.extent_mm
        return rigid(_R_PHANTOM_IMAGE, [x_mm, -w / 2, -self.depth_mm])

    def T_left_phantom(self) -> np.ndarray:
        """Where the phantom sits in the left camera frame: chosen so that the marker of
        the nominal mid-sweep pose is at ``distance_mm``, tilted by ``tilt_deg``."""
        T_left_marker = look_at_pose(np.array([-10.0, -15.0, self.distance_mm]), tilt_deg=self.tilt_deg, tilt_axis_deg=20.0, roll_deg=10.0)
        T_phantom_marker = self.nominal_image_pose() @ invert(self.T_marker_image())
        return T_left_marker @ invert(T_phantom_marker)

    def marker_pose(self, T_phantom_image: np.ndarray) -> np.ndarray:
        """T_left_marker for a probe whose image is at ``T_phantom_image``."""
        return self.T_left_phantom() @ T_phantom_image @ invert(self.T_marker_image())


def _smooth_noise(t: np.ndarray, rng: np.random.Generator, amplitude: float, freqs=(0.7, 1.6, 3.1, 5.3)) -> np.ndarray:
    """A sum of sinusoids at hand-tremor frequencies with random phases, RMS ≈ amplitude."""
    out = np.zeros_like(t)
    for f in freqs:
        out += np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) * rng.uniform(0.5, 1.0)
    return out * amplitude / max(np.sqrt(np.mean(out**2)), 1e-12)


def sweep_poses(
    setup: ProbeSetup,
    rng: np.random.Generator,
    n_frames: int = 94,
    length_mm: float = 56.0,
    fps: float = 15.0,
    tremor_mm: float = 0.3,
    tremor_deg: float = 0.7,
    yaw_deg: float = 4.0,
    times: np.ndarray | None = None,
) -> tuple[np.ndarray, list]:
    """A hand-held sweep along the tube: times (s) and T_phantom_image per frame.

    The probe moves along the axis at constant speed with a constant yaw (the cross-sections
    are slightly oblique), plus tremor in all six degrees of freedom. ``times`` samples the
    same motion at given instants instead of ``n_frames`` at ``fps`` (e.g. the cameras' and
    the scanner's clocks).
    """
    t = np.arange(n_frames) / fps if times is None else np.asarray(times, dtype=np.float64)
    if len(t) < 2 or np.ptp(t) <= 0:
        raise ValueError("a sweep needs at least 2 frames spread in time")
    n_frames = len(t)
    xs = -length_mm / 2 + length_mm * (t - t.min()) / np.ptp(t)
    dx, dy, dz = (_smooth_noise(t, rng, tremor_mm) for _ in range(3))
    ax, ay, az = (_smooth_noise(t, rng, tremor_deg) for _ in range(3))
    base_yaw = yaw_deg + rng.uniform(-1.0, 1.0)
    poses = []
    for k in range(n_frames):
        T0 = setup.nominal_image_pose(xs[k])
        # Rotate about the point under the transducer's middle, as a hand would.
        pivot = T0[:3, :3] @ np.array([setup.transducer.extent_mm[0] / 2, 0, 0]) + T0[:3, 3]
        R = _rot_xyz([ax[k], ay[k], az[k] + base_yaw])
        T = rigid(R @ T0[:3, :3], R @ (T0[:3, 3] - pivot) + pivot + [dx[k], dy[k], dz[k]])
        poses.append(T)
    return t, poses


def calibration_poses(
    setup: ProbeSetup,
    rng: np.random.Generator,
    n: int = 30,
    point=(0.0, 0.0, 0.0),
    max_angle_deg: float = 15.0,
    elevation_sigma_mm: float = 0.15,
) -> list:
    """Probe poses that bring the wire crossing at ``point`` (phantom frame) into the image
    at varied pixels and angles: T_phantom_image per image. The operator aligns the plane
    with the crossing only to within ``elevation_sigma_mm``."""
    w, h = setup.transducer.extent_mm
    P = np.asarray(point, dtype=np.float64)
    out = []
    for _ in range(n):
        u = rng.uniform(0.2, 0.8) * w
        v = rng.uniform(0.3, 0.8) * h
        R = _R_PHANTOM_IMAGE @ _rot_xyz(rng.uniform(-max_angle_deg, max_angle_deg, 3))
        e = rng.normal(0.0, elevation_sigma_mm)
        out.append(rigid(R, P - R @ np.array([u, v, e])))
    return out


def _write_session(out: Path, rig, marker_poses: list, us_images: list, times_cam, times_us, rng, progress: bool):
    for d in ("left", "right", "us"):
        (out / d).mkdir(parents=True, exist_ok=True)
    it = range(len(marker_poses))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"render {out.name}", unit="pair", leave=False)
    for k in it:
        frame = render_stereo(rig, marker_poses[k], seed=rng)
        cv2.imwrite(str(out / "left" / f"{k:05d}.png"), frame.images[0])
        cv2.imwrite(str(out / "right" / f"{k:05d}.png"), frame.images[1])
    with open(out / "us" / "timestamps.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["file", "timestamp_s"])
        for k, (t, im) in enumerate(zip(times_us, us_images)):
            name = f"us_{k:05d}.png"
            cv2.imwrite(str(out / "us" / name), im)
            w.writerow([name, f"{t:.6f}"])


def write_simulated_recording(
    out_dir,
    n_frames: int = 20,
    seed: int = 0,
    camera_fps: float = 30.0,
    us_fps: float = 15.0,
    calibration_frames: int = 12,
    progress: bool = True,
    us_delay_s: float = 0.0,
) -> dict:
    """A recording as a user's rig would produce it, from the simulation:
    - the sweep: ``left/`` and ``right/`` camera frames at ``camera_fps``, ``us/``
      ultrasound frames with ``timestamps.csv`` at ``us_fps`` (half a camera frame late:
      the clocks are not in step);
    - ``calibration/``: the same three folders for a cross-wire session, one frame of each
      per probe position, one position a second;
    - ``probe_true.yaml``: the true calibration, to compare with.
    ``us_delay_s``: the scanner's clock runs this much late (its frames are stamped late):
    what a temporal calibration finds and ``--time-offset`` takes back.
    Returns the truth: the seed pixel inside the tube on the first frame, the true
    diameter, the paths."""
    from .experiment import TRUE_DIAMETER_MM  # the experiment imports this module

    out = Path(out_dir)
    setup, rig = ProbeSetup(), StereoRig.default()
    rng = np.random.default_rng(seed)
    # The sweep: one hand motion (9 mm/s along the tube), sampled by both clocks; the
    # scanner's frames fall between the cameras' (half a camera frame late).
    t_us = np.arange(n_frames) / us_fps + 0.5 / camera_fps
    n_cam = int(np.floor(t_us[-1] * camera_fps)) + 2
    t_cam = np.arange(n_cam) / camera_fps
    t_all = np.concatenate([t_cam, t_us])
    _, all_poses = sweep_poses(setup, rng, length_mm=9.0 * t_all.max(), times=t_all)
    cam_poses, us_poses = all_poses[:n_cam], all_poses[n_cam:]
    phantom = tube_phantom()
    us_images = [simulate_bmode(phantom, T, setup.transducer, rng) for T in us_poses]
    _write_session(out, rig, [setup.marker_pose(T) for T in cam_poses], us_images, t_cam, t_us + us_delay_s, rng, progress)
    # The calibration session: the probe held still on the wire crossing, one second per
    # position, the cameras and the scanner each taking one frame per position.
    cal = calibration_poses(setup, rng, calibration_frames)
    cw = crosswire_phantom()
    t_cal = np.arange(calibration_frames, dtype=np.float64)
    _write_session(
        out / "calibration",
        rig,
        [setup.marker_pose(T) for T in cal],
        [simulate_bmode(cw, T, setup.transducer, rng) for T in cal],
        t_cal,
        t_cal,
        rng,
        progress,
    )
    ProbeCalibration(setup.T_marker_image(), setup.transducer.spacing, setup.transducer.size).save(out / "probe_true.yaml")
    seed_px = invert(us_poses[0])[:3, 3][:2] / np.asarray(setup.transducer.spacing)
    return {
        "seed_px": seed_px,
        "diameter_mm": TRUE_DIAMETER_MM,
        "camera_fps": camera_fps,
        "us_frames": n_frames,
        "camera_frames": n_cam,
        "left": out / "left",
        "right": out / "right",
        "us": out / "us",
        "calibration": out / "calibration",
        "true_calibration": out / "probe_true.yaml",
        "spacing": setup.transducer.spacing,
        "T_phantom_image": us_poses,
        "T_left_phantom": setup.T_left_phantom(),
    }


__all__ = ["ProbeSetup", "calibration_poses", "sweep_poses", "write_simulated_recording"]
