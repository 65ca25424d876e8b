"""Physically honest renderer of the marker seen by a calibrated camera or stereo rig.

How an image is made (docs/design.md §8):

1. Geometry: every pixel's ray is cast through the inverse lens-distortion model
   (``Camera.normalized_grid``) onto the marker plane, where the printed texture is
   evaluated analytically (``Marker.reflectance``). Pixels whose footprint straddles
   a ring or plate edge are supersampled on an S x S grid (S = 16 by default), so
   the pixel value is the pixel's area coverage — edges land where the geometry
   says to well under 0.01 px.
2. Light: the scene (plate over a background) is multiplied by an illumination
   field (linear gradient) and the lens vignetting, and by the exposure gain
   ``alpha`` (the paper's darkness factor).
3. Optics and motion: a Gaussian PSF and an optional linear motion-blur kernel.
4. Sensor: photo-electrons with Poisson shot noise, Gaussian read noise, 8-bit
   quantisation with clipping. Defaults are of the order of the PYTHON 1300
   sensor of the paper's Basler acA1300-200um: ~10 ke- full well, ~10 e- read noise.

Ground truth comes with every view: the projected 3D ring centres, the imaged
outer/inner ellipses as conics (ideal, undistorted pixels) and their centres,
a ring-ID mask and the pose. Everything is deterministic for a given seed.
:func:`render_tools` puts several tools in one stereo pair, nearer plates painted over
farther ones, with each tool's truth and how much of each ring is seen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import Camera, StereoRig
from ..geometry import circle_conic, imaged_circle_centers, plane_homography, project_conic
from ..marker import Marker
from .background import clutter_background


@dataclass(frozen=True)
class Imaging:
    """Illumination, optics and sensor settings for one view.

    Attributes:
        alpha: exposure gain, the paper's darkness factor (1 = normal, 0.039 = darkest tested).
        exposure: fraction of the full well that white paper reaches at alpha = 1.
        gradient: illumination falls off linearly by this fraction across the image diagonal.
        gradient_angle: direction of the illumination gradient, degrees.
        vignetting: relative brightness loss in the image corners (cos^4-like falloff).
        psf_sigma: Gaussian PSF sigma, px (0 = none).
        motion_blur: linear motion-blur kernel length, px (0 = none).
        motion_angle: direction of the motion, degrees.
        full_well: electrons at which the 8-bit output saturates (255).
        read_noise: read noise, electrons rms.
        noise: add shot and read noise (False gives the noise-free expectation, still 8-bit).
        quantize: round to 8 bits (False returns the float image ×255, for tests).
        supersample: S for the S x S anti-aliasing grid of edge pixels.
        paper, ink: reflectance of the paper and of the printed black.
        plate_light: None, or a function of marker-plane points (mx, my) in mm giving the
            light on the plate relative to the rest of the scene (shadows, uneven light on
            the plate; :mod:`markerpose.synth.realism`).
        gamma: camera response: the 8-bit output raised to this power (1 = linear).
        resample: the image shrunk by this factor and enlarged back (1 = none), as an
            image passed through a smaller format is.
        jpeg_quality: JPEG-compressed at this quality (0 = not compressed).
    """

    alpha: float = 1.0
    exposure: float = 0.8
    gradient: float = 0.15
    gradient_angle: float = 30.0
    vignetting: float = 0.15
    psf_sigma: float = 0.6
    motion_blur: float = 0.0
    motion_angle: float = 0.0
    full_well: float = 10_000.0
    read_noise: float = 10.0
    noise: bool = True
    quantize: bool = True
    supersample: int = 16
    paper: float = 0.85
    ink: float = 0.04
    plate_light: object = None
    gamma: float = 1.0
    resample: float = 1.0
    jpeg_quality: int = 0

    def __post_init__(self):
        if not self.alpha > 0:
            raise ValueError(f"alpha must be > 0, got {self.alpha}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if self.motion_blur < 0 or self.psf_sigma < 0:
            raise ValueError("motion_blur and psf_sigma must be >= 0")

    @classmethod
    def ideal(cls, **kw) -> Imaging:
        """Noise-free, blur-free, evenly lit, unquantised: for geometric tests."""
        base = {"gradient": 0.0, "vignetting": 0.0, "psf_sigma": 0.0, "noise": False, "quantize": False}
        base.update(kw)
        return cls(**base)


@dataclass
class ViewTruth:
    """Ground truth of one rendered view.

    Attributes:
        T_cam_marker: (4, 4) marker → this camera.
        centers: (3, 2) projected 3D ring centres (distorted px), by ID.
        outer_conics, inner_conics: (3, 3, 3) imaged ring circles as conics in ideal
            (undistorted) pixels.
        outer_centers: (3, 2) centres of the imaged outer ellipses, mapped into distorted
            px (they differ from ``centers`` by the perspective bias).
        mask: (H, W) uint8, ring ID + 1 where the pixel centre lies inside a ring's
            outer circle, 0 elsewhere.
        in_image: (3,) bool, the whole outer circle of the ring lies inside the image.
    """

    T_cam_marker: np.ndarray
    centers: np.ndarray
    outer_conics: np.ndarray
    inner_conics: np.ndarray
    outer_centers: np.ndarray
    mask: np.ndarray
    in_image: np.ndarray


@dataclass
class StereoFrame:
    """A rendered stereo pair with its ground truth."""

    images: list
    views: list
    T_left_marker: np.ndarray
    imaging: tuple = field(default=(), repr=False)


@dataclass
class ToolTruth:
    """Ground truth of one tool in a :class:`ToolsFrame`.

    Attributes:
        marker: the tool.
        T_left_marker: (4, 4) tool → left camera, mm.
        views: the left (0) and right (1) :class:`ViewTruth`, whose ``mask`` is 0 where a
            nearer plate covers the ring.
        visible: (2, 3) per view and ring, the fraction of the ring's outer disk that is in
            the image and not covered by a nearer plate (pixel centres, as ``mask`` counts
            them; exactly 1.0 when the whole ring is in the image and no pixel of it is covered).
    """

    marker: Marker
    T_left_marker: np.ndarray
    views: list
    visible: np.ndarray

    @property
    def fully_visible(self) -> bool:
        """Every ring of both views wholly in the image (``in_image``) and no pixel of it covered."""
        return bool(all(v.in_image.all() for v in self.views) and np.all(self.visible >= 1.0))


@dataclass
class ToolsFrame:
    """A rendered stereo pair of several tools, with each tool's ground truth by name."""

    images: list
    truths: dict
    imaging: tuple = field(default=(), repr=False)


