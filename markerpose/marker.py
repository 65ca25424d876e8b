"""The three-ring planar marker: its geometry, in millimetres, in the marker frame.

Marker frame (docs/design.md §1): origin at the centre of ring c0, c1 on +x, c2 on +y,
z = x × y out of the printed face. Every ring is a black disk of diameter
``outer_diameter`` with a concentric white disk of diameter ``inner_diameter``.
The printed plate is the rings' bounding box grown by ``margin`` on every side.

A tool is a marker with a name (and optionally a pointer's tip), kept in a small YAML
file (:meth:`Marker.load`, :meth:`Marker.save`)::

    name: probe
    rings: [[0, 0], [25, 0], [0, 40]]   # c0, c1, c2 in the marker frame, mm
    outer_diameter: 20
    inner_diameter: 8
    plate_margin: 10                    # mm beyond the rings' outer edges
    tip: [10, -60, 0]                   # optional: a point of the tool in the marker frame, mm
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TOOL_KEYS = ("name", "rings", "outer_diameter", "inner_diameter", "plate_margin", "tip")
REQUIRED_KEYS = TOOL_KEYS[:5]  # every key but the optional tip
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")  # a name that OpenIGTLink's device names and file names take


def _numbers(value, shape: tuple, key: str, where: str) -> np.ndarray:
    """``value`` as finite float64 numbers of ``shape``, else ``ValueError`` naming the key."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.all(np.isfinite(a)) or isinstance(value, bool):
        want = "a number" if shape == () else f"{' x '.join(map(str, shape))} numbers"
        raise ValueError(f"{where}: {key} must be {want}, got {value!r}")
    return a


