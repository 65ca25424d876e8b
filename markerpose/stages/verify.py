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
from ..settings import flag, number

default_conf = {
    "epipolar_tol": 3.0,  # max epipolar distance of same-ID refined centres, px
    "plate_check": True,  # each view's refined rings must fit one plate pose (ours)
    "max_shape_error": 2.0,  # mm: RMS misfit of the triangulated centres to the marker's layout
    # px: the six centres' RMS reprojection error above which a synchronised pair's views do not
    # fit the rig (a camera moved, the wrong rig file): no pose rather than one millimetres off
    "max_residual_px": 1.0,
}
RULES = {
    "epipolar_tol": number(0, above=True, no_limit=True),
    "plate_check": flag(),
    "max_shape_error": number(0, above=True, no_limit=True),
    "max_residual_px": number(0, above=True, no_limit=True),
}

EPIPOLAR_TOL_COARSE = 12.0  # max epipolar distance of same-ID points that could not be refined, px
PLATE_TOL = 0.05  # largest misfit of the rings' ellipses to the plate's pose (relative radius)


def plate_poses(det: Detection | None, camera, marker: Marker, tol: float) -> list:
    """The marker's poses in one view (:func:`~markerpose.geometry.view_poses`) if the best
    explains the three refined rings' ellipses within ``tol``, else []."""
    if det is None or not det.refined.all() or det.ellipses is None:
        return []
    poses = view_poses(camera, det.centers, det.ellipses, marker.points3d, marker.outer_radius)
    return poses if poses and poses[0][0] <= tol else []


VIEWS = ("left", "right")


def _unrefined_reason(det: Detection, view: str) -> str:
    """Why a view's detection has rings that do not count as refined."""
    rings = ", ".join(f"c{i}" for i in np.nonzero(~det.refined)[0])
    return (
        f"{rings} not refined in the {view} view (the sub-pixel edge fit failed, or under heavy blur the "
        "blurred-ring fit disagreed with it or could not run)"
    )


def rejection(rig, found: list, marker: Marker, conf: dict, all_refined: bool) -> str | None:
    """Why refined detections of both views may not give a pose, or None when they may:
    every centre refined (when ``all_refined``), same-ID centres on each other's
    epipolar lines and, with ``plate_check``, each view's rings on one plate."""
    for det, view in zip(found, VIEWS):
        if det is None:
            return f"nothing to refine in the {view} view"
    if all_refined:
        for det, view in zip(found, VIEWS):
            if not det.refined.all():
                return _unrefined_reason(det, view)
    # The IDs give the correspondences; the epipolar constraint checks them.
    d = np.diag(epipolar_distance(rig, found[0].centers, found[1].centers))
    both = found[0].refined & found[1].refined
    tol = np.where(both, conf["epipolar_tol"], EPIPOLAR_TOL_COARSE)
    if np.any(d > tol):
        i = int(np.argmax(d - tol))
        return f"epipolar check: c{i} is {d[i]:.1f} px from its epipolar line (limit {tol[i]:g} px)"
    if conf["plate_check"]:
        for det, cam, view in zip(found, rig.cameras, VIEWS):
            if det.ellipses is not None and det.refined.all():
                reason = plate_rejection(det, cam, marker, PLATE_TOL, view)
                if reason is not None:
                    return reason
    return None


def plate_rejection(det: Detection, camera, marker: Marker, tol: float, view: str) -> str | None:
    """Why one view's refined rings fit no pose of the marker plate within ``tol`` (the
    misfit and the limit), or None when they do."""
    if det is None:
        return f"the {view} view's rings could not be refined"
    if plate_poses(det, camera, marker, tol):
        return None
    if not det.refined.all():
        return _unrefined_reason(det, view)
    if det.ellipses is None:
        return f"the {view} view's rings have no fitted ellipses to check"
    poses = view_poses(camera, det.centers, det.ellipses, marker.points3d, marker.outer_radius)
    misfit = f"{poses[0][0]:.3f}" if poses else "no pose"
    return f"plate check: the {view} view's rings fit no pose of the marker (misfit {misfit}, limit {tol:g})"


def pair(rig, found: list, marker: Marker, conf: dict, all_refined: bool) -> bool:
    """Whether refined detections of both views may give a pose (:func:`rejection` is None)."""
    return rejection(rig, found, marker, conf, all_refined) is None


def shape_error(points3d: np.ndarray, model: np.ndarray) -> float:
    """RMS distance (mm) between measured points (N, 3) and the rigidly fitted model (N, 3)."""
    T = pose_rigid(points3d, model)
    fitted = model @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((fitted - points3d) ** 2, axis=1))))


def shape(points3d: np.ndarray, marker: Marker, conf: dict) -> bool:
    """Whether triangulated centres (3, 3) have the marker's shape: a wrong triple (a
    decoy, an occluded ring replaced by something else) does not."""
    return shape_error(points3d, marker.points3d) <= conf["max_shape_error"]


__all__ = [
    "EPIPOLAR_TOL_COARSE",
    "PLATE_TOL",
    "RULES",
    "default_conf",
    "pair",
    "plate_poses",
    "plate_rejection",
    "rejection",
    "shape",
    "shape_error",
]