# --- geometry of the view --------------------------------------------------------------
def _ring_truth(camera: Camera, T: np.ndarray, marker: Marker):
    H = plane_homography(camera.K, T)
    c2 = marker.centers2d
    outer = np.stack([project_conic(circle_conic(c, marker.outer_radius), H) for c in c2])
    inner = np.stack([project_conic(circle_conic(c, marker.inner_radius), H) for c in c2])
    outer_centers = imaged_circle_centers(camera, T, c2, marker.outer_radius)
    centers, _ = cv2.projectPoints(marker.points3d, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], camera.K, camera.dist)
    return centers.reshape(3, 2), outer, inner, outer_centers


def _circle_points(marker: Marker, n: int = 64) -> np.ndarray:
    """(3, n, 3) points on each ring's outer circle, marker frame."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * marker.outer_radius
    return marker.points3d[:, None, :] + ring[None]


def _rim_pixels(camera: Camera, T: np.ndarray, marker: Marker, n: int = 64) -> np.ndarray:
    """(3, n, 2) each ring's outer circle projected into ``camera`` (distorted px)."""
    rim = _circle_points(marker, n) @ T[:3, :3].T + T[:3, 3]
    return camera.project(rim.reshape(-1, 3)).reshape(3, -1, 2)


def _view_truth(camera: Camera, T: np.ndarray, marker: Marker, mask: np.ndarray) -> ViewTruth:
    """The :class:`ViewTruth` of a plate rendered at ``T`` whose ring-ID mask is ``mask``."""
    w, h = camera.image_size
    centers, outer, inner, outer_centers = _ring_truth(camera, T, marker)
    uv = _rim_pixels(camera, T, marker)
    in_image = np.all((uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1), axis=1)
    return ViewTruth(T, centers, outer, inner, outer_centers, mask, in_image)