@dataclass(frozen=True)
class Marker:
    """Geometry of the marker (all lengths in mm).

    Attributes:
        outer_diameter: diameter of each black ring.
        inner_diameter: diameter of the white disk inside each ring.
        c1: (x, y) of ring c1 in the marker frame (on the +x axis by convention).
        c2: (x, y) of ring c2 in the marker frame (on the +y axis by convention).
        margin: white plate border around the rings' bounding box.
        name: the tool's name (letters, digits, ``_`` and ``-``, starting with a letter).
        tip: optional (x, y, z) of a point of the tool (a pointer's tip) in the marker frame.
    """

    outer_diameter: float = 20.0
    inner_diameter: float = 8.0
    c1: tuple[float, float] = (25.0, 0.0)
    c2: tuple[float, float] = (0.0, 40.0)
    margin: float = 10.0
    name: str = "marker"
    tip: tuple[float, float, float] | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not NAME.fullmatch(self.name):
            raise ValueError(f"name must be 1-32 letters, digits, _ or - starting with a letter, got {self.name!r}")
        if self.tip is not None:
            if len(self.tip) != 3 or not all(math.isfinite(float(v)) for v in self.tip):
                raise ValueError(f"tip must be three finite numbers (x, y, z) in mm, got {self.tip!r}")
            object.__setattr__(self, "tip", tuple(float(v) for v in self.tip))  # hashable, as the caches key on markers
        if not (0 < self.inner_diameter < self.outer_diameter):
            raise ValueError(f"need 0 < inner_diameter < outer_diameter, got {self.inner_diameter} and {self.outer_diameter}")
        if self.margin < 0:
            raise ValueError(f"margin must be >= 0, got {self.margin}")
        c = self.centers2d
        d01 = np.linalg.norm(c[1] - c[0])
        d02 = np.linalg.norm(c[2] - c[0])
        if min(d01, d02, np.linalg.norm(c[2] - c[1])) <= self.outer_diameter:
            raise ValueError("rings overlap: centre distances must exceed outer_diameter")
        # Handedness: c0 -> c1 -> c2 must turn counter-clockwise in the marker frame so that
        # z = x × y points out of the printed face.
        a, b = c[1] - c[0], c[2] - c[0]
        if a[0] * b[1] - a[1] * b[0] <= 0:
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

    def to_dict(self) -> dict:
        """The tool file's fields (:data:`TOOL_KEYS`), as plain numbers."""
        out = {
            "name": self.name,
            "rings": [[0.0, 0.0], [float(v) for v in self.c1], [float(v) for v in self.c2]],
            "outer_diameter": float(self.outer_diameter),
            "inner_diameter": float(self.inner_diameter),
            "plate_margin": float(self.margin),
        }
        if self.tip is not None:
            out["tip"] = [float(v) for v in self.tip]
        return out

    def save(self, path: str | Path) -> Path:
        """Write the tool file (YAML) that :meth:`load` reads back as this marker."""
        import yaml

        path = Path(path)
        path.write_text(yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None))
        return path

    @classmethod
    def load(cls, path: str | Path) -> Marker:
        """A tool file (YAML: :data:`TOOL_KEYS`); ``ValueError`` naming the file and what is wrong."""
        import yaml

        path = Path(path)
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the tool file ({getattr(exc, 'strerror', None) or exc})") from None
        if len(text) > 65536:  # a tool file is a few lines; a huge one is not one (and deep nesting costs the parser)
            raise ValueError(f"{path}: not a tool file ({len(text)} characters)")
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
        except RecursionError:
            raise ValueError(f"{path}: nested too deeply to be a tool file") from None
        return cls.from_dict(data, str(path))

    @classmethod
    def from_dict(cls, data, where: str = "tool") -> Marker:
        """The marker of a tool file's fields (:data:`TOOL_KEYS`; ``where`` names the source
        in errors): c0 at the origin, c1 on +x, c2 in the +y half-plane."""
        if not isinstance(data, dict):
            raise ValueError(f"{where}: a tool file maps the keys {list(TOOL_KEYS)}, got {type(data).__name__}")
        unknown = sorted(str(k) for k in data if k not in TOOL_KEYS)
        missing = [k for k in REQUIRED_KEYS if k not in data]
        if unknown or missing:
            what = ", ".join(p for p in (f"unknown {unknown}" if unknown else "", f"missing {missing}" if missing else "") if p)
            raise ValueError(f"{where}: {what} key(s); a tool file has {list(TOOL_KEYS)} (tip optional)")
        rings = _numbers(data["rings"], (3, 2), "rings", where)
        if np.any(rings[0] != 0):
            raise ValueError(f"{where}: rings: c0 must be at the origin (0, 0), got {rings[0].tolist()}")
        if rings[1, 1] != 0 or rings[1, 0] <= 0:
            raise ValueError(f"{where}: rings: c1 must lie on the +x axis (x > 0, 0), got {rings[1].tolist()}")
        if rings[2, 1] <= 0:
            raise ValueError(f"{where}: rings: c2 must lie in the +y half-plane (y > 0), got {rings[2].tolist()}")
        size = {k: float(_numbers(data[k], (), k, where)) for k in ("outer_diameter", "inner_diameter", "plate_margin")}
        tip = None if data.get("tip") is None else tuple(_numbers(data["tip"], (3,), "tip", where).tolist())
        try:
            return cls(
                outer_diameter=size["outer_diameter"],
                inner_diameter=size["inner_diameter"],
                c1=tuple(rings[1].tolist()),
                c2=tuple(rings[2].tolist()),
                margin=size["plate_margin"],
                name=data["name"],
                tip=tip,
            )
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

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


# --------------------------------------------------------------------------------------
# Printable target
# --------------------------------------------------------------------------------------
#
# The page is described once as a list of primitives in page millimetres (origin at the
# bottom-left corner of the sheet, x right, y up — the marker frame's orientation) and then
# written either as hand-made SVG (true <circle> elements, user unit = 1 mm) or as a vector
# PDF through matplotlib (figure = sheet, one axes spanning it, data unit = 1 mm). Everything
# that is not a ring stays outside the plate outline, so the plate prints exactly what
# `Marker.reflectance` models and a detector reads clean rings.

PAPER_SIZES_MM: dict[str, tuple[float, float]] = {
    "a4": (210.0, 297.0),
    "letter": (215.9, 279.4),
}

_TARGET_SUFFIXES = (".pdf", ".svg")
_MM_PER_INCH = 25.4
_PT_PER_MM = 72.0 / _MM_PER_INCH

_PAGE_MARGIN = 10.0  # mm kept free at the left/right sheet edges (printer's unprintable band)
_TOP_RESERVED = 25.0  # mm at the top for the title
_BOTTOM_RESERVED = 48.0  # mm at the bottom for the scale bar and the notes
_LABEL_GAP = 3.0  # mm from the plate edge to a ring ID label
_AXIS_GAP = 11.0  # mm from the plate edge to an axis arrow
_LABEL_SIZE = 3.5  # mm, ring ID labels
_NOTE_SIZE = 2.8  # mm (about 8 pt), notes
_TITLE_SIZE = 5.0  # mm

