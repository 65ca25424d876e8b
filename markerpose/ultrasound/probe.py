"""The tracked probe: where its image plane sits relative to the marker.

Frames (millimetres):
- image: origin at the centre of pixel (0, 0), x along the columns (lateral), y along the
  rows (depth, away from the transducer face), z = x × y. Pixel (u, v) is the point
  (u * sx, v * sy, 0).
- marker: the marker frame of :class:`markerpose.Marker`, rigidly mounted on the probe.
- tracker: the left camera (``T_left_marker`` from :class:`markerpose.MarkerPose`).

A probe calibration is the rigid ``T_marker_image`` plus the pixel spacing. PLUS and 3D
Slicer name the marker frame "Probe" and fold the spacing into ``ImageToProbe``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..geometry import nearest_rotation


@dataclass
class ProbeCalibration:
    """Image → marker transform of a tracked ultrasound probe.

    Attributes:
        T_marker_image: (4, 4) rigid transform, image mm → marker mm.
        spacing: (sx, sy) pixel size, mm (lateral, depth).
        size: (width, height) of the ultrasound images, px (None if unknown).
        rms_mm: RMS point-reconstruction error of the calibration that produced it (None if
            not from a calibration).
    """

    T_marker_image: np.ndarray
    spacing: tuple[float, float]
    size: tuple[int, int] | None = None
    rms_mm: float | None = None

    def __post_init__(self):
        T = np.asarray(self.T_marker_image, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_marker_image must be a finite (4, 4) matrix, got shape {T.shape}")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
            raise ValueError("T_marker_image: the rotation part is not a rotation")
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError("T_marker_image: last row must be [0, 0, 0, 1]")
        self.T_marker_image = T
        sx, sy = (float(v) for v in self.spacing)
        if not (np.isfinite(sx) and np.isfinite(sy) and sx > 0 and sy > 0):
            raise ValueError(f"spacing must be two positive numbers (mm), got {self.spacing}")
        self.spacing = (sx, sy)
        if self.size is not None:
            w, h = (int(v) for v in self.size)
            if w <= 0 or h <= 0:
                raise ValueError(f"size must be positive (width, height), got {self.size}")
            self.size = (w, h)

    @property
    def image_to_probe(self) -> np.ndarray:
        """PLUS's ``ImageToProbe``: pixels → marker mm, the spacing folded in."""
        return self.T_marker_image @ np.diag([self.spacing[0], self.spacing[1], 1.0, 1.0])

    def pixels_to_marker(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates → (N, 3) points in the marker frame, mm."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        p = np.column_stack([uv[:, 0] * self.spacing[0], uv[:, 1] * self.spacing[1]])
        return p @ self.T_marker_image[:3, :2].T + self.T_marker_image[:3, 3]

    def save(self, path: str | Path) -> None:
        """Write an OpenCV FileStorage file (.yaml/.yml/.xml), like the rig files."""
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise ValueError(f"cannot write {path}")
        fs.write("T_marker_image", self.T_marker_image)
        fs.write("spacing", np.array(self.spacing, dtype=np.float64).reshape(1, 2))
        if self.size is not None:
            fs.write("image_size", np.array(self.size, dtype=np.float64).reshape(1, 2))
        if self.rms_mm is not None:
            fs.write("rms_mm", float(self.rms_mm))
        fs.release()

    @classmethod
    def load(cls, path: str | Path) -> ProbeCalibration:
        """Read a file written by :meth:`save` (keys ``T_marker_image``, ``spacing``, and
        optionally ``image_size``, ``rms_mm``)."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"{path}: no such file")
        from ..formats import open_storage, storage_array

        fs = open_storage(path)
        try:
            T = storage_array(fs, "T_marker_image", path)
            sp = storage_array(fs, "spacing", path)
            if T is None or sp is None:
                raise ValueError(f"{path}: needs the keys T_marker_image (4x4) and spacing (sx, sy)")
            size = storage_array(fs, "image_size", path)
            size = None if size is None else tuple(round(v) for v in size.ravel())
            node = fs.getNode("rms_mm")
            rms = float(node.real()) if node.isReal() or node.isInt() else None
        finally:
            fs.release()
        flat = T.ndim == 1 or 1 in T.shape  # sixteen numbers in a row, read row by row
        if T.size != 16 or not (T.shape == (4, 4) or flat) or sp.size != 2:
            raise ValueError(f"{path}: T_marker_image must be 4x4 (got {'x'.join(map(str, T.shape))}) and spacing two numbers")
        try:
            return cls(T.reshape(4, 4), tuple(sp.ravel()), size, rms)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 from a rotation (re-orthonormalised) and a translation."""
    T = np.eye(4)
    T[:3, :3] = nearest_rotation(np.asarray(R, dtype=np.float64))
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


__all__ = ["ProbeCalibration", "invert", "rigid"]
