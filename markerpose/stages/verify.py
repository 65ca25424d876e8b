"""Verify: a pose only from rings that are the marker, never a wrong pose.

Checks, cheapest first: with the edge refit, all six centres must be edge-fitted; the
same-ID centres of the two views must lie on each other's epipolar lines
(``epipolar_tol``, looser for points that could not be refined); each view's three
refined rings must fit one pose of the marker plate (``plate_check``, ours: P3P ranked
by how the projected circles fit the fitted ellipses, :func:`markerpose.geometry.view_poses`);
and the triangulated centres must have the marker's shape (``max_shape_error``, mm).
"""

from __future__ import annotations

import numpy as np

from ..geometry import epipolar_distance, pose_rigid, view_poses
from ..marker import Marker
from ..results import Detection

default_conf = {
    "epipolar_tol": 3.0,  # max epipolar distance of same-ID refined centres, px
    "epipolar_tol_coarse": 12.0,  # ... of points that could not be refined, px
    "plate_check": True,  # each view's refined rings must fit one plate pose (ours)
    "plate_tol": 0.05,  # largest misfit of the rings' ellipses to that pose (relative radius)
    "max_shape_error": 2.0,  # mm: RMS misfit of the triangulated centres to the marker's layout
}


def plate_poses(det: Detection | None, camera, marker: Marker, tol: float) -> list:
    """The marker's poses in one view (:func:`~markerpose.geometry.view_poses`) if the best
    explains the three refined rings' ellipses within ``tol``, else []."""
    if det is None or not det.refined.all() or det.ellipses is None:
        return []
    poses = view_poses(camera, det.centers, det.ellipses, marker.points3d, marker.outer_radius)
    return poses if poses and poses[0][0] <= tol else []


def pair(rig, found: list, marker: Marker, conf: dict, all_refined: bool) -> bool:
    """Whether refined detections of both views may give a pose: every centre refined
    (when ``all_refined``), same-ID centres on each other's epipolar lines and, with
    ``plate_check``, each view's rings on one plate."""
    if found[0] is None or found[1] is None:
        return False
    if all_refined and not (found[0].refined.all() and found[1].refined.all()):
        return False
    # The IDs give the correspondences; the epipolar constraint checks them.
    d = np.diag(epipolar_distance(rig, found[0].centers, found[1].centers))
    both = found[0].refined & found[1].refined
    if np.any(d > np.where(both, conf["epipolar_tol"], conf["epipolar_tol_coarse"])):
        return False
    if conf["plate_check"]:
        for det, cam in zip(found, rig.cameras):
            if det.ellipses is not None and det.refined.all() and not plate_poses(det, cam, marker, conf["plate_tol"]):
                return False
    return True


def shape_error(points3d: np.ndarray, model: np.ndarray) -> float:
    """RMS distance (mm) between measured points (N, 3) and the rigidly fitted model (N, 3)."""
    T = pose_rigid(points3d, model)
    fitted = model @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((fitted - points3d) ** 2, axis=1))))


def shape(points3d: np.ndarray, marker: Marker, conf: dict) -> bool:
    """Whether triangulated centres (3, 3) have the marker's shape: a wrong triple (a
    decoy, an occluded ring replaced by something else) does not."""
    return shape_error(points3d, marker.points3d) <= conf["max_shape_error"]


__all__ = ["default_conf", "pair", "plate_poses", "shape", "shape_error"]