_INK = "#000000"
_PAPER = "#ffffff"
_CUT = "#999999"  # plate outline: light enough not to look like marker ink
_ANNOT = "#404040"  # arrows, labels, notes


@dataclass(frozen=True)
class _Circle:
    cx: float
    cy: float
    r: float
    fill: str
    gid: str


@dataclass(frozen=True)
class _Polyline:
    points: tuple[tuple[float, float], ...]
    color: str
    width: float  # mm
    closed: bool
    filled: bool  # filled polygon without stroke (arrowheads)
    gid: str


@dataclass(frozen=True)
class _Text:
    x: float
    y: float  # baseline, page mm (y up)
    text: str
    size: float  # mm (em size)
    ha: str  # "left" | "center" | "right"
    color: str
    gid: str

    def bbox(self) -> tuple[float, float, float, float]:
        """Conservative extent (xmin, ymin, xmax, ymax) for layout checks (0.62 em per glyph)."""
        w = 0.62 * self.size * len(self.text)
        x0 = {"left": self.x, "center": self.x - w / 2, "right": self.x - w}[self.ha]
        return (x0, self.y - 0.25 * self.size, x0 + w, self.y + 0.8 * self.size)


def _fmt(v: float) -> str:
    """Compact, exact-enough (0.1 µm) decimal for the SVG."""
    s = f"{float(v):.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _num(v: float) -> str:
    """Human-readable number for the notes (25, 12.5, not 25.0)."""
    return f"{float(v):g}"


def _text_centered(x: float, y: float, text: str, size: float, ha: str, color: str, gid: str) -> _Text:
    # Place the baseline so the lower-case/digit body is roughly centred on y (cap height of
    # DejaVu/Helvetica-like fonts ≈ 0.72 em). The same baseline is used for both formats.
    return _Text(x, y - 0.36 * size, text, size, ha, color, gid)


def _arrow(p0: np.ndarray, p1: np.ndarray, color: str, width: float, gid: str, head: float = 3.0):
    """Shaft p0 → base of head plus a filled triangular head ending exactly at p1."""
    d = p1 - p0
    u = d / np.linalg.norm(d)
    n = np.array([-u[1], u[0]])
    base = p1 - head * u
    shaft = _Polyline((tuple(p0), tuple(base)), color, width, False, False, gid + "-shaft")
    tri = (tuple(p1), tuple(base + 0.35 * head * n), tuple(base - 0.35 * head * n))
    return [shaft, _Polyline(tri, color, 0.0, True, True, gid + "-head")]


def _target_items(marker: Marker, paper_mm: tuple[float, float]) -> list:
    """All primitives of the printable page, in page mm (y up). Raises ValueError if they do not fit."""
    W, H = paper_mm
    c = marker.centers2d
    x0, y0, x1, y1 = marker.plate
    # Centre the plate on the sheet; page = marker + offset (pure translation: y stays up).
    off = np.array([W / 2 - (x0 + x1) / 2, H / 2 - (y0 + y1) / 2])
    cp = c + off
    px0, py0, px1, py1 = x0 + off[0], y0 + off[1], x1 + off[0], y1 + off[1]
    corners = np.array([(px0, py0), (px1, py0), (px1, py1), (px0, py1)])

    items: list = []

    # Plate outline (cut line): a thin grey rectangle exactly on the plate boundary.
    items.append(_Polyline(tuple(map(tuple, corners)), _CUT, 0.2, True, False, "plate"))

    # Rings: black disk of the outer diameter, white disk of the inner diameter on top.
    for i, (cx, cy) in enumerate(cp):
        items.append(_Circle(cx, cy, marker.outer_radius, _INK, f"c{i}-outer"))
        items.append(_Circle(cx, cy, marker.inner_radius, _PAPER, f"c{i}-inner"))

    items += _ring_labels(cp, (px0, py0, px1, py1))
    items += _axis_items(cp, corners)
    if marker.name != "marker":  # a tool's name, on its plate's bottom margin where that has room, else under it
        on_plate = marker.margin >= 2 * _LABEL_SIZE
        y = py0 + 0.7 * _LABEL_SIZE if on_plate else py0 - _LABEL_GAP - 0.75 * _LABEL_SIZE
        items.append(_Text((px0 + px1) / 2, y, marker.name, _LABEL_SIZE, "center", _ANNOT, "name"))
    _check_fits(items, marker, paper_mm)

    # Title.
    items.append(_Text(W / 2, H - 15.0, _title(marker), _TITLE_SIZE, "center", _INK, "title"))

    items += _scale_bar(W / 2)
    items += _notes(marker, W)
    return items