def _plate_pixels(camera: Camera, T: np.ndarray, marker: Marker) -> np.ndarray:
    """(H, W) bool: the pixels whose centre's ray meets the plate, the test by which
    :func:`_render_plate` paints a pixel with the plate rather than what lies behind it.
    Exact under lens distortion, where the plate's straight edges image as curves."""
    w, h = camera.image_size
    on = np.zeros((h, w), bool)
    bbox = plate_bbox(camera, T, marker)
    if bbox is None:
        return on
    bx0, by0, bx1, by1 = bbox
    grid = camera.normalized_grid()[by0:by1, bx0:bx1]
    Hinv = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    mx, my = plane_coords(Hinv, grid[..., 0], grid[..., 1])
    x0, y0, x1, y1 = marker.plate
    on[by0:by1, bx0:bx1] = (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)
    return on


def _disk_areas(camera: Camera, T: np.ndarray, marker: Marker) -> np.ndarray:
    """(3,) area (px²) of each ring's outer disk imaged by ``camera``, the parts beyond the
    image's edges included: its projected rim as a 256-gon (area short by ~1e-4)."""
    uv = _rim_pixels(camera, T, marker, 256)
    x, y = uv[..., 0], uv[..., 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))


def plate_bbox(camera: Camera, T: np.ndarray, marker: Marker):
    """Pixel bounding box (x0, y0, x1, y1) of a planar target's plate seen by ``camera``,
    or None when none of it is in the image.

    Args:
        camera: the view.
        T: (4, 4) T_camera_target, mm.
        marker: anything with a ``plate`` (x0, y0, x1, y1) in its plane, mm (a
            :class:`Marker`, a calibration grid, a peer's target).

    Raises ``ValueError`` when the plate does not lie entirely in front of the camera.
    """
    x0, y0, x1, y1 = marker.plate
    s = np.linspace(0, 1, 33)
    border = np.concatenate(
        [
            np.stack([x0 + (x1 - x0) * s, np.full_like(s, y0)], 1),
            np.stack([x0 + (x1 - x0) * s, np.full_like(s, y1)], 1),
            np.stack([np.full_like(s, x0), y0 + (y1 - y0) * s], 1),
            np.stack([np.full_like(s, x1), y0 + (y1 - y0) * s], 1),
        ]
    )
    P = np.column_stack([border, np.zeros(len(border))]) @ T[:3, :3].T + T[:3, 3]
    if np.any(P[:, 2] <= 1.0):
        raise ValueError("the marker plate must lie entirely in front of the camera")
    uv = camera.project(P)
    w, h = camera.image_size
    bx0 = int(np.floor(uv[:, 0].min())) - 2
    by0 = int(np.floor(uv[:, 1].min())) - 2
    bx1 = int(np.ceil(uv[:, 0].max())) + 3
    by1 = int(np.ceil(uv[:, 1].max())) + 3
    bx0, by0, bx1, by1 = max(bx0, 0), max(by0, 0), min(bx1, w), min(by1, h)
    if bx0 >= bx1 or by0 >= by1:
        return None
    return bx0, by0, bx1, by1


