"""Freehand 3D ultrasound with a MarkerPose-tracked probe (the paper's section 5.3).

Plain functions, one module per step:
- :mod:`.probe`: the probe calibration (image → marker), saved and loaded as YAML;
- :mod:`.bmode`: a B-mode simulator (phantoms of cylinders and wires);
- :mod:`.simulate`: a simulated probe, hand-held sweeps and calibration sessions;
- :mod:`.calibrate`: probe calibration from a cross-wire (point) phantom;
- :mod:`.segment`: semi-automatic segmentation of a tube's wall and of a wire crossing;
- :mod:`.reconstruct`: 3D points, cylinder fit, volume compounding, pose interpolation;
- :mod:`.recording`: the same on a user's own recording (poses.csv + frames);
- :mod:`.experiment`: the paper's tube experiment on simulated data (``markerpose ultrasound demo``).
"""

from .bmode import Transducer, crosswire_phantom, simulate_bmode, tube_phantom
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
from .segment import RingSearch, point_target, ring_points, sweep_points
from .simulate import ProbeSetup, calibration_poses, sweep_poses

__all__ = [
    "CylinderFit",
    "ProbeCalibration",
    "ProbeSetup",
    "RingSearch",
    "Transducer",
    "Volume",
    "calibrate_probe",
    "calibration_poses",
    "compound",
    "crosswire_phantom",
    "fit_cylinder",
    "interpolate_poses",
    "point_target",
    "ring_points",
    "simulate_bmode",
    "sweep_normal",
    "sweep_points",
    "sweep_poses",
    "tracker_points",
    "tube_phantom",
]