def _title(marker: Marker) -> str:
    return "markerpose three-ring target" if marker.name == "marker" else f"markerpose tool: {marker.name}"


def _ring_labels(cp: np.ndarray, plate: tuple) -> list:
    """The ring IDs' labels: outside the plate (page mm: x0, y0, x1, y1), just beyond the
    plate edge nearest to the ring (ties broken towards the side facing away from the
    rings' centroid), aligned with the ring centre; cp: (3, 2) page mm."""
    px0, py0, px1, py1 = plate
    items = []
    centroid = cp.mean(axis=0)
    for i, (cx, cy) in enumerate(cp):
        away = np.array([cx, cy]) - centroid
        edges = [  # (distance to edge, outward normal)
            (cx - px0, np.array([-1.0, 0.0])),
            (px1 - cx, np.array([1.0, 0.0])),
            (cy - py0, np.array([0.0, -1.0])),
            (py1 - cy, np.array([0.0, 1.0])),
        ]
        _, nrm = min(edges, key=lambda e: (round(e[0], 6), -float(e[1] @ away)))
        s = _LABEL_SIZE
        if nrm[0] < 0:
            t = _text_centered(px0 - _LABEL_GAP, cy, f"c{i}", s, "right", _ANNOT, f"label-c{i}")
        elif nrm[0] > 0:
            t = _text_centered(px1 + _LABEL_GAP, cy, f"c{i}", s, "left", _ANNOT, f"label-c{i}")
        elif nrm[1] < 0:
            t = _Text(cx, py0 - _LABEL_GAP - 0.75 * s, f"c{i}", s, "center", _ANNOT, f"label-c{i}")
        else:
            t = _Text(cx, py1 + _LABEL_GAP, f"c{i}", s, "center", _ANNOT, f"label-c{i}")
        items.append(t)
    return items


def _axis_items(cp: np.ndarray, corners: np.ndarray) -> list:
    """The marker axes: the segment c0→c1 (x) and the frame's y axis up to c2's height
    (c0→c2 where c2 lies on +y), each translated perpendicular to itself, away from the
    third ring, until it clears the plate (``corners`` (4, 2)) by _AXIS_GAP. They keep the
    true direction and length of the axes and never come near the rings; cp: (3, 2) page mm."""
    items: list = []
    ux = (cp[1] - cp[0]) / np.linalg.norm(cp[1] - cp[0])
    uy = np.array([-ux[1], ux[0]])  # the frame's y: x turned a quarter counter-clockwise (the page's y is up)
    ends = {1: cp[1], 2: cp[0] + uy * float((cp[2] - cp[0]) @ uy)}
    for name, j, k in (("x", 1, 2), ("y", 2, 1)):
        d = ends[j] - cp[0]
        u = d / np.linalg.norm(d)
        n = np.array([-u[1], u[0]])
        if n @ (cp[k] - cp[0]) > 0:
            n = -n
        shift = float(np.max((corners - cp[0]) @ n)) + _AXIS_GAP
        a0, a1 = cp[0] + shift * n, ends[j] + shift * n
        items += _arrow(a0, a1, _ANNOT, 0.35, f"axis-{name}")
        # A short tick at the origin end marks where c0 projects onto the arrow.
        items.append(_Polyline((tuple(a0 - 1.5 * n), tuple(a0 + 1.5 * n)), _ANNOT, 0.35, False, False, f"axis-{name}-origin"))
        tip = a1 + 2.8 * u
        items.append(_text_centered(tip[0], tip[1], name, _LABEL_SIZE, "center", _ANNOT, f"axis-{name}-label"))
    return items


