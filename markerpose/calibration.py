"""Stereo calibration with an asymmetric circle grid (as the paper calibrated its rig).

- :class:`CircleGrid`: the printed grid in OpenCV's layout (``cols`` circles per row,
  ``rows`` rows, row i shifted by half a period when odd; ``spacing`` is OpenCV's square
  size: circles of one row are 2 spacings apart, rows 1 spacing apart).
- :func:`calibrate`: ``cv2.findCirclesGrid`` in both views, pairs where either view
  fails are rejected, ``cv2.calibrateCamera`` per view, then ``cv2.stereoCalibrate`` with
  those intrinsics; the rig in our conventions (``X_right = R X_left + t``, mm).
- :func:`plot_coverage`: where the grid was seen in each image.

The grid's ``reflectance`` and ``plate`` let the renderer draw it
(:func:`markerpose.synth.render_target_view`); the procedure checked on rendered images
of a known rig is :mod:`markerpose.experiments.calibration_check`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .camera import Camera, StereoRig
from .images import as_gray


@dataclass(frozen=True)
class CircleGrid:
    """An asymmetric grid of black circles on white, in OpenCV's layout.

    Attributes:
        cols, rows: circles per row and rows (OpenCV's pattern size (cols, rows)).
        spacing: OpenCV's square size, mm.
        diameter: circle diameter, mm (default: half a spacing).
        margin: white border around the outermost circles, mm (default: one spacing).
    """

    cols: int = 4
    rows: int = 11
    spacing: float = 20.0
    diameter: float | None = None
    margin: float | None = None

    def __post_init__(self):
        if self.cols < 2 or self.rows < 3:
            raise ValueError(f"a circle grid needs at least 2 x 3 circles, got {self.cols}x{self.rows}")
        if not self.spacing > 0:
            raise ValueError(f"spacing must be > 0 mm, got {self.spacing}")
        if not 0 < self.radius * 2 < self.spacing * np.sqrt(2):
            raise ValueError(f"circles of {2 * self.radius} mm overlap at a spacing of {self.spacing} mm")

    @property
    def radius(self) -> float:
        return 0.5 * (0.5 * self.spacing if self.diameter is None else self.diameter)

    @property
    def points3d(self) -> np.ndarray:
        """(rows * cols, 3) circle centres in the grid's frame, mm, in OpenCV's order."""
        i, j = np.divmod(np.arange(self.rows * self.cols), self.cols)
        return np.column_stack([(2 * j + i % 2) * self.spacing, i * self.spacing, np.zeros(len(i))]).astype(np.float64)

    @property
    def plate(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the printed sheet, mm."""
        m = self.spacing if self.margin is None else self.margin
        p = self.points3d
        return (
            float(p[:, 0].min() - self.radius - m),
            float(p[:, 1].min() - self.radius - m),
            float(p[:, 0].max() + self.radius + m),
            float(p[:, 1].max() + self.radius + m),
        )

    def reflectance(self, xy: np.ndarray, black: float = 0.04, white: float = 0.85) -> np.ndarray:
        """Reflectance at plane points (..., 2), mm; NaN off the sheet."""
        x, y = xy[..., 0] / self.spacing, xy[..., 1] / self.spacing
        ink = np.zeros(x.shape, bool)
        r2 = (self.radius / self.spacing) ** 2
        for di in (-1, 0, 1):  # the nearest row and its neighbours
            i = np.clip(np.round(y) + di, 0, self.rows - 1)
            j = np.clip(np.round((x - i % 2) / 2), 0, self.cols - 1)
            ink |= (x - (2 * j + i % 2)) ** 2 + (y - i) ** 2 <= r2
        x0, y0, x1, y1 = self.plate
        out = np.where(ink, black, white)
        off = (xy[..., 0] < x0) | (xy[..., 0] > x1) | (xy[..., 1] < y0) | (xy[..., 1] > y1)
        return np.where(off, np.nan, out)


@dataclass
class Calibration:
    """What :func:`calibrate` found: the rig, its errors and the views it used."""

    rig: StereoRig
    rms_left_px: float
    rms_right_px: float
    rms_stereo_px: float
    pairs_used: list
    pairs_rejected: list
    points: tuple = field(repr=False, default=())  # per view, (M, 2) every detected centre
    why_rejected: dict = field(default_factory=dict)  # pair name -> why it was not used

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.rig.t))

    def summary(self) -> dict:
        return {
            "rms_left_px": self.rms_left_px,
            "rms_right_px": self.rms_right_px,
            "rms_stereo_px": self.rms_stereo_px,
            "baseline_mm": self.baseline_mm,
            "pairs_used": len(self.pairs_used),
            "pairs_rejected": self.pairs_rejected,
            "why_rejected": {str(k): v for k, v in self.why_rejected.items()},
            "f_left_px": [float(self.rig.left.K[0, 0]), float(self.rig.left.K[1, 1])],
            "f_right_px": [float(self.rig.right.K[0, 0]), float(self.rig.right.K[1, 1])],
            "volume_mm": None if self.rig.volume is None else self.rig.volume.tolist(),
        }


