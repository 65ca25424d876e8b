"""Augmentations of training images, with their points moved along.

The paper's (flips, random affine, contrast, motion blur, Gaussian blur, Gaussian noise)
and what real photographs add: JPEG and palette compression, down- and re-up-sampling,
vignetting, glare, gamma. Flips keep each ring's label: the IDs are defined by the
layout (c0 the right-angle corner, c1 the nearer, c2 the farther neighbour), which a
mirror does not change.

All functions take an explicit ``np.random.Generator``.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..synth.render import motion_kernel

default_conf = {
    "p_hflip": 0.5,
    "p_vflip": 0.2,
    "p_affine": 0.6,
    "rotate": 20.0,  # degrees
    "scale": (0.8, 1.25),
    "shear": 8.0,  # degrees
    "translate": 0.1,  # fraction of the image size
    "p_gamma": 0.5,
    "p_contrast": 0.5,
    "p_gauss_blur": 0.2,
    "p_motion_blur": 0.15,
    "p_noise": 0.3,
    "p_jpeg": 0.35,
    "p_palette": 0.1,
    "p_resample": 0.25,
    "p_vignetting": 0.2,
    "p_glare": 0.15,
}


def geometric(image: np.ndarray, points: np.ndarray, labels: np.ndarray, rng, conf: dict | None = None):
    """Flips and a random affine map; points leaving the image become absent.

    Args:
        image: (H, W) uint8.
        points: (3, 2) pixel coordinates (NaN allowed where absent).
        labels: (3,) int8 (1 target, 0 absent, -1 ignored).
    Returns:
        (image, points, labels), new arrays.
    """
    c = {**default_conf, **(conf or {})}
    h, w = image.shape
    A = np.eye(3)
    if rng.uniform() < c["p_hflip"]:
        A = np.array([[-1, 0, w - 1], [0, 1, 0], [0, 0, 1.0]]) @ A
    if rng.uniform() < c["p_vflip"]:
        A = np.array([[1, 0, 0], [0, -1, h - 1], [0, 0, 1.0]]) @ A
    if rng.uniform() < c["p_affine"]:
        ang = np.deg2rad(rng.uniform(-c["rotate"], c["rotate"]))
        s = np.exp(rng.uniform(*np.log(c["scale"])))
        sh = np.tan(np.deg2rad(rng.uniform(-c["shear"], c["shear"])))
        aniso = np.exp(rng.uniform(-0.1, 0.1))
        M = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]]) @ np.array([[s * aniso, sh * s], [0, s / aniso]])
        ctr = np.array([(w - 1) / 2, (h - 1) / 2])
        shift = rng.uniform(-c["translate"], c["translate"], 2) * [w, h]
        B = np.eye(3)
        B[:2, :2] = M
        B[:2, 2] = ctr + shift - M @ ctr
        A = B @ A
    if np.allclose(A, np.eye(3)):
        return image.copy(), points.copy(), labels.copy()
    fill = int(rng.integers(0, 256))
    out = cv2.warpAffine(image, A[:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
    p = np.asarray(points, np.float64) @ A[:2, :2].T + A[:2, 2]
    lab = labels.copy()
    outside = ~((p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1))
    lab[outside & (lab != 0)] = 0
    # A ring whose centre lands within a few px of the border is half cut: ambiguous.
    edge = (np.minimum(np.minimum(p[:, 0], w - 1 - p[:, 0]), np.minimum(p[:, 1], h - 1 - p[:, 1])) < 3) & (lab == 1)
    lab[edge] = -1
    return out, p.astype(np.float32), lab


def photometric(image: np.ndarray, rng, conf: dict | None = None) -> np.ndarray:
    """Contrast, gamma, blur, noise, vignetting, glare, resampling and compression."""
    c = {**default_conf, **(conf or {})}
    h, w = image.shape
    img = image.astype(np.float32)
    if rng.uniform() < c["p_vignetting"]:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        img *= 1 - rng.uniform(0.2, 0.6) * r2
    if rng.uniform() < c["p_glare"]:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        cx, cy, s = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.05, 0.3) * w
        img += rng.uniform(60, 300) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    if rng.uniform() < c["p_contrast"]:
        mean = img.mean()
        img = (img - mean) * rng.uniform(0.5, 1.5) + mean + rng.uniform(-30, 30)
    if rng.uniform() < c["p_gamma"]:
        img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** np.exp(rng.uniform(-0.5, 0.5))
    if rng.uniform() < c["p_gauss_blur"]:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 1.3))
    if rng.uniform() < c["p_motion_blur"]:
        img = cv2.filter2D(img, -1, motion_kernel(rng.uniform(2, 7), rng.uniform(0, 180)), borderType=cv2.BORDER_REFLECT)
    if rng.uniform() < c["p_resample"]:
        f = rng.uniform(0.35, 0.8)
        small = cv2.resize(img, (max(8, int(w * f)), max(8, int(h * f))), interpolation=cv2.INTER_AREA)
        interp = (cv2.INTER_LINEAR, cv2.INTER_CUBIC, cv2.INTER_NEAREST)[int(rng.integers(3))]
        img = cv2.resize(small, (w, h), interpolation=interp)
    if rng.uniform() < c["p_noise"]:
        img = img + rng.normal(0, rng.uniform(1, 10), img.shape).astype(np.float32)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if rng.uniform() < c["p_palette"]:
        levels = int(rng.integers(6, 33))
        step = 256 / levels
        out = (np.floor(out / step) * step + step / 2).clip(0, 255).astype(np.uint8)
    if rng.uniform() < c["p_jpeg"]:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(15, 91))])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


def augment(image, points, labels, rng, conf: dict | None = None):
    """Geometric then photometric augmentation: (image, points, labels)."""
    image, points, labels = geometric(image, points, labels, rng, conf)
    return photometric(image, rng, conf), points, labels


__all__ = ["augment", "default_conf", "geometric", "photometric"]