def plane_coords(Hinv: np.ndarray, xn: np.ndarray, yn: np.ndarray):
    """Plane coordinates (mm) of the rays through normalised image points.

    Args:
        Hinv: (3, 3) inverse of the plane's homography ``[r1 r2 t]`` of T_camera_plane
            (normalised image → plane).
        xn, yn: normalised image coordinates, any one shape.
    Returns (mx, my), each of that shape (meaningless where the plane is behind the ray).
    """
    w = Hinv[2, 0] * xn + Hinv[2, 1] * yn + Hinv[2, 2]
    mx = (Hinv[0, 0] * xn + Hinv[0, 1] * yn + Hinv[0, 2]) / w
    my = (Hinv[1, 0] * xn + Hinv[1, 1] * yn + Hinv[1, 2]) / w
    return mx, my


def _texture(marker: Marker, mx, my, paper: float, ink: float, background):
    """Reflectance at plane points; off-plate points take the background value."""
    val = np.full(mx.shape, paper)
    ro2, ri2 = marker.outer_radius**2, marker.inner_radius**2
    for cx, cy in marker.centers2d:
        r2 = (mx - cx) ** 2 + (my - cy) ** 2
        val[(r2 <= ro2) & (r2 > ri2)] = ink
    x0, y0, x1, y1 = marker.plate
    off = (mx < x0) | (mx > x1) | (my < y0) | (my > y1)
    val[off] = np.broadcast_to(background, mx.shape)[off]
    return val


