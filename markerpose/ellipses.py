"""Stage 2: EllipSegNet, patches around the stage-1 points, and sub-pixel ellipse centres.

A square window around each rough centre is cut from the full-resolution image and
resampled to 120x120 (:func:`extract_patch`); EllipSegNet segments the filled outer
ellipse of the ring nearest the patch centre; the centre of that mask
(:func:`mask_center`) is mapped back to the image exactly.

Patches:
- ``"fixed"`` (the paper): a 120x120 window at full resolution, no resampling. A ring
  larger than ~110 px does not fit.
- ``"adaptive"`` (ours): a window of ``patch_scale`` times the ring's apparent diameter
  (judged from the spacing of the three stage-1 points), resampled to 120x120, so rings
  of 40 to 200 px all fill the patch alike.

Centres from the mask:
- ``"ellipse"`` (the paper): ``cv2.fitEllipse`` on the contour of the thresholded mask;
- ``"moments"`` (the paper's alternative): the centroid of the thresholded mask;
- ``"subpixel"`` (ours): an ellipse fitted to the mask's 0.5 iso-line, located to a
  fraction of a pixel by interpolating the network's probabilities between pixels.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .geometry import ring_diameter
from .nets import load_network

PATCH = 120
ENC_WIDTHS = (16, 16, 32, 32, 64, 64, 64, 64)
DEC_WIDTHS = (64, 32, 32, 16, 16, 16)
PATCH_MODES = ("adaptive", "fixed")
FITS = ("subpixel", "ellipse", "moments")

default_conf = {
    "patch": "adaptive",  # "adaptive" (ours) or "fixed" (paper: 120x120 at full resolution)
    "fit": "subpixel",  # "subpixel" (ours), "ellipse" (paper) or "moments"
    "patch_scale": 1.8,  # adaptive: window side / apparent outer diameter
    "min_side": 48,  # adaptive window limits, full-resolution px
    "max_side": 480,
    "threshold": 0.5,  # mask probability threshold
    "min_area_frac": 0.005,  # a mask smaller than this fraction of the patch is "no ring"
}


def build_network():
    """EllipSegNet (torch ``nn.Module``) with the paper's widths.

    Input (B, 1, 120, 120) float in [0, 1]; output (B, 1, 120, 120) logits.
    """
    import torch
    from torch import nn

    def block(cin, cout):
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        )

    class EllipSegNet(nn.Module):
        def __init__(self):
            super().__init__()
            e = ENC_WIDTHS
            self.enc = nn.ModuleList(
                [nn.Sequential(block(1, e[0]), block(e[0], e[1]))]
                + [nn.Sequential(block(e[2 * k - 1], e[2 * k]), block(e[2 * k], e[2 * k + 1])) for k in (1, 2, 3)]
            )
            self.pool = nn.MaxPool2d(2, 2)
            d = DEC_WIDTHS
            skips = (e[5], e[3], e[1])  # 64, 32, 16 channels at 1/4, 1/2, 1
            ups = (e[7], d[1], d[3])  # channels coming up: 64, 32, 16
            self.dec = nn.ModuleList(
                [nn.Sequential(block(u + s, d[2 * k]), block(d[2 * k], d[2 * k + 1])) for k, (u, s) in enumerate(zip(ups, skips))]
            )
            self.head = nn.Conv2d(d[-1], 1, 1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            feats = []
            for k, stage in enumerate(self.enc):
                x = stage(x if k == 0 else self.pool(x))
                feats.append(x)
            x = feats[-1]
            for stage, skip in zip(self.dec, reversed(feats[:-1])):
                x = nn.functional.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
                x = stage(torch.cat([x, skip], 1))
            return self.head(x)

    return EllipSegNet()


# --- patches ---------------------------------------------------------------------------
def window_side(points: np.ndarray, marker, conf: dict | None = None) -> int:
    """Side (full-resolution px) of the patch window for rings near ``points`` (3, 2)."""
    c = {**default_conf, **(conf or {})}
    if c["patch"] == "fixed":
        return PATCH
    return int(np.clip(round(c["patch_scale"] * ring_diameter(points, marker)), c["min_side"], c["max_side"]))


def extract_patch(gray: np.ndarray, center, side: int, size: int = PATCH) -> tuple[np.ndarray, np.ndarray]:
    """A ``side`` x ``side`` window around ``center``, resampled to ``size`` x ``size``.

    The window is pixel-aligned (its corner is an integer), padded by edge replication
    where it crosses the image border, and resized with area averaging (down) or bilinear
    interpolation (up). The mapping is exact: ``patch = (full - origin + 0.5) * scale - 0.5``.

    Args:
        gray: (H, W) uint8 image.
        center: (2,) x, y at full resolution.
        side: window side, px.
    Returns:
        (patch (size, size) uint8, [origin_x, origin_y, scale]).
    """
    h, w = gray.shape
    x0 = int(np.floor(center[0] + 0.5)) - side // 2
    y0 = int(np.floor(center[1] + 0.5)) - side // 2
    pad = (max(0, -y0), max(0, y0 + side - h), max(0, -x0), max(0, x0 + side - w))
    crop = gray[max(y0, 0) : min(y0 + side, h), max(x0, 0) : min(x0 + side, w)]
    if any(pad):
        if crop.size == 0:
            crop = np.zeros((side, side), gray.dtype)
        else:
            crop = cv2.copyMakeBorder(crop, *pad, cv2.BORDER_REPLICATE)
    if side != size:
        crop = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
    return crop, np.array([x0, y0, size / side], np.float64)


def patch_to_image(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Patch pixels → full-resolution pixels for a patch ``frame`` = [x0, y0, scale]."""
    return (np.asarray(points, np.float64) + 0.5) / frame[2] - 0.5 + frame[:2]


