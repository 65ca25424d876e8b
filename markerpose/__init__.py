"""markerpose: accurate real-time stereo pose of a three-ring planar marker."""

from __future__ import annotations

import importlib

__version__ = "0.57.0"

# The public names and the modules that define them, imported on first use: ``import
# markerpose`` stays light, so that the command line starts at once (and a Ctrl-C while it
# starts is an interruption, not a traceback from inside an import).
_PUBLIC = {
    "Camera": "camera",
    "StereoRig": "camera",
    "Marker": "marker",
    "write_target": "marker",
    "MarkerPose": "pipeline",
    "PRESETS": "presets",
    "Detection": "results",
    "Estimate": "results",
    "relative_covariances": "results",
    "relative_poses": "results",
}


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'markerpose' has no attribute {name!r}")


def __dir__() -> list:
    return sorted([*globals(), *_PUBLIC])


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
