"""The three-ring planar marker: its geometry, in millimetres, in the marker frame.

Marker frame (DESIGN §2): origin at the centre of ring c0, c1 on +x, c2 on +y,
z = x × y out of the printed face. Every ring is a black disk of diameter
``outer_diameter`` with a concentric white disk of diameter ``inner_diameter``.
The printed plate is the rings' bounding box grown by ``margin`` on every side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Marker:
    """Geometry of the marker (all lengths in mm).

    Attributes:
        outer_diameter: diameter of each black ring.
        inner_diameter: diameter of the white disk inside each ring.
        c1: (x, y) of ring c1 in the marker frame (on the +x axis by convention).
        c2: (x, y) of ring c2 in the marker frame (on the +y axis by convention).
        margin: white plate border around the rings' bounding box.
    """

    outer_diameter: float = 20.0
    inner_diameter: float = 8.0
    c1: tuple[float, float] = (25.0, 0.0)
    c2: tuple[float, float] = (0.0, 40.0)
    margin: float = 10.0

    def __post_init__(self):
        if not (0 < self.inner_diameter < self.outer_diameter):
            raise ValueError(
                f"need 0 < inner_diameter < outer_diameter, got {self.inner_diameter} and {self.outer_diameter}"
            )
        if self.margin < 0:
            raise ValueError(f"margin must be >= 0, got {self.margin}")
        c = self.centers2d
        d01 = np.linalg.norm(c[1] - c[0])
        d02 = np.linalg.norm(c[2] - c[0])
        if min(d01, d02, np.linalg.norm(c[2] - c[1])) <= self.outer_diameter:
            raise ValueError("rings overlap: centre distances must exceed outer_diameter")
        # Handedness: c0 -> c1 -> c2 must turn counter-clockwise in the marker frame so that
        # z = x × y points out of the printed face (DESIGN §2).
        if np.cross(c[1] - c[0], c[2] - c[0]) <= 0:
            raise ValueError("c0 -> c1 -> c2 must be counter-clockwise (c2 on the +y side)")

    @property
    def outer_radius(self) -> float:
        return self.outer_diameter / 2.0

    @property
    def inner_radius(self) -> float:
        return self.inner_diameter / 2.0

    @property
    def centers2d(self) -> np.ndarray:
        """(3, 2) ring centres c0, c1, c2 in the marker plane, mm."""
        return np.array([(0.0, 0.0), self.c1, self.c2], dtype=np.float64)

    @property
    def points3d(self) -> np.ndarray:
        """(3, 3) ring centres c0, c1, c2 in the marker frame (z = 0), mm."""
        return np.column_stack([self.centers2d, np.zeros(3)])

    @property
    def plate(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the printed plate in the marker frame, mm."""
        c = self.centers2d
        r = self.outer_radius + self.margin
        return (c[:, 0].min() - r, c[:, 1].min() - r, c[:, 0].max() + r, c[:, 1].max() + r)

    @property
    def plate_corners3d(self) -> np.ndarray:
        """(4, 3) plate corners in the marker frame, counter-clockwise, mm."""
        x0, y0, x1, y1 = self.plate
        return np.array([(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)], dtype=np.float64)

    def reflectance(self, xy: np.ndarray, black: float = 0.04, white: float = 0.85) -> np.ndarray:
        """Ideal printed reflectance at marker-plane points.

        Args:
            xy: (..., 2) points in the marker plane, mm.
            black, white: reflectance of ink and paper.
        Returns:
            (...) reflectance; points off the plate get NaN (the caller composites them).
        """
        xy = np.asarray(xy, dtype=np.float64)
        out = np.full(xy.shape[:-1], white)
        x, y = xy[..., 0], xy[..., 1]
        for cx, cy in self.centers2d:
            r2 = (x - cx) ** 2 + (y - cy) ** 2
            out[(r2 <= self.outer_radius**2) & (r2 > self.inner_radius**2)] = black
        x0, y0, x1, y1 = self.plate
        out[(x < x0) | (x > x1) | (y < y0) | (y > y1)] = np.nan
        return out