def image_to_patch(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Full-resolution pixels → patch pixels."""
    return (np.asarray(points, np.float64) - frame[:2] + 0.5) * frame[2] - 0.5


# --- centre from the mask ------------------------------------------------------------------
def _central_component(binary: np.ndarray) -> np.ndarray | None:
    """The connected component of a binary mask nearest the patch centre (uint8 0/1)."""
    n, lab, stats, cent = cv2.connectedComponentsWithStats(binary.astype(np.uint8), connectivity=8)
    if n <= 1:
        return None
    h, w = binary.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    best, best_d = None, np.inf
    for k in range(1, n):
        ys, xs = np.nonzero(lab == k)
        d = np.min((xs - c[0]) ** 2 + (ys - c[1]) ** 2)  # nearest pixel of the component
        if d < best_d:
            best, best_d = k, d
    return (lab == best).astype(np.uint8)


def _iso_points(prob: np.ndarray, comp: np.ndarray, level: float) -> np.ndarray:
    """Sub-pixel points where ``prob`` crosses ``level`` on the border of a component."""
    # Dilate the component by one pixel so both sides of every crossing are included.
    region = cv2.dilate(comp, np.ones((3, 3), np.uint8)).astype(bool)
    pts = []
    for axis in (0, 1):
        a = prob[:-1, :] if axis == 0 else prob[:, :-1]
        b = prob[1:, :] if axis == 0 else prob[:, 1:]
        ra = region[:-1, :] if axis == 0 else region[:, :-1]
        rb = region[1:, :] if axis == 0 else region[:, 1:]
        cross = ((a - level) * (b - level) < 0) & ra & rb
        ys, xs = np.nonzero(cross)
        t = (level - a[ys, xs]) / (b[ys, xs] - a[ys, xs])
        if axis == 0:
            pts.append(np.column_stack([xs, ys + t]))
        else:
            pts.append(np.column_stack([xs + t, ys]))
    return np.concatenate(pts).astype(np.float32)


def mask_center(prob: np.ndarray, fit: str = "subpixel", threshold: float = 0.5, min_area_frac: float = 0.005):
    """Centre of the ellipse nearest the patch centre in a probability mask.

    Args:
        prob: (H, W) float probabilities (sigmoid of the logits).
        fit: "subpixel", "ellipse" or "moments" (see the module docstring).
    Returns:
        ((2,) centre in patch pixels, RotatedRect or None) or None when there is no
        usable ellipse (too small, or a contour too short to fit).
    """
    if fit not in FITS:
        raise ValueError(f"unknown fit {fit!r}; choose from {FITS}")
    comp = _central_component(prob > threshold)
    if comp is None or comp.sum() < min_area_frac * prob.size:
        return None
    if fit == "moments":
        m = cv2.moments(comp, binaryImage=True)
        return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]]), None
    if fit == "ellipse":
        contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        pts = max(contours, key=len).reshape(-1, 2).astype(np.float32)
    else:
        pts = _iso_points(prob.astype(np.float64), comp, threshold)
    if len(pts) < 6:
        return None
    rect = cv2.fitEllipse(pts)
    return np.array(rect[0], np.float64), rect


# --- the stage-2 model -------------------------------------------------------------------
def sigmoid(x: np.ndarray) -> np.ndarray:
    """The logistic function, float32, without overflow warnings for large negative x."""
    x = np.asarray(x, np.float32)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1 / (1 + e), e / (1 + e)).astype(np.float32)


class EllipseNet:
    """EllipSegNet with its weights: rough centres → sub-pixel centres.

    Args:
        weights: an ``.onnx`` file (ONNX Runtime) or a ``.pt`` checkpoint (PyTorch), or
            None for the shipped default (:func:`markerpose.nets.default_weights`).
        conf: overrides of :data:`default_conf`.
        device: torch device (``.pt`` weights only).
        threads: the runtime's threads (None: its default, every core).
        backend: what runs ``.onnx`` weights (:data:`markerpose.nets.BACKENDS`).
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        conf: dict | None = None,
        device: str = "cpu",
        threads: int | None = None,
        backend: str = "onnxruntime",
    ):
        self.conf = {**default_conf, **(conf or {})}
        for key, allowed in (("patch", PATCH_MODES), ("fit", FITS)):
            if self.conf[key] not in allowed:
                raise ValueError(f"unknown {key} {self.conf[key]!r}; choose from {allowed}")
        self.runner, self.meta, self.path = load_network(
            weights, "ellipses", lambda meta: build_network(), threads, device, backend=backend
        )

    def probabilities(self, patches: np.ndarray) -> np.ndarray:
        """(N, 120, 120) uint8 patches → (N, 120, 120) float32 mask probabilities."""
        (logits,) = self.runner(patches.astype(np.float32)[:, None] / 255.0)
        return sigmoid(logits[:, 0])

    def __call__(self, grays: list[np.ndarray], points: list[np.ndarray], marker, with_ellipses: bool = False) -> list[tuple]:
        """Sub-pixel centres for rough centres in several images, all patches in one batch.

        Args:
            grays: uint8 (H, W) images.
            points: per image, (3, 2) rough centres by ID.
            marker: the marker (judges the window size).
            with_ellipses: also return the fitted ellipses (``fit`` "subpixel" or
                "ellipse"), in full-resolution pixels.
        Returns:
            per image, (centers (3, 2), refined (3,) bool) [+ ellipses: per ring a
            RotatedRect or None]; where no ellipse is found the rough centre is kept and
            ``refined`` is False.
        """
        patches, frames = [], []
        for gray, pts in zip(grays, points):
            side = window_side(pts, marker, self.conf)
            for p in pts:
                patch, frame = extract_patch(gray, p, side)
                patches.append(patch)
                frames.append(frame)
        probs = self.probabilities(np.stack(patches)) if patches else []
        out, k = [], 0
        for pts in points:
            centers, ok, rects = np.array(pts, np.float64), np.zeros(len(pts), bool), [None] * len(pts)
            for i in range(len(pts)):
                found = mask_center(probs[k], self.conf["fit"], self.conf["threshold"], self.conf["min_area_frac"])
                if found is not None:
                    centers[i] = patch_to_image(found[0], frames[k])
                    ok[i] = True
                    if found[1] is not None:  # the patch is a scaled copy: axes / scale
                        (_, _), (w, h), ang = found[1]
                        rects[i] = (tuple(centers[i]), (w / frames[k][2], h / frames[k][2]), ang)
                k += 1
            out.append((centers, ok, rects) if with_ellipses else (centers, ok))
        return out


__all__ = [
    "EllipseNet",
    "FITS",
    "PATCH",
    "PATCH_MODES",
    "build_network",
    "default_conf",
    "extract_patch",
    "image_to_patch",
    "mask_center",
    "patch_to_image",
    "window_side",
]
