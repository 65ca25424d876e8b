"""Random training and test scenes for stage 1, rendered at the network's 320x240 input.

A 320x240 network input is a full-resolution frame shrunk by ~4 in each direction. We
render it directly: a full-resolution camera is drawn at random (size, focal length,
distortion) and scaled to 320x240 (an anisotropic scale when the aspect ratio differs,
as the resize does), and each 320x240 pixel collects the light of the ~16 full-resolution
pixels it stands for (full well x b, read noise x sqrt(b)). Blur lengths are drawn in
full-resolution pixels and scaled the same way. This is ~16x cheaper than rendering the
full frame and shrinking it, and the ring edges stay exact (the renderer supersamples).

Everything the shipped model will meet on real photographs is drawn here: the whole
working volume (apparent ring sizes of a 50-150 px ring at full resolution, and beyond),
tilt to 65°, any in-plane rotation, the marker partly outside the image, darkness down
to a gain of 0.02, motion blur to 30 px, uneven light, clutter with ring-like decoys,
skin-like and cable-like occluders over the marker, and images without a marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from ..keypoints import INPUT_SIZE
from ..marker import Marker
from ..synth import Imaging, clutter_background, look_at_pose, render_view, sensor_readout
from .data import draw as draw_value

FULL_SIZES = ((1280, 1024), (1280, 1024), (1280, 1024), (1280, 960), (1920, 1080), (1600, 1200), (2048, 1536), (640, 480))


@dataclass
class Sample:
    """One stage-1 training image.

    Attributes:
        image: (240, 320) uint8.
        points: (3, 2) float32 centres c0, c1, c2 in image pixels (NaN where not in view).
        labels: (3,) int8: 1 = visible target, 0 = absent, -1 = ambiguous (ignored).
        alpha, blur: the darkness gain and motion-blur length (full-resolution px) used.
        ring_px: apparent outer-ring diameter at full resolution, px (0 for negatives).
        scale: (2,) full-resolution px per image px in x and y (errors are reported at full
            resolution).
    """

    image: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    alpha: float = 1.0
    blur: float = 0.0
    ring_px: float = 0.0
    scale: np.ndarray | None = None


def scaled_camera(full_size, f: float, dist, size=INPUT_SIZE) -> tuple[Camera, float]:
    """A full-resolution camera seen at ``size``: (camera, pixels binned per output pixel)."""
    W0, H0 = full_size
    w, h = size
    sx, sy = w / W0, h / H0
    cx0, cy0 = (W0 - 1) / 2, (H0 - 1) / 2
    K = np.array([[f * sx, 0, sx * (cx0 + 0.5) - 0.5], [0, f * sy, sy * (cy0 + 0.5) - 0.5], [0, 0, 1.0]])
    return Camera(K, np.asarray(dist, np.float64), (w, h)), 1.0 / (sx * sy)


def random_imaging(
    rng, alpha: float, blur: float, px_scale: float = 1.0, binning: float = 1.0, psf=(0.3, 2.5), vignetting: float = 0.5
) -> Imaging:
    """Random light, optics, print and sensor (noise-free expectation; add noise with
    :func:`~markerpose.synth.sensor_readout` using its ``full_well`` and ``read_noise``).

    Args:
        alpha, blur: the darkness gain and the motion-blur length (full-resolution px).
        px_scale: output px per full-resolution px (blur and PSF shrink with it).
        binning: full-resolution pixels per output pixel (full well and read noise grow).
        psf: range of the Gaussian PSF sigma, full-resolution px.
        vignetting: largest vignetting.
    """
    paper = rng.uniform(0.55, 0.95)
    return Imaging(
        alpha=alpha,
        exposure=rng.uniform(0.5, 1.0),
        gradient=rng.uniform(0, 0.7),
        gradient_angle=rng.uniform(0, 360),
        vignetting=rng.uniform(0, vignetting),
        psf_sigma=rng.uniform(*psf) * px_scale,
        motion_blur=blur * px_scale,
        motion_angle=rng.uniform(0, 180),
        full_well=10_000.0 * binning,
        read_noise=rng.uniform(5, 20) * np.sqrt(binning),
        noise=False,
        quantize=False,
        supersample=8,
        paper=paper,
        ink=rng.uniform(0.02, 0.25) * paper / 0.85,  # printing contrast varies
    )


def loguniform(rng, lo, hi):
    """A draw between ``lo`` and ``hi`` (both > 0), uniform in the logarithm: each factor
    of two as likely as any other."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _draw_decoys(bg: np.ndarray, rng, ring_px: float, ratio: float):
    """Rings with the marker's inner/outer ratio in layouts that are not the marker's."""
    h, w = bg.shape
    for _ in range(int(rng.integers(1, 4))):
        n = int(rng.integers(1, 4))
        c = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        step = ring_px * rng.uniform(1.1, 2.5)
        a0 = rng.uniform(0, 2 * np.pi)
        for k in range(n):  # collinear or equilateral groups, one or two rings
            ang = a0 + (k * np.pi / 3 if rng.uniform() < 0.5 else 0)
            p = c + k * step * np.array([np.cos(ang), np.sin(ang)])
            r = ring_px / 2 * rng.uniform(0.7, 1.3)
            ax = (2 * r, 2 * r * rng.uniform(0.5, 1.0))
            ang_e = rng.uniform(0, 180)
            cv2.ellipse(bg, (tuple(p), ax, ang_e), float(rng.uniform(0, 0.12)), -1, cv2.LINE_AA)
            cv2.ellipse(bg, (tuple(p), (ax[0] * ratio, ax[1] * ratio), ang_e), float(rng.uniform(0.6, 0.95)), -1, cv2.LINE_AA)


