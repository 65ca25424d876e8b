"""markerpose: accurate real-time stereo pose of a three-ring planar marker."""

from .camera import Camera, StereoRig
from .marker import Marker, write_target
from .pipeline import MarkerPose
from .presets import PRESETS
from .results import Detection, Estimate, relative_covariances, relative_poses

__version__ = "0.35.0"
__all__ = [
    "Camera",
    "StereoRig",
    "Marker",
    "MarkerPose",
    "PRESETS",
    "Detection",
    "Estimate",
    "write_target",
    "relative_covariances",
    "relative_poses",
    "__version__",
]
