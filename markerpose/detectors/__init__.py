"""Detectors, found by name: each turns a call's images into hypotheses of both views
(:class:`~markerpose.detectors.base.Detector`). A new detector is one module here and one
line in :data:`DETECTORS`.
"""

from __future__ import annotations

from .base import Detector, NeuralDetector
from .decoded import DecodedDetector
from .rings import ClassicalDetector
from .stereo import StereoDetector

DETECTORS: dict[str, type[Detector]] = {
    "stereo": StereoDetector,  # ours: stage-1 candidates matched across views by the 3D shape
    "decoded": DecodedDetector,  # the paper's: one triple per view by the ID head (or the layout)
    "classical": ClassicalDetector,  # the paper's classical detector (§3.4)
}


def name_for(conf: dict) -> str:
    """The detector a resolved configuration asks for: ``detector`` names it, where
    "neural" (stage 1) means the stereo or the decoded detector by ``match.method``."""
    if conf["detector"] != "neural":
        return conf["detector"]
    return "stereo" if conf["match"]["method"] == "stereo" else "decoded"


def create(conf: dict, rig, marker, refiner, threads: int | None = None, backend: str = "onnxruntime") -> Detector:
    """The detector of a resolved configuration (:func:`name_for`), built."""
    cls = DETECTORS[name_for(conf)]
    if cls.neural:
        return cls(conf, rig, marker, refiner, threads, backend)
    return cls(conf, rig, marker, refiner)


__all__ = ["DETECTORS", "ClassicalDetector", "DecodedDetector", "Detector", "NeuralDetector", "StereoDetector", "create", "name_for"]
