"""The named pipeline configurations every experiment compares, in one place.

Each is a set of :class:`~markerpose.pipeline.MarkerPose` options. The "(paper)" rows are
the paper's configurations; the others switch on our improvements one at a time, so each
gain is measured in the same run on the same frames (DESIGN §5).
"""

from __future__ import annotations

import importlib.util

from ..ellipses import EllipseNet
from ..keypoints import KeypointNet

PAPER_POSE = {"pose": "paper", "bias_correction": False}
OURS_POSE = {"pose": "rigid", "bias_correction": True}

CLASSICAL = {
    # The paper's classical method (§3.4): binarise, contours, cv2.fitEllipse on the contour.
    "classical (paper)": {"detector": "classical", "subpixel": False, **PAPER_POSE},
    # + sub-pixel edge refinement of the outer ellipse; same centres and pose as the paper.
    "classical + sub-pixel": {"detector": "classical", "subpixel": True, **PAPER_POSE},
    # + perspective-bias correction of the centres.
    "classical + sub-pixel + bias": {"detector": "classical", "subpixel": True, "pose": "paper", "bias_correction": True},
    # + orthonormal least-squares rigid fit of the three points.
    "classical + sub-pixel + bias + rigid": {"detector": "classical", "subpixel": True, **OURS_POSE},
}

NEURAL = {
    # The paper's MarkerPose: stage 1, EllipSegNet on fixed 120 px patches, cv2.fitEllipse.
    "neural (paper)": {"detector": "neural", "ids": "head", "refine": "ellipsegnet", "patch": "fixed", "fit": "ellipse", "edge_refit": False, **PAPER_POSE},
    # + ring IDs from the marker's shape, adaptive patches and the sub-pixel iso-line fit of the mask.
    "neural + adaptive + sub-pixel": {"detector": "neural", "ids": "layout", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": False, **PAPER_POSE},
    # + perspective-bias correction and the rigid fit.
    "neural + adaptive + sub-pixel + bias + rigid": {"detector": "neural", "ids": "layout", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": False, **OURS_POSE},
    # + stage-1 candidates of both views matched by the marker's 3D shape.
    "neural + stereo match + adaptive + sub-pixel + bias + rigid": {"detector": "neural", "ids": "stereo", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": False, **OURS_POSE},
    # + the ring's outer edge fitted in the image from EllipSegNet's ellipse, without the
    # transfer fallback (matching.transfer) for markers one camera sees at 70-80°.
    "neural + stereo match (no transfer) + EllipSegNet + edge refit + bias + rigid": {"detector": "neural", "ids": "stereo", "transfer": False, "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": True, **OURS_POSE},
    # ... with the transfer fallback, but the edge fit alone under heavy motion blur.
    "neural + stereo match + EllipSegNet + edge refit (no blur fit) + bias + rigid": {"detector": "neural", "ids": "stereo", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": True, "blur_fit": False, **OURS_POSE},
    # ... and motion-blurred rings refitted under a blur model: the default, MarkerPose(rig).
    "neural + stereo match + EllipSegNet + edge refit + bias + rigid": {"detector": "neural", "ids": "stereo", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": True, **OURS_POSE},
    # ... without stage 1's second look (a 640x480 pass when the first finds no marker).
    "neural + stereo match + EllipSegNet + edge refit + bias + rigid (no second look)": {"detector": "neural", "ids": "stereo", "refine": "ellipsegnet", "patch": "adaptive", "fit": "subpixel", "edge_refit": True, "second_look": 1.0, **OURS_POSE},
    # Stage 1 (stereo match) with the classical ring fit instead of EllipSegNet.
    "neural stereo match + classical refine + bias + rigid": {"detector": "neural", "ids": "stereo", "refine": "classical", "subpixel": True, **OURS_POSE},
}


# Our best neural configuration, every switch on (the demo draws its estimates on the frames).
DEFAULT = "neural + stereo match + EllipSegNet + edge refit + bias + rigid"


def available(names=None) -> dict:
    """The configurations whose weights are present (all by default, or those in ``names``)."""
    torch = importlib.util.find_spec("torch") is not None
    have_kp = torch and KeypointNet.default_weights.is_file()
    have_es = EllipseNet.default_weights.is_file()
    every = {**NEURAL, **CLASSICAL}
    unknown = [n for n in (names or ()) if n not in every]
    if unknown:
        raise ValueError(f"unknown configuration(s) {unknown}; known: {list(every)}")
    out = {}
    for name, c in every.items():
        if names is not None and name not in names:
            continue
        if c["detector"] == "neural" and (not have_kp or (c.get("refine") == "ellipsegnet" and not have_es)):
            continue
        out[name] = c
    return out
