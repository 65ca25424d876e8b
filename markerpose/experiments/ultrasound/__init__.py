"""Freehand 3D ultrasound on simulated data: the lab side of :mod:`markerpose.ultrasound`.

- :mod:`.bmode`: a B-mode simulator (phantoms of cylinders and wires);
- :mod:`.simulate`: a simulated probe, hand-held sweeps and calibration sessions, and a
  whole recording written as a user's rig would (``markerpose ultrasound simulate``);
- :mod:`.experiment`: the paper's tube experiment (``markerpose ultrasound demo``).

What runs on real data (probe calibration, segmentation, reconstruction, recordings)
is :mod:`markerpose.ultrasound`; this package only feeds it simulated frames and poses.
"""

from .bmode import Transducer, crosswire_phantom, simulate_bmode, tube_phantom
from .simulate import ProbeSetup, calibration_poses, sweep_poses, write_simulated_recording

__all__ = [
    "ProbeSetup",
    "Transducer",
    "calibration_poses",
    "crosswire_phantom",
    "simulate_bmode",
    "sweep_poses",
    "tube_phantom",
    "write_simulated_recording",
]