def occluders(shape, rng, near: np.ndarray | None, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Skin-like blobs (fingers, a hand's edge) and cables: (coverage (H, W) in [0, 1], reflectance).

    ``shape`` is (H, W); most blobs start near ``near`` ((2,) px, or None: anywhere), and
    ``scale`` (px, about a ring's size) sets their size."""
    h, w = shape
    cover = np.zeros((h, w), np.float32)
    refl = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 3))):
        layer = np.zeros((h, w), np.float32)
        if near is not None and rng.uniform() < 0.8:
            c = near + rng.normal(0, 1.0, 2) * scale
        else:
            c = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        if rng.uniform() < 0.55:  # finger-like: a thick capsule coming from outside
            ang = rng.uniform(0, 2 * np.pi)
            L = rng.uniform(2, 6) * scale
            p0 = c + L * np.array([np.cos(ang), np.sin(ang)])
            cv2.line(
                layer, tuple(int(v) for v in c), tuple(int(v) for v in p0), 1.0, max(2, int(rng.uniform(0.4, 1.1) * scale)), cv2.LINE_AA
            )
            value = rng.uniform(0.3, 0.75)  # skin
        else:  # cable: a smooth curve
            t = np.linspace(0, 1, 30)[:, None]
            pts = [c + rng.normal(0, 2.5, 2) * scale for _ in range(3)]
            curve = (1 - t) ** 2 * pts[0] + 2 * t * (1 - t) * pts[1] + t**2 * pts[2]
            cv2.polylines(layer, [np.round(curve * 4).astype(np.int32)], False, 1.0, int(rng.integers(1, 5)), cv2.LINE_AA, shift=2)
            value = rng.uniform(0.0, 0.9)
        shade = value * (1 + 0.15 * cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 3))
        refl = refl * (1 - layer) + shade * layer
        cover = np.maximum(cover, layer)
    return cover, refl