def _check_fits(items: list, marker: Marker, paper_mm: tuple[float, float]) -> None:
    """Raise ValueError unless ``items`` (everything drawn around the plate) sit in the
    free area of the sheet."""
    W, H = paper_mm
    x0, y0, x1, y1 = marker.plate
    ext = _items_extent(items)
    free = (_PAGE_MARGIN, _BOTTOM_RESERVED, W - _PAGE_MARGIN, H - _TOP_RESERVED)
    if ext[0] < free[0] or ext[1] < free[1] or ext[2] > free[2] or ext[3] > free[3]:
        raise ValueError(
            f"marker does not fit on the page: the plate ({x1 - x0:g} x {y1 - y0:g} mm), centred on the "
            f"{W:g} x {H:g} mm sheet with its labels and axes, spans x {ext[0]:.1f}..{ext[2]:.1f}, "
            f"y {ext[1]:.1f}..{ext[3]:.1f} mm but must stay within x {free[0]:g}..{free[2]:g}, "
            f"y {free[1]:g}..{free[3]:g} mm (use a smaller marker or larger paper)"
        )


def _notes(marker: Marker, W: float) -> list:
    """The geometry and printing instructions, centred on the sheet of width ``W`` mm."""
    items = []
    do, di = marker.outer_diameter, marker.inner_diameter
    x0, y0, x1, y1 = marker.plate
    (c1x, c1y), (c2x, c2y) = marker.c1, marker.c2
    y_axis = "c0\u2192c2" if c2x == 0 else "x turned 90\u00b0 toward c2"
    axes = f"x: c0\u2192c1, y: {y_axis}, z out of the page."
    notes = [
        f"Rings: black outer \u00d8 {_num(do)} mm, white inner \u00d8 {_num(di)} mm; "
        f"plate {_num(x1 - x0)} \u00d7 {_num(y1 - y0)} mm (grey cut line, margin {_num(marker.margin)} mm).",
        f"Centres (marker frame, mm): c0 (0, 0), c1 ({_num(c1x)}, {_num(c1y)}), c2 ({_num(c2x)}, {_num(c2y)}); " + axes,
        "Print at 100% / actual size (no \u201cfit to page\u201d); check the scale bar with a ruler.",
    ]
    for k, line in enumerate(notes):
        items.append(_Text(W / 2, 24.0 - 5.0 * k, line, _NOTE_SIZE, "center", _ANNOT if k < 2 else _INK, f"note-{k}"))
    return items


def _scale_bar(x_center: float, bar_y: float = 36.0, bar_len: float = 50.0) -> list:
    """A 50 mm scale bar with end ticks (tick centres exactly 50 mm apart), 10 mm minor
    ticks and its label, centred on ``x_center`` (page mm, y up)."""
    bx0 = x_center - bar_len / 2
    items = [_Polyline(((bx0, bar_y), (bx0 + bar_len, bar_y)), _INK, 0.3, False, False, "scale-bar")]
    for m in range(0, int(bar_len) + 1, 10):
        h = 3.0 if m in (0, bar_len) else 1.5
        items.append(_Polyline(((bx0 + m, bar_y - h), (bx0 + m, bar_y + h)), _INK, 0.3, False, False, f"scale-tick-{m}"))
    items.append(_Text(x_center, bar_y + 4.5, "50 mm", _NOTE_SIZE * 1.2, "center", _INK, "scale-label"))
    return items


