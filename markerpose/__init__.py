"""markerpose: accurate real-time stereo pose of a three-ring planar marker."""

from .camera import Camera, StereoRig
from .marker import Marker

__version__ = "0.1.0"
__all__ = ["Camera", "StereoRig", "Marker", "__version__"]
