"""``markerpose estimate``: the marker's pose from a stereo pair of image files (JSON)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats import dumps
from .common import EXIT_NOT_FOUND, add_marker_args, add_preset_args, add_rig_arg, add_set_arg, tracker


def read_image(path) -> np.ndarray:
    """An image file as a numpy array, or ValueError naming the file (no OpenCV warning)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cannot read image {path}: no such file")
    img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot read image {path}: not an image format OpenCV can decode")
    return img


def cmd_estimate(args):
    pose_tracker = tracker(args)
    images = [read_image(p) for p in (args.left, args.right)]
    est = pose_tracker.estimate(*images)
    if est is None:
        print(dumps({"found": False}, None))
        return EXIT_NOT_FOUND
    print(dumps({"found": True, "T_left_marker": est.T, "points3d": est.points3d, "centers": est.centers, "residual_px": est.residual_px}))
    return 0


def register(sub) -> None:
    e = sub.add_parser("estimate", help="pose of the marker from a stereo pair of image files (JSON)")
    e.add_argument("left")
    e.add_argument("right")
    add_rig_arg(e)
    add_preset_args(e)
    add_set_arg(e)
    add_marker_args(e)
    e.set_defaults(func=cmd_estimate)