def write_grid(grid, path, paper: str = "a4") -> Path:
    """Write a printable asymmetric circle grid (:class:`markerpose.calibration.CircleGrid`)
    at exact physical scale, with a 50 mm scale bar and its geometry, as ``.pdf`` or ``.svg``.
    ``ValueError`` for an unsupported suffix or paper, or a grid that does not fit."""
    path, key = _page(path, paper)
    W, H = PAPER_SIZES_MM[key]
    p = grid.points3d[:, :2]
    span = p.max(0) - p.min(0) + 2 * grid.radius
    free_w, free_h = W - 2 * _PAGE_MARGIN, H - _TOP_RESERVED - _BOTTOM_RESERVED
    if span[0] > free_w or span[1] > free_h:
        raise ValueError(
            f"the grid ({span[0]:g} x {span[1]:g} mm) does not fit on {key} (at most {free_w:g} x {free_h:g} mm): "
            "use a smaller --spacing or larger paper"
        )
    # Centred in the free area; the grid's y axis runs down the page (as seen in an image).
    ox = W / 2 - (p[:, 0].min() + p[:, 0].max()) / 2
    oy = _BOTTOM_RESERVED + free_h / 2 + (p[:, 1].min() + p[:, 1].max()) / 2
    items = [_Circle(ox + x, oy - y, grid.radius, _INK, f"circle-{k}") for k, (x, y) in enumerate(p)]
    items.append(_Text(W / 2, H - 15.0, f"markerpose calibration grid {grid.cols}x{grid.rows}", _TITLE_SIZE, "center", _INK, "title"))
    items += _scale_bar(W / 2)
    notes = [
        f"Asymmetric circle grid, {grid.cols} x {grid.rows} (OpenCV's pattern size), spacing {_num(grid.spacing)} mm, "
        f"circles Ø {_num(2 * grid.radius)} mm.",
        f"markerpose calibrate LEFT RIGHT --grid {grid.cols}x{grid.rows} --spacing {_num(grid.spacing)} --out rig.yaml",
        "Print at 100% / actual size (no “fit to page”); check the scale bar with a ruler; mount it flat.",
    ]
    for k, line in enumerate(notes):
        items.append(_Text(W / 2, 24.0 - 5.0 * k, line, _NOTE_SIZE, "center", _ANNOT if k < 2 else _INK, f"note-{k}"))
    return _write(items, (W, H), path, f"markerpose calibration grid {grid.cols}x{grid.rows}")


def _page(path, paper: str) -> tuple[Path, str]:
    """(path, paper key) after checking the suffix (.pdf or .svg) and the paper name."""
    path = Path(path)
    if path.suffix.lower() not in _TARGET_SUFFIXES:
        raise ValueError(f"unsupported file suffix {path.suffix!r}: use one of {', '.join(_TARGET_SUFFIXES)}")
    key = str(paper).lower()
    if key not in PAPER_SIZES_MM:
        raise ValueError(f"unknown paper {paper!r}: use one of {', '.join(PAPER_SIZES_MM)}")
    return path, key


def _write(items: list, paper_mm: tuple, path: Path, title: str) -> Path:
    """The page as SVG or PDF, by the path's suffix."""
    if path.suffix.lower() == ".svg":
        _write_svg(items, paper_mm, path, title)
    else:
        _write_pdf(items, paper_mm, path, title)
    return path


def _items_extent(items: list) -> tuple[float, float, float, float]:
    xs: list[float] = []
    ys: list[float] = []
    for it in items:
        if isinstance(it, _Circle):
            xs += [it.cx - it.r, it.cx + it.r]
            ys += [it.cy - it.r, it.cy + it.r]
        elif isinstance(it, _Polyline):
            xs += [p[0] for p in it.points]
            ys += [p[1] for p in it.points]
        else:
            bx0, by0, bx1, by1 = it.bbox()
            xs += [bx0, bx1]
            ys += [by0, by1]
    return (min(xs), min(ys), max(xs), max(ys))


def _write_svg(items: list, paper_mm: tuple[float, float], path: Path, title: str) -> None:
    from xml.sax.saxutils import escape

    W, H = paper_mm

    def y(v: float) -> str:  # page mm (y up) → SVG user units (y down)
        return _fmt(H - v)

    out = [
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
        # Physical size in mm and a viewBox of the same numbers: one user unit is one millimetre.
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_fmt(W)}mm" height="{_fmt(H)}mm" '
        f'viewBox="0 0 {_fmt(W)} {_fmt(H)}">',
        f"<title>{escape(title)}</title>",
        "<desc>Created by markerpose. Print at 100% / actual size.</desc>",
        f'<rect id="page" x="0" y="0" width="{_fmt(W)}" height="{_fmt(H)}" fill="{_PAPER}"/>',
    ]
    anchors = {"left": "start", "center": "middle", "right": "end"}
    for it in items:
        if isinstance(it, _Circle):
            out.append(f'<circle id="{it.gid}" cx="{_fmt(it.cx)}" cy="{y(it.cy)}" r="{_fmt(it.r)}" fill="{it.fill}"/>')
        elif isinstance(it, _Polyline):
            pts = " ".join(f"{_fmt(px)},{y(py)}" for px, py in it.points)
            tag = "polygon" if (it.closed or it.filled) else "polyline"
            if it.filled:
                style = f'fill="{it.color}" stroke="none"'
            else:
                style = f'fill="none" stroke="{it.color}" stroke-width="{_fmt(it.width)}" stroke-linecap="butt" stroke-linejoin="miter"'
            out.append(f'<{tag} id="{it.gid}" points="{pts}" {style}/>')
        else:
            out.append(
                f'<text id="{it.gid}" x="{_fmt(it.x)}" y="{y(it.y)}" font-size="{_fmt(it.size)}" '
                f'font-family="DejaVu Sans, Helvetica, Arial, sans-serif" text-anchor="{anchors[it.ha]}" '
                f'fill="{it.color}">{escape(it.text)}</text>'
            )
    out.append("</svg>")
    path.write_text("\n".join(out) + "\n", encoding="utf-8")