def find_grid(image: np.ndarray, grid: CircleGrid) -> np.ndarray | None:
    """(rows * cols, 2) circle centres in OpenCV's order, or None when the grid is not found."""
    gray = as_gray(image)
    ok, centers = cv2.findCirclesGrid(gray, (grid.cols, grid.rows), flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
    return centers.reshape(-1, 2).astype(np.float64) if ok else None


def _consistent(left: np.ndarray, right: np.ndarray, grid: CircleGrid) -> np.ndarray:
    """The right view's centres in the order that matches the left's. The grid looks the
    same from its two ends (with an odd number of rows, reversed row by row), so
    ``cv2.findCirclesGrid`` may start it at either end in each view; the order whose row
    and column directions agree best with the left view's is the same physical one."""

    def axes(p):
        q = p.reshape(grid.rows, grid.cols, 2)
        return np.concatenate([(q[:, -1] - q[:, 0]).mean(0), (q[-1] - q[0]).mean(0)])

    a = axes(left)
    q = right.reshape(grid.rows, grid.cols, 2)
    options = [q, q[::-1], q[::-1, ::-1], q[:, ::-1]]
    return max(options, key=lambda o: float(axes(o.reshape(-1, 2)) @ a)).reshape(-1, 2)


def _grid_volume(obj: np.ndarray, rvecs, tvecs) -> np.ndarray:
    """(2, 3) the box (left-camera frame, mm) the grid's points filled over the pairs used."""
    pts = np.concatenate([obj.astype(np.float64) @ cv2.Rodrigues(rv)[0].T + np.ravel(tv) for rv, tv in zip(rvecs, tvecs)])
    return np.stack([pts.min(0), pts.max(0)])


def calibrate(pairs, grid: CircleGrid, names=None, min_pairs: int = 6) -> Calibration:
    """Calibrate a stereo rig from image pairs of ``grid``.

    Args:
        pairs: iterable of (left, right) uint8 images of one size, or of (name, left,
            right); read one pair at a time (a generator over a long video is fine).
        grid: the printed grid.
        names: a name per pair for the report (default: the pair's own, else its index).
        min_pairs: fewest pairs with the grid found in both views.
    """
    obj = grid.points3d.astype(np.float32)
    used, rejected, P1, P2, why = [], [], [], [], {}
    size = None
    for k, item in enumerate(pairs):
        name, (left, right) = (item[0], item[1:]) if len(item) == 3 else (k, item)
        name = names[k] if names is not None else name
        a, b = find_grid(left, grid), find_grid(right, grid)
        shape = np.asarray(left).shape[1::-1]
        if size is None:
            size = shape
        elif shape != size:
            raise ValueError(f"pair {name}: images of {shape[0]}x{shape[1]}, the first were {size[0]}x{size[1]}")
        if a is None or b is None:
            rejected.append(name)
            view = "either view" if a is None and b is None else ("the left view" if a is None else "the right view")
            why[name] = f"the {grid.cols}x{grid.rows} grid was not found in {view}"
            continue
        used.append(name)
        P1.append(a.astype(np.float32))
        P2.append(_consistent(a, b, grid).astype(np.float32))
    if len(used) < min_pairs:
        raise ValueError(
            f"the grid ({grid.cols}x{grid.rows}) was found in both views of only {len(used)} pairs; "
            f"at least {min_pairs} are needed (rejected: {rejected[:10]}{' ...' if len(rejected) > 10 else ''})"
        )
    objs = [obj] * len(used)
    rms1, K1, d1, rv1, tv1 = cv2.calibrateCamera(objs, P1, size, None, None)
    rms2, K2, d2, _, _ = cv2.calibrateCamera(objs, P2, size, None, None)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    rms, K1, d1, K2, d2, R, t, _, _ = cv2.stereoCalibrate(objs, P1, P2, K1, d1, K2, d2, size, criteria=crit, flags=cv2.CALIB_FIX_INTRINSIC)
    rig = StereoRig(
        Camera(K1, d1.ravel(), image_size=tuple(int(v) for v in size)),
        Camera(K2, d2.ravel(), image_size=tuple(int(v) for v in size)),
        R,
        t.ravel(),
        volume=_grid_volume(obj, rv1, tv1),
    )
    return Calibration(rig, float(rms1), float(rms2), float(rms), used, rejected, (np.concatenate(P1), np.concatenate(P2)), why)


def plot_coverage(cal: Calibration, path: str | Path) -> Path:
    """Where the grid's circles were seen in each image: the parts left blank are
    uncalibrated (the lens model is extrapolated there)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = cal.rig.left.image_size
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, pts, name in zip(axes, cal.points, ("left", "right")):
        ax.scatter(pts[:, 0], pts[:, 1], s=2, alpha=0.5)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {len(pts)} circle centres from {len(cal.pairs_used)} pairs")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Calibration coverage (RMS {cal.rms_left_px:.3f} / {cal.rms_right_px:.3f} px, stereo {cal.rms_stereo_px:.3f} px)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


__all__ = ["Calibration", "CircleGrid", "calibrate", "find_grid", "plot_coverage"]
