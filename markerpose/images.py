"""The one gate every input image passes: type, dtype, channels and size checked at the door."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

MIN_SIDE = 16  # px: no marker fits in less
RESIDUAL_BINS = 4 * 255 + 1  # |4 I - (sum of the 4 neighbours)| of a uint8 image: 0 ... 1020 (the noise estimate's)


def as_gray(image, name: str = "image", allow_float: bool = False) -> np.ndarray:
    """Validate an input image and return it as gray (H, W).

    Accepts uint8 gray (H, W), (H, W, 1) or BGR (H, W, 3); with ``allow_float`` also
    float32 on the 0..255 scale (noise-free renders), returned as float32. Anything else
    raises ``ValueError`` naming ``name`` and what was wrong.
    """
    if image is None:
        raise ValueError(f"{name} is None")
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(image).__name__}")
    dtypes = (np.uint8, np.float32) if allow_float else (np.uint8,)
    if image.dtype not in dtypes:
        wanted = "uint8 (or float32 on the 0..255 scale)" if allow_float else "uint8"
        raise ValueError(f"{name} must be {wanted}, got dtype {image.dtype}")
    if image.size == 0:
        raise ValueError(f"{name} is empty (shape {image.shape})")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 3:
        if image.shape[2] != 3:
            raise ValueError(f"{name} must be gray (H, W) or BGR (H, W, 3), got {image.shape[2]} channels")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"{name} must be gray (H, W) or BGR (H, W, 3), got shape {image.shape}")
    if min(image.shape) < MIN_SIDE:
        raise ValueError(f"{name} is too small: {image.shape}, need at least {MIN_SIDE} x {MIN_SIDE}")
    if image.dtype == np.float32 and not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains non-finite values")
    return image


def check_size(image: np.ndarray, camera, name: str) -> None:
    """``ValueError`` unless ``image`` (H, W) has the size ``camera`` was calibrated for
    (when the rig file states it)."""
    if camera.image_size is not None and (image.shape[1], image.shape[0]) != tuple(camera.image_size):
        w, h = camera.image_size
        raise ValueError(f"{name} is {image.shape[1]}x{image.shape[0]} but the rig was calibrated for {w}x{h}")


def gray_pair(left, right, rig) -> list[np.ndarray]:
    """A stereo pair validated (:func:`as_gray`, the same size, the rig's :func:`check_size`)
    and returned as [left, right] gray images."""
    gl, gr = as_gray(left, "left image"), as_gray(right, "right image")
    if gl.shape != gr.shape:
        raise ValueError(f"left and right images differ in size: {gl.shape[::-1]} vs {gr.shape[::-1]}")
    check_size(gl, rig.left, "left image")
    check_size(gr, rig.right, "right image")
    return [gl, gr]


def read_image(path) -> np.ndarray:
    """An image file as OpenCV decodes it (gray, BGR, ...), or a ValueError naming the file
    and what is wrong (missing, empty, not an image), never OpenCV's own error."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cannot read image {path}: no such file")
    data = np.fromfile(path, np.uint8)
    if data.size == 0:
        raise ValueError(f"cannot read image {path}: the file is empty")
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise ValueError(f"cannot read image {path}: not an image format OpenCV can decode")
    return img


__all__ = ["read_image", "MIN_SIDE", "as_gray", "check_size", "gray_pair"]
