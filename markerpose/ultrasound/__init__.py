"""Freehand 3D ultrasound with a MarkerPose-tracked probe (the paper's section 5.3).

Plain functions, one module per step:
- :mod:`.probe`: the probe calibration (image → marker), saved and loaded as YAML;
- :mod:`.calibrate`: probe calibration from a cross-wire (point) phantom;
- :mod:`.segment`: semi-automatic segmentation of a tube's wall and of a wire crossing;
- :mod:`.reconstruct`: 3D points, cylinder fit, volume compounding, pose interpolation;
- :mod:`.recording`: the same on a user's own recording (poses.csv + frames).

The simulation (B-mode images, sweeps, a simulated recording) and the paper's tube
experiment on it are in the lab, :mod:`markerpose.experiments.ultrasound`.
"""

from .calibrate import calibrate_probe
from .probe import ProbeCalibration
from .reconstruct import (
    CylinderFit,
    Volume,
    compound,
    fit_cylinder,
    interpolate_poses,
    sweep_normal,
    tracker_points,
)
from .recording import calibrate_recording, read_frames, read_track_csv, reconstruct_recording
from .segment import RingSearch, point_target, ring_points, sweep_points

__all__ = [
    "CylinderFit",
    "ProbeCalibration",
    "RingSearch",
    "Volume",
    "calibrate_probe",
    "calibrate_recording",
    "compound",
    "fit_cylinder",
    "interpolate_poses",
    "point_target",
    "read_frames",
    "read_track_csv",
    "reconstruct_recording",
    "ring_points",
    "sweep_normal",
    "sweep_points",
    "tracker_points",
]