def _render_plate(camera: Camera, T: np.ndarray, marker: Marker, scene: np.ndarray, imaging: Imaging):
    """Paint the plate into ``scene`` (float, in place); return the ring-ID mask."""
    w, h = camera.image_size
    mask = np.zeros((h, w), np.uint8)
    bbox = plate_bbox(camera, T, marker)
    if bbox is None:
        return mask
    bx0, by0, bx1, by1 = bbox
    # One pixel of grid beyond the box on each side, for the central differences below.
    gx0, gy0, gx1, gy1 = max(bx0 - 1, 0), max(by0 - 1, 0), min(bx1 + 1, w), min(by1 + 1, h)
    grid = camera.normalized_grid()[gy0:gy1, gx0:gx1]
    J_u = np.gradient(grid, axis=1)  # d(normalised)/d(u), central differences
    J_v = np.gradient(grid, axis=0)
    Hinv = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    mx, my = plane_coords(Hinv, grid[..., 0], grid[..., 1])
    # Footprint of a pixel on the plane (mm): how far the texture can change within it.
    # Differences on the grown grid, so a box one pixel thin still has neighbours.
    dmx_u, dmy_u = np.gradient(mx, axis=1), np.gradient(my, axis=1)
    dmx_v, dmy_v = np.gradient(mx, axis=0), np.gradient(my, axis=0)
    sl = (slice(by0 - gy0, by1 - gy0), slice(bx0 - gx0, bx1 - gx0))
    grid, J_u, J_v, mx, my = grid[sl], J_u[sl], J_v[sl], mx[sl], my[sl]
    dmx_u, dmy_u, dmx_v, dmy_v = dmx_u[sl], dmy_u[sl], dmx_v[sl], dmy_v[sl]

    xn, yn = grid[..., 0], grid[..., 1]
    bg = scene[by0:by1, bx0:bx1]
    val = _texture(marker, mx, my, imaging.paper, imaging.ink, bg)

    foot = 0.75 * (np.hypot(dmx_u, dmy_u) + np.hypot(dmx_v, dmy_v)) + 1e-9
    near = np.zeros(mx.shape, bool)
    for cx, cy in marker.centers2d:
        r = np.hypot(mx - cx, my - cy)
        near |= np.abs(r - marker.outer_radius) < foot
        near |= np.abs(r - marker.inner_radius) < foot
    x0, y0, x1, y1 = marker.plate
    near |= (np.abs(mx - x0) < foot) | (np.abs(mx - x1) < foot) | (np.abs(my - y0) < foot) | (np.abs(my - y1) < foot)
    for i, (cx, cy) in enumerate(marker.centers2d):
        mask[by0:by1, bx0:bx1][np.hypot(mx - cx, my - cy) <= marker.outer_radius] = i + 1

    # Supersample the edge pixels: sub-pixel offsets mapped through the local Jacobian of
    # the inverse distortion (its second-order term is ~1e-5 px over half a pixel).
    iy, ix = np.nonzero(near)
    S = imaging.supersample
    if len(iy) and S > 1:
        off = (np.arange(S) + 0.5) / S - 0.5
        du, dv = np.meshgrid(off, off)
        du, dv = du.ravel()[None, :], dv.ravel()[None, :]
        chunk = max(1, 400_000 // (S * S))
        for k in range(0, len(iy), chunk):
            yy, xx = iy[k : k + chunk], ix[k : k + chunk]
            sx = xn[yy, xx][:, None] + J_u[yy, xx, 0][:, None] * du + J_v[yy, xx, 0][:, None] * dv
            sy = yn[yy, xx][:, None] + J_u[yy, xx, 1][:, None] * du + J_v[yy, xx, 1][:, None] * dv
            smx, smy = plane_coords(Hinv, sx, sy)
            v = _texture(marker, smx, smy, imaging.paper, imaging.ink, bg[yy, xx][:, None])
            val[yy, xx] = v.mean(axis=1)
    if imaging.plate_light is not None:
        on = (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)
        val[on] = val[on] * imaging.plate_light(mx[on], my[on])
    scene[by0:by1, bx0:bx1] = val
    return mask


def _scene(camera: Camera, background, rng: np.random.Generator) -> np.ndarray:
    """The float32 scene a view's plates are painted into: a copy of ``background``, or
    random clutter drawn from ``rng`` when it is None."""
    if camera.image_size is None:
        raise ValueError("camera.image_size is needed to render")
    w, h = camera.image_size
    if background is None:
        return clutter_background((w, h), rng)
    scene = np.asarray(background, dtype=np.float32)
    if scene.shape != (h, w):
        raise ValueError(f"background must be (H, W) = {(h, w)}, got {scene.shape}")
    return scene.copy()


# --- light, optics, sensor -----------------------------------------------------------
def _illumination(size, imaging: Imaging) -> np.ndarray:
    w, h = size
    u = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / (w / 2)
    v = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / (w / 2)
    a = np.deg2rad(imaging.gradient_angle)
    diag = np.hypot(1.0, h / w)
    field = 1.0 - imaging.gradient * (0.5 + (np.cos(a) * u[None, :] + np.sin(a) * v[:, None]) / (2 * diag))
    if imaging.vignetting:
        r2 = (u[None, :] ** 2 + v[:, None] ** 2) / diag**2
        field = field * (1.0 - imaging.vignetting * r2)
    return field.astype(np.float32)


def motion_kernel(length: float, angle_deg: float) -> np.ndarray:
    """Normalised linear motion-blur kernel: a line of ``length`` px at ``angle_deg``,
    anti-aliased, with its centroid exactly on the middle pixel (OpenCV's anchor), so
    blurring does not shift the image. (OpenCV's thick lines are not symmetric about
    their axis: uncorrected, the kernel's centroid can be a tenth of a pixel off, which
    would shift every blurred render against its truth.)"""
    n = int(np.ceil(length)) | 1
    n = max(n, 3)
    up = 8
    big = np.zeros((n * up, n * up), np.float32)
    c = (n * up - 1) / 2
    a = np.deg2rad(angle_deg)
    d = np.array([np.cos(a), np.sin(a)]) * (length * up - 1) / 2
    p0 = tuple(int(round(v * 16)) for v in (c - d[0], c - d[1]))
    p1 = tuple(int(round(v * 16)) for v in (c + d[0], c + d[1]))
    cv2.line(big, p0, p1, 1.0, thickness=up, lineType=cv2.LINE_AA, shift=4)
    k = cv2.resize(big, (n, n), interpolation=cv2.INTER_AREA).astype(np.float64)
    k = np.pad(k / k.sum(), 1)  # room for the shift below; still odd-sized and centred
    m = n + 2
    yy, xx = np.mgrid[:m, :m]
    off = np.array([(k * xx).sum(), (k * yy).sum()]) - (m - 1) / 2
    # Linear interpolation at positions shifted by s (|s| < 1) moves the centroid by -s.
    for axis, s in ((1, off[0]), (0, off[1])):
        nxt = np.roll(k, -1 if s >= 0 else 1, axis=axis)  # the padding keeps the roll clean
        k = (1 - abs(s)) * k + abs(s) * nxt
    return (k / k.sum()).astype(np.float32)


_POISSON_EXACT_BELOW = 25.0  # electrons


def expose(scene: np.ndarray, size, imaging: Imaging, rng: np.random.Generator) -> np.ndarray:
    """A scene's radiance (float32 (H, W), reflectance units) to the recorded image: the
    illumination field and vignetting, the exposure gain, the PSF and motion blur, the
    sensor (shot and read noise, quantisation) and what follows it (gamma, resampling,
    JPEG). ``size`` is (W, H). Returns what :func:`sensor_readout` returns, after that."""
    img = scene * _illumination(size, imaging)
    if imaging.psf_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), imaging.psf_sigma, borderType=cv2.BORDER_REFLECT)
    if imaging.motion_blur > 1:
        img = cv2.filter2D(img, -1, motion_kernel(imaging.motion_blur, imaging.motion_angle), borderType=cv2.BORDER_REFLECT)
    dn = img * np.float32(imaging.alpha * imaging.exposure * 255.0)
    return _recorded(sensor_readout(dn, imaging, rng), imaging)


