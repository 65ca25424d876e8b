"""Any planar target rendered as the marker is: a calibration grid, a peer's fiducial.

A target has a ``reflectance(xy)`` (plane points (..., 2), mm → [0, 1], NaN off it) and
a ``plate`` (x0, y0, x1, y1), mm. Each pixel's ray goes through the lens model onto the
plane; pixels whose footprint straddles an edge of the texture are supersampled; then
the renderer's light, optics and sensor (:func:`markerpose.synth.render.expose`).
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from .background import clutter_background
from .render import Imaging, expose, plane_coords, plate_bbox


def render_target_view(camera: Camera, T_cam_target: np.ndarray, target, imaging=None, background=None, seed=0) -> np.ndarray:
    """One view of a planar ``target``.

    Args:
        camera: the view.
        T_cam_target: (4, 4) pose of the target's plane in the camera frame, mm.
        target: has ``reflectance(xy)`` and ``plate`` (see the module).
        imaging: :class:`Imaging` (default ``Imaging()``); ``supersample`` is the edge
            pixels' S (S x S samples).
        background: float (H, W) scene behind the target, reflectance units (default: a
            random clutter background).
        seed: int or ``np.random.Generator``.
    Returns uint8 (H, W).
    """
    imaging = imaging or Imaging()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    w, h = camera.image_size
    scene = clutter_background((w, h), rng) if background is None else np.asarray(background, np.float32).copy()
    T = np.asarray(T_cam_target, np.float64)
    bbox = plate_bbox(camera, T, target)  # only pixels that can see the sheet are cast
    if bbox is not None:
        bx0, by0, bx1, by1 = bbox
        _paint(camera, T, target, imaging, scene, (slice(by0, by1), slice(bx0, bx1)))
    return expose(scene, (w, h), imaging, rng)


def _paint(camera: Camera, T: np.ndarray, target, imaging, scene: np.ndarray, box: tuple) -> None:
    """Ray-cast the target into ``scene[box]`` (in place), edge pixels supersampled."""
    # The box grown by one pixel, so the differences below are central up to its edge.
    h, w = scene.shape
    ys, xs = box
    gy0, gy1, gx0, gx1 = max(ys.start - 1, 0), min(ys.stop + 1, h), max(xs.start - 1, 0), min(xs.stop + 1, w)
    grid = camera.normalized_grid()[gy0:gy1, gx0:gx1]
    inner = (slice(ys.start - gy0, ys.stop - gy0), slice(xs.start - gx0, xs.stop - gx0))
    Hinv = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    mx, my = plane_coords(Hinv, grid[..., 0], grid[..., 1])
    front = Hinv[2, 0] * grid[..., 0] + Hinv[2, 1] * grid[..., 1] + Hinv[2, 2]  # > 0: the plane lies ahead
    # The pixel's footprint on the plane.
    foot = 0.75 * (np.hypot(np.gradient(mx, axis=1), np.gradient(my, axis=1)) + np.hypot(np.gradient(mx, axis=0), np.gradient(my, axis=0)))
    J_u, J_v = np.gradient(grid, axis=1)[inner], np.gradient(grid, axis=0)[inner]
    grid, mx, my, front, foot = grid[inner], mx[inner], my[inner], front[inner], foot[inner]
    sub = scene[box]
    val = target.reflectance(np.stack([mx, my], -1))
    # Edge pixels: the texture differs across the pixel's footprint.
    near = np.zeros(mx.shape, bool)
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = target.reflectance(np.stack([mx + sx * foot, my + sy * foot], -1))
            near |= ~((c == val) | (np.isnan(c) & np.isnan(val)))
    S = imaging.supersample
    iy, ix = np.nonzero(near)
    if len(iy) and S > 1:
        off = (np.arange(S) + 0.5) / S - 0.5
        du, dv = (a.ravel()[None, :] for a in np.meshgrid(off, off))
        chunk = max(1, 400_000 // (S * S))
        for k in range(0, len(iy), chunk):
            yy, xx = iy[k : k + chunk], ix[k : k + chunk]
            sx = grid[yy, xx, 0][:, None] + J_u[yy, xx, 0][:, None] * du + J_v[yy, xx, 0][:, None] * dv
            sy = grid[yy, xx, 1][:, None] + J_u[yy, xx, 1][:, None] * du + J_v[yy, xx, 1][:, None] * dv
            smx, smy = plane_coords(Hinv, sx, sy)
            v = target.reflectance(np.stack([smx, smy], -1))
            val[yy, xx] = np.where(np.isnan(v), sub[yy, xx][:, None], v).mean(1)
    on = np.isfinite(val) & (front > 0)
    sub[on] = val[on]


__all__ = ["render_target_view"]