def _write_pdf(items: list, paper_mm: tuple[float, float], path: Path, title: str) -> None:
    import matplotlib
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle, Polygon

    W, H = paper_mm
    with matplotlib.rc_context({"pdf.fonttype": 42, "path.simplify": False}):
        # Figure = sheet; one axes over the whole figure with limits (0, W) x (0, H): 1 data unit
        # is 1 mm on paper in both directions (the figure's aspect equals the sheet's).
        fig = Figure(figsize=(W / _MM_PER_INCH, H / _MM_PER_INCH), facecolor=_PAPER)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_xlim(0.0, W)
        ax.set_ylim(0.0, H)
        ax.set_axis_off()
        for it in items:
            if isinstance(it, _Circle):
                ax.add_patch(Circle((it.cx, it.cy), it.r, facecolor=it.fill, edgecolor="none", linewidth=0, gid=it.gid))
            elif isinstance(it, _Polyline):
                if it.filled:
                    ax.add_patch(Polygon(it.points, closed=True, facecolor=it.color, edgecolor="none", linewidth=0, gid=it.gid))
                elif it.closed:
                    ax.add_patch(
                        Polygon(
                            it.points,
                            closed=True,
                            fill=False,
                            edgecolor=it.color,
                            linewidth=it.width * _PT_PER_MM,
                            joinstyle="miter",
                            gid=it.gid,
                        )
                    )
                else:
                    xs, ys = zip(*it.points)
                    ax.add_line(
                        Line2D(
                            xs,
                            ys,
                            color=it.color,
                            linewidth=it.width * _PT_PER_MM,
                            solid_capstyle="butt",
                            solid_joinstyle="miter",
                            gid=it.gid,
                        )
                    )
            else:
                ax.text(
                    it.x,
                    it.y,
                    it.text,
                    fontsize=it.size * _PT_PER_MM,
                    ha=it.ha,
                    va="baseline",
                    color=it.color,
                    family="DejaVu Sans",
                    gid=it.gid,
                )
        fig.savefig(path, format="pdf", facecolor=_PAPER, metadata={"Title": title, "Creator": "markerpose", "CreationDate": None})


def write_target(marker: Marker, path, paper: str = "a4") -> Path:
    """Write a printable target for ``marker`` at exact physical scale.

    The page holds the three rings (black disk of ``outer_diameter`` with a white disk of
    ``inner_diameter``) on a plate outlined by a thin grey cut line, centred on the sheet with
    the marker's y axis pointing up the page; outside the plate: the ring IDs c0/c1/c2, the
    marker axes (x along c0→c1, y along c0→c2, offset so they never touch a ring), a 50 mm
    scale bar with end ticks, and a note with the geometry and the printing instructions.
    Both formats are vector; writing twice gives identical bytes.

    Args:
        marker: the marker geometry (mm).
        path: output file; its suffix chooses the format, ``.pdf`` or ``.svg``.
        paper: ``"a4"`` (210 x 297 mm) or ``"letter"`` (215.9 x 279.4 mm).
    Returns:
        The written path.
    Raises:
        ValueError: unsupported suffix or paper, or the marker does not fit on the sheet.
    """
    path, key = _page(path, paper)
    paper_mm = PAPER_SIZES_MM[key]
    return _write(_target_items(marker, paper_mm), paper_mm, path, _title(marker))