def _recorded(image: np.ndarray, imaging: Imaging) -> np.ndarray:
    """What the camera's output goes through before a detector sees it: the response
    curve, a resampling, JPEG compression (8-bit images only)."""
    if image.dtype != np.uint8:
        return image
    if imaging.gamma != 1.0:
        lut = np.clip(np.rint(255.0 * (np.arange(256) / 255.0) ** imaging.gamma), 0, 255).astype(np.uint8)
        image = cv2.LUT(image, lut)
    if imaging.resample > 1.0:
        h, w = image.shape
        small = cv2.resize(image, (round(w / imaging.resample), round(h / imaging.resample)), interpolation=cv2.INTER_AREA)
        image = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if imaging.jpeg_quality:
        buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(imaging.jpeg_quality)])[1]
        image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return image


def sensor_readout(dn: np.ndarray, imaging: Imaging, rng: np.random.Generator) -> np.ndarray:
    """The sensor's output for an expected signal.

    Args:
        dn: (H, W) float expected signal in 8-bit units (255 = full well).
        imaging: ``full_well``, ``read_noise``, ``noise`` and ``quantize`` are used.
        rng: random generator for the noise.
    Returns:
        uint8 (H, W), or float32 DN when ``imaging.quantize`` is False.
    """
    electrons = np.maximum(np.asarray(dn, np.float32), 0) * np.float32(imaging.full_well / 255.0)
    if imaging.noise:
        # Shot noise: exact Poisson draws where few electrons arrive; above
        # _POISSON_EXACT_BELOW the normal approximation N(λ, λ) is used (its error in
        # the variance is nil and its skew is < 0.2), which is much faster on a full frame.
        low = electrons < _POISSON_EXACT_BELOW
        shot = np.sqrt(electrons) * rng.standard_normal(electrons.shape, dtype=np.float32)
        if low.any():
            lam = electrons[low]
            shot[low] = rng.poisson(lam).astype(np.float32) - lam
        electrons = electrons + shot + np.float32(imaging.read_noise) * rng.standard_normal(electrons.shape, dtype=np.float32)
    out = electrons * np.float32(255.0 / imaging.full_well)
    if not imaging.quantize:
        return out.astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# --- public API ------------------------------------------------------------------------
