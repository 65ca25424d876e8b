"""Drawing on images: marker axes and detected centres, tools' names (for the demo and users' own videos)."""

from __future__ import annotations

import cv2
import numpy as np

from .camera import Camera

_AXIS_COLORS = ((0, 0, 255), (0, 200, 0), (255, 80, 0))  # x red, y green, z blue (BGR)
_ID_COLORS = ((0, 255, 255), (0, 0, 255), (0, 200, 0))


def draw_axes(image: np.ndarray, camera: Camera, T_cam_marker: np.ndarray, length: float = 30.0, thickness: int = 3) -> np.ndarray:
    """Draw the marker frame's x (red), y (green), z (blue) axes of ``length`` mm.

    Args:
        image: uint8 gray (H, W) or BGR (H, W, 3); not modified.
        camera: the camera that took the image.
        T_cam_marker: (4, 4) marker → camera.
    Returns:
        BGR copy of the image with the axes drawn.
    """
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    T = np.asarray(T_cam_marker, dtype=np.float64)
    pts = np.array([[0, 0, 0], [length, 0, 0], [0, length, 0], [0, 0, length]], dtype=np.float64)
    uv = camera.project(pts @ T[:3, :3].T + T[:3, 3])
    o = tuple(int(round(v)) for v in uv[0])
    for k in range(3):
        p = tuple(int(round(v)) for v in uv[k + 1])
        cv2.arrowedLine(out, o, p, _AXIS_COLORS[k], thickness, cv2.LINE_AA, tipLength=0.15)
    return out


def draw_centers(image: np.ndarray, centers: np.ndarray, radius: int = 6) -> np.ndarray:
    """Draw the ring centres (3, 2) with their IDs c0, c1, c2; returns a BGR copy."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    for i, (x, y) in enumerate(np.asarray(centers).reshape(-1, 2)):
        c = (int(round(x)), int(round(y)))
        cv2.drawMarker(out, c, _ID_COLORS[i % 3], cv2.MARKER_CROSS, 2 * radius, 2, cv2.LINE_AA)
        cv2.putText(out, f"c{i}", (c[0] + radius, c[1] - radius), cv2.FONT_HERSHEY_SIMPLEX, 0.8, _ID_COLORS[i % 3], 2, cv2.LINE_AA)
    return out


def annotate_pair(images, est, rig, length: float = 30.0) -> np.ndarray:
    """Both views side by side (BGR), with the estimate's axes and centres drawn on each
    (the views unmarked when ``est`` is None)."""
    views = []
    for i, (img, cam) in enumerate(zip(images, rig.cameras)):
        if est is None:
            views.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy())
            continue
        T = est.T if i == 0 else rig.T_right_left @ est.T
        views.append(draw_centers(draw_axes(img, cam, T, length=length), est.centers[i]))
    return np.hstack(views)


def annotate_tools(images, found: dict, rig, length: float = 30.0) -> np.ndarray:
    """Both views side by side (BGR), with each found tool's axes drawn on each and its
    name written beside its origin (``found``: ``{name: Estimate}``, as
    :meth:`markerpose.MarkerPose.track_all` returns it; the views unmarked when empty)."""
    views = []
    for i, (img, cam) in enumerate(zip(images, rig.cameras)):
        out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
        for name, est in found.items():
            T = est.T if i == 0 else rig.T_right_left @ est.T
            out = draw_axes(out, cam, T, length=length)
            u, v = (int(round(x)) for x in cam.project(T[:3, 3][None])[0])
            org = (u + 8, v + 24)  # below right of the origin, clear of the arrows' base
            # A dark outline under the light text: readable on the white plate and on clutter.
            cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA)
        views.append(out)
    return np.hstack(views)