def sample(rng: np.random.Generator, marker: Marker | None = None, negative: bool | None = None, conf: dict | None = None) -> Sample:
    """One random stage-1 image with its labels.

    Args:
        rng: the only source of randomness.
        marker: the marker (default geometry).
        negative: force an image without the marker (None: 8% of draws).
        conf: fixes some draws to a value or a (lo, hi) range: ``alpha``, ``blur`` (full-res
            px), ``tilt`` (deg), ``ring_px``; ``inside`` (bool: marker kept off the border),
            ``p_occlude``. Used by the held-out test sets.
    """
    conf = conf or {}
    marker = marker or Marker()

    def draw(key, default):
        return draw_value(rng, conf, key, default)

    full = FULL_SIZES[int(rng.integers(len(FULL_SIZES)))]
    f = rng.uniform(0.75, 1.5) * 2500 * full[0] / 1280  # 12 mm-ish lens on that sensor, varied
    dist = [rng.uniform(-0.25, 0.05), rng.uniform(-0.05, 0.15), 0, 0, 0]
    cam, binning = scaled_camera(full, f, dist)
    w, h = INPUT_SIZE
    s_full = w / full[0]  # output px per full-resolution px (x)

    if negative is None:
        negative = rng.uniform() < 0.08
    # Apparent outer diameter at full resolution: 50-150 px over the working volume, plus
    # margins either side for other lenses and distances.
    ring_px = draw("ring_px", lambda: loguniform(rng, 40, 190))
    z = f * 2 * marker.outer_radius / ring_px
    tilt = draw("tilt", lambda: rng.uniform(0, 60) if rng.uniform() < 0.9 else rng.uniform(60, 65))
    T = look_at_pose([0, 0, z], tilt, rng.uniform(0, 360), rng.uniform(0, 360))
    centroid = marker.points3d.mean(0)
    inside = conf.get("inside", rng.uniform() < 0.85)
    m = 0.12 if inside else -0.12  # fraction of the image kept free at the border (negative: may cross it)
    u, v = rng.uniform(m * w, (1 - m) * w), rng.uniform(m * h, (1 - m) * h)
    ray = np.linalg.solve(cam.K, [u, v, 1.0])
    T[:3, 3] = ray * z - T[:3, :3] @ centroid
    if negative:
        T[:3, 3] = [50 * z, 0, z]  # far outside the view: no marker in the image

    ring_low = ring_px * s_full
    bg = clutter_background((w, h), rng)
    if rng.uniform() < 0.5:
        _draw_decoys(bg, rng, ring_low, marker.inner_radius / marker.outer_radius)

    def default_alpha():
        r = rng.uniform()
        return rng.uniform(0.25, 1.0) if r < 0.45 else loguniform(rng, 0.035, 0.25) if r < 0.92 else loguniform(rng, 0.02, 0.035)

    alpha = draw("alpha", default_alpha)
    blur = draw("blur", lambda: 0.0 if rng.uniform() < 0.45 else rng.uniform(1, 30))
    imaging = random_imaging(rng, alpha, blur, s_full, binning)
    dn, truth = render_view(cam, T, marker, imaging, background=bg, seed=rng)

    points = truth.centers.astype(np.float32)
    labels = np.zeros(3, np.int8)
    if not negative:
        occ_cover = np.zeros((h, w), np.float32)
        if rng.uniform() < conf.get("p_occlude", 0.3):
            near = truth.centers[int(rng.integers(3))]
            occ_cover, occ_refl = occluders((h, w), rng, near, ring_low)
            level = float(imaging.alpha * imaging.exposure * 255.0)
            dn = dn * (1 - occ_cover) + occ_refl * level * occ_cover
        # A ring is a target when its centre is in the image and >= 65% of its disk is
        # visible; 30-65% is ambiguous (ignored), less is absent.
        for i in range(3):
            x, y = truth.centers[i]
            if not (0 <= x <= w - 1 and 0 <= y <= h - 1):
                continue
            Q = truth.outer_conics[i]
            area = _conic_area(Q)
            vis = float(((truth.mask == i + 1) * (1 - occ_cover)).sum()) / max(area, 1e-9)
            labels[i] = 1 if vis >= 0.65 else (-1 if vis >= 0.3 else 0)
    else:
        points[:] = np.nan
    image = sensor_readout(dn, Imaging(full_well=imaging.full_well, read_noise=imaging.read_noise), rng)
    scale = np.array([full[0] / w, full[1] / h], np.float32)
    return Sample(image, points, labels, float(alpha), float(blur), 0.0 if negative else float(ring_px), scale)


def _conic_area(C: np.ndarray) -> float:
    """Area of the ellipse x^T C x = 0 (3x3 conic, any scale)."""
    A = C[:2, :2]
    detA = np.linalg.det(A)
    if detA <= 0:
        return float("inf")
    return float(np.pi * abs(np.linalg.det(C)) / detA**1.5)


__all__ = ["FULL_SIZES", "Sample", "loguniform", "occluders", "random_imaging", "sample", "scaled_camera"]