def render_view(
    camera: Camera,
    T_cam_marker: np.ndarray,
    marker: Marker | None = None,
    imaging: Imaging | None = None,
    background: np.ndarray | None = None,
    seed: int | np.random.Generator | None = 0,
) -> tuple[np.ndarray, ViewTruth]:
    """Render one view of the marker.

    Args:
        camera: camera with ``image_size``.
        T_cam_marker: (4, 4) marker → camera, mm.
        marker: marker geometry (default ``Marker()``).
        imaging: light/optics/sensor settings (default ``Imaging()``).
        background: (H, W) float reflectance in [0, 1]; None → random clutter from the seed.
        seed: int or Generator; the same seed gives the same image.
    Returns:
        (image, truth): uint8 (H, W) image (float32 if ``imaging.quantize`` is False) and
        its :class:`ViewTruth`.
    """
    marker = marker or Marker()
    imaging = imaging or Imaging()
    if camera.image_size is None:
        raise ValueError("camera.image_size is needed to render")
    T = np.asarray(T_cam_marker, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_cam_marker must be (4, 4), got {T.shape}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    scene = _scene(camera, background, rng)
    mask = _render_plate(camera, T, marker, scene, imaging)
    image = expose(scene, camera.image_size, imaging, rng)
    return image, _view_truth(camera, T, marker, mask)


def render_stereo(
    rig: StereoRig,
    T_left_marker: np.ndarray,
    marker: Marker | None = None,
    imaging: Imaging | tuple[Imaging, Imaging] | None = None,
    background: np.ndarray | tuple | None = None,
    seed: int | np.random.Generator | None = 0,
) -> StereoFrame:
    """Render both views of the rig.

    Args:
        rig: the stereo rig (both cameras need ``image_size``).
        T_left_marker: (4, 4) marker → left camera, mm.
        marker: marker geometry.
        imaging: one :class:`Imaging` for both views, or a pair.
        background: one (H, W) background for both, a pair, or None (random clutter per view).
        seed: int or Generator.
    Returns:
        :class:`StereoFrame` with ``images[i]`` and ``views[i]`` for left (0) and right (1).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    imgs = imaging if isinstance(imaging, tuple) else (imaging or Imaging(),) * 2
    bgs = background if isinstance(background, (tuple, list)) else (background, background)
    T_left = np.asarray(T_left_marker, dtype=np.float64)
    Ts = (T_left, rig.T_right_left @ T_left)
    images, views = [], []
    for cam, T, im, bg in zip(rig.cameras, Ts, imgs, bgs):
        image, truth = render_view(cam, T, marker, im, bg, rng)
        images.append(image)
        views.append(truth)
    return StereoFrame(images, views, T_left, tuple(imgs))


def render_tools(
    rig: StereoRig,
    poses,
    imaging: Imaging | tuple[Imaging, Imaging] | None = None,
    background: np.ndarray | tuple | None = None,
    seed: int | np.random.Generator | None = 0,
) -> ToolsFrame:
    """Render both views of the rig with several tools in the scene.

    In each view the plates are painted farthest first, by the depth of the plate's
    centre in that camera, so a nearer plate hides what lies behind it (painter's order;
    plates that cut through each other are not resolved pixel by pixel). Each view is
    exposed once, as :func:`render_stereo` exposes it: a single tool renders exactly as
    :func:`render_stereo` renders it with the same seed.

    Args:
        rig: the stereo rig (both cameras need ``image_size``).
        poses: (marker, T_left_marker) pairs, one per tool, with distinct ``marker.name``.
        imaging: one :class:`Imaging` for both views, or a pair.
        background: one (H, W) background for both, a pair, or None (random clutter per view).
        seed: int or Generator.
    Returns:
        :class:`ToolsFrame` with ``images[i]`` for left (0) and right (1), and each tool's
        :class:`ToolTruth` under its name, in the order of ``poses``.
    Raises:
        ValueError: two tools share a name, a pose is not (4, 4), or a plate does not lie
            entirely in front of a camera (the tool named).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    imgs = imaging if isinstance(imaging, tuple) else (imaging or Imaging(),) * 2
    bgs = background if isinstance(background, (tuple, list)) else (background, background)
    markers, Ts = [], []
    for marker, T_left_marker in poses:
        if marker.name in (m.name for m in markers):
            raise ValueError(f"two tools named {marker.name!r}; each tool needs its own name")
        T_left = np.asarray(T_left_marker, dtype=np.float64)
        if T_left.shape != (4, 4):
            raise ValueError(f"{marker.name}: T_left_marker must be (4, 4), got {T_left.shape}")
        markers.append(marker)
        Ts.append((T_left, rig.T_right_left @ T_left))
    n = len(markers)
    images = []
    views = [[None, None] for _ in range(n)]
    visible = np.zeros((n, 2, 3))
    for v, (cam, im, bg) in enumerate(zip(rig.cameras, imgs, bgs)):
        scene = _scene(cam, bg, rng)
        depth = []
        for m, T in zip(markers, Ts):
            x0, y0, x1, y1 = m.plate
            depth.append((T[v] @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0, 1.0]))[2])
        order = np.argsort(-np.asarray(depth), kind="stable")  # farthest first; ties in the order given
        masks = {}
        for k in order:
            try:
                masks[k] = _render_plate(cam, Ts[k][v], markers[k], scene, im)
            except ValueError as e:
                raise ValueError(f"{markers[k].name}: {e}") from None
        images.append(expose(scene, cam.image_size, im, rng))
        # Nearest first, so that `cover` holds the pixels of the plates in front of tool k.
        w, h = cam.image_size
        cover = np.zeros((h, w), bool)
        for k in order[::-1]:
            T, mask = Ts[k][v], masks[k]
            truth = _view_truth(cam, T, markers[k], np.where(cover, 0, mask).astype(np.uint8))
            areas = _disk_areas(cam, T, markers[k])
            for i in range(3):
                ring = mask == i + 1
                seen = np.count_nonzero(ring & ~cover)
                # A ring wholly in the image is all in the mask: its own pixel count is exact.
                total = np.count_nonzero(ring) if truth.in_image[i] else areas[i]
                visible[k, v, i] = min(1.0, seen / total) if total > 0 else 0.0
            views[k][v] = truth
            cover |= _plate_pixels(cam, T, markers[k])
    truths = {m.name: ToolTruth(m, Ts[k][0], views[k], visible[k].copy()) for k, m in enumerate(markers)}
    return ToolsFrame(images, truths, tuple(imgs))


def look_at_pose(position: np.ndarray, tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """T_cam_marker of a marker at ``position`` (c0, mm) facing the camera.

    The marker starts fronto-parallel (its z toward the camera, +x right, +y up in the
    image), is rolled by ``roll_deg`` about its normal, then tilted by ``tilt_deg`` about an
    in-plane axis at ``tilt_axis_deg``.
    """
    from ..geometry import rotation_about_axis

    R0 = np.diag([1.0, -1.0, -1.0])  # marker z toward the camera, y up in the image
    Rroll = rotation_about_axis([0, 0, 1], np.deg2rad(roll_deg))
    a = np.deg2rad(tilt_axis_deg)
    Rtilt = rotation_about_axis([np.cos(a), np.sin(a), 0.0], np.deg2rad(tilt_deg))
    T = np.eye(4)
    T[:3, :3] = R0 @ Rtilt @ Rroll
    T[:3, 3] = position
    return T


__all__ = [
    "Imaging",
    "ViewTruth",
    "StereoFrame",
    "ToolTruth",
    "ToolsFrame",
    "render_view",
    "render_stereo",
    "render_tools",
    "motion_kernel",
    "look_at_pose",
    "sensor_readout",
    "expose",
    "plane_coords",
    "plate_bbox",
]
