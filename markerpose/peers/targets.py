"""The peers' printed targets, on the same plate as the three-ring marker.

Every target is a raster printed on the three-ring marker's plate (``Marker().plate``,
65 × 80 mm), in the marker frame: the same plate pose renders every system's target at
the same place, and the ground-truth pose is the same 4 × 4 matrix for all of them.

- square tags (AprilTag tag36h11, ArUco 4×4, STag HD21): a 52 mm black square centred
  on the plate (AprilTag's own quiet zone of one module, 6.5 mm, fits the 65 mm width);
- the ChArUco board: 5 × 6 squares of 13 mm (65 × 78 mm), ArUco 4×4 markers of 9.75 mm.

A raster is read with nearest-pixel lookup, so a module grid (one raster pixel per
module) prints with exact edges; the renderer supersamples pixels across an edge.
The raster's top row is the plate's +y side, so a fronto-parallel plate shows the
print upright, as the printed page looks (a mirror image decodes as nothing).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..marker import Marker

PLATE = Marker().plate  # (x0, y0, x1, y1), mm
CENTRE = np.array([(PLATE[0] + PLATE[2]) / 2, (PLATE[1] + PLATE[3]) / 2, 0.0])  # where errors are measured
SQUARE_MM = 52.0  # black square of every square tag
CHARUCO_SQUARES = (5, 6)  # columns, rows
CHARUCO_SQUARE_MM = 13.0
CHARUCO_MARKER_MM = 9.75


@dataclass(frozen=True)
class PrintedTarget:
    """A raster printed on the plate.

    Attributes:
        raster: (rows, cols) uint8, 0 = ink, 255 = paper.
        origin: (x, y) in mm of the raster's top-left corner (its top row at +y).
        pixel_mm: printed size of one raster pixel, mm.
        plate: (x0, y0, x1, y1) of the white plate, mm.
        points: (N, 3) the points the system measures (corners), marker frame, mm, in
            the order its detector reports them.
    """

    raster: np.ndarray
    origin: tuple[float, float]
    pixel_mm: float
    plate: tuple[float, float, float, float]
    points: np.ndarray

    def reflectance(self, xy: np.ndarray, black: float = 0.04, white: float = 0.85) -> np.ndarray:
        """Reflectance at plane points (..., 2), mm; NaN off the plate."""
        xy = np.asarray(xy, np.float64)
        x, y = xy[..., 0], xy[..., 1]
        col = np.floor((x - self.origin[0]) / self.pixel_mm)
        row = np.floor((self.origin[1] - y) / self.pixel_mm)
        rows, cols = self.raster.shape
        inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
        v = np.full(x.shape, 255.0)
        v[inside] = self.raster[row[inside].astype(np.intp), col[inside].astype(np.intp)]
        out = black + (white - black) * v / 255.0
        x0, y0, x1, y1 = self.plate
        return np.where((x < x0) | (x > x1) | (y < y0) | (y > y1), np.nan, out)

    def to_plate(self, raster_xy: np.ndarray) -> np.ndarray:
        """Raster coordinates (x right, y down, in raster pixels from the top-left corner
        of the raster) → (N, 3) marker-frame points, mm."""
        p = np.asarray(raster_xy, np.float64).reshape(-1, 2) * self.pixel_mm
        return np.column_stack([self.origin[0] + p[:, 0], self.origin[1] - p[:, 1], np.zeros(len(p))])


def _square_tag(modules: np.ndarray, quiet: int) -> PrintedTarget:
    """A tag whose black square (``modules``, one raster pixel per module, border
    included) is SQUARE_MM wide, centred on the plate, with ``quiet`` white modules
    around it in the raster. Points: the black square's corners TL, TR, BR, BL as seen
    upright (the order of OpenCV's ArUco and of IPPE_SQUARE's model)."""
    n = modules.shape[0]
    raster = np.pad(modules, quiet, constant_values=255)
    s = SQUARE_MM / n
    origin = (CENTRE[0] - SQUARE_MM / 2 - quiet * s, CENTRE[1] + SQUARE_MM / 2 + quiet * s)
    t = PrintedTarget(raster, origin, s, PLATE, np.zeros((0, 3)))
    corners = t.to_plate(np.array([[quiet, quiet], [quiet + n, quiet], [quiet + n, quiet + n], [quiet, quiet + n]]))
    return PrintedTarget(raster, origin, s, PLATE, corners)


def aruco_dictionary(name: str):
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def apriltag_target(tag_id: int = 0) -> PrintedTarget:
    """AprilTag tag36h11 (OpenCV's copy of the family: the same codes), 8 × 8 modules."""
    m = cv2.aruco.generateImageMarker(aruco_dictionary("DICT_APRILTAG_36h11"), tag_id, 8, borderBits=1)
    return _square_tag(m, quiet=1)


def aruco_target(marker_id: int = 0) -> PrintedTarget:
    """ArUco DICT_4X4_50 (the family with the largest modules), 6 × 6 modules."""
    m = cv2.aruco.generateImageMarker(aruco_dictionary("DICT_4X4_50"), marker_id, 6, borderBits=1)
    return _square_tag(m, quiet=0)


def charuco_board() -> cv2.aruco.CharucoBoard:
    return cv2.aruco.CharucoBoard(CHARUCO_SQUARES, CHARUCO_SQUARE_MM, CHARUCO_MARKER_MM, aruco_dictionary("DICT_4X4_50"))


def charuco_target(px_per_square: int = 100) -> PrintedTarget:
    """A ChArUco board of 5 × 6 squares, 65 × 78 mm, centred on the plate. Points: the
    board's inner chessboard corners in OpenCV's ID order."""
    board = charuco_board()
    cols, rows = CHARUCO_SQUARES
    raster = board.generateImage((cols * px_per_square, rows * px_per_square), marginSize=0, borderBits=1)
    s = CHARUCO_SQUARE_MM / px_per_square
    origin = (CENTRE[0] - cols * CHARUCO_SQUARE_MM / 2, CENTRE[1] + rows * CHARUCO_SQUARE_MM / 2)
    # OpenCV's board frame: x along the raster's columns, y along its rows, mm.
    corners = np.asarray(board.getChessboardCorners(), np.float64)[:, :2] / s
    t = PrintedTarget(raster, origin, s, PLATE, np.zeros((0, 3)))
    return PrintedTarget(raster, origin, s, PLATE, t.to_plate(corners))


# STag HD21 (Benligiray et al., 2019), from the format's published definition: a black
# square of side S with a white disc of radius 0.4 S cut out; inside it 48 code cells,
# discs of radius 0.04374 S, bit j (of the codeword, LSB first) black when set. Cell j
# = 12 q + k sits at polar (0.7 rho_k, theta_k + q pi/2) about the centre, theta
# counter-clockwise on the page. The published HD21 codeword of ID 0.
STAG_HD21_ID0 = 157678901735884
_STAG_CELLS = (  # (rho, theta) of the 12 cells of one quadrant
    (0.088363142525988, 0.785398163397448),
    (0.206935928182607, 0.459275804122858),
    (0.206935928182607, np.pi / 2 - 0.459275804122858),
    (0.313672146827381, 0.200579720495241),
    (0.327493143484516, 0.591687617505840),
    (0.327493143484516, np.pi / 2 - 0.591687617505840),
    (0.313672146827381, np.pi / 2 - 0.200579720495241),
    (0.437421957035861, 0.145724938287167),
    (0.437226762361658, 0.433363129825345),
    (0.430628029742607, 0.785398163397448),
    (0.437226762361658, np.pi / 2 - 0.433363129825345),
    (0.437421957035861, np.pi / 2 - 0.145724938287167),
)
STAG_ORDER = np.array([0, 1, 2, 3])  # stag.detectMarkers reports TL, TR, BR, BL already


def stag_modules(codeword: int = STAG_HD21_ID0, px: int = 2600) -> np.ndarray:
    """The STag's black square as a (px, px) binary raster (0 = ink), no quiet zone."""
    u = (np.arange(px) + 0.5) / px - 0.5  # pixel centres, units of S from the centre
    x, y = np.meshgrid(u, u)
    ink = x**2 + y**2 > 0.4**2
    for j in range(48):
        if (codeword >> j) & 1:
            rho, theta = _STAG_CELLS[j % 12]
            t = theta + (j // 12) * np.pi / 2
            cx, cy = 0.7 * rho * np.cos(t), -0.7 * rho * np.sin(t)
            ink |= (x - cx) ** 2 + (y - cy) ** 2 <= (0.7 * 0.062482177287080) ** 2
    return np.where(ink, 0, 255).astype(np.uint8)


def stag_target(marker_id: int = 0) -> PrintedTarget:
    """STag HD21, ID 0 (the only ID whose codeword is kept here)."""
    if marker_id != 0:
        raise ValueError("only the STag HD21 marker of ID 0 is available")
    return _square_tag(stag_modules(), quiet=0)
