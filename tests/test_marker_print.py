"""Printable target (marker.write_target): exact physical scale in SVG and PDF, error paths."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
import zlib

import numpy as np
import pytest

from markerpose.marker import PAPER_SIZES_MM, Marker, write_target

SVG_NS = "{http://www.w3.org/2000/svg}"
PT_PER_MM = 72.0 / 25.4
_UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "in": 25.4, "pt": 25.4 / 72.0, "px": 25.4 / 96.0}


# ---------------------------------------------------------------------------- SVG helpers


def _svg_length_mm(value: str) -> float:
    m = re.fullmatch(r"\s*([0-9.]+)\s*(mm|cm|in|pt|px)\s*", value)
    assert m, f"SVG length without a physical unit: {value!r}"
    return float(m.group(1)) * _UNIT_TO_MM[m.group(2)]


def _svg_geometry(path):
    """Paper size in mm, mm per user unit (x, y) and the circles {id: (cx_mm, cy_mm, r_mm, fill)}."""
    root = ET.parse(path).getroot()
    w_mm, h_mm = _svg_length_mm(root.get("width")), _svg_length_mm(root.get("height"))
    vx, vy, vw, vh = map(float, root.get("viewBox").split())
    sx, sy = w_mm / vw, h_mm / vh
    circles = {
        c.get("id"): ((float(c.get("cx")) - vx) * sx, (float(c.get("cy")) - vy) * sy, float(c.get("r")) * sx, c.get("fill"))
        for c in root.iter(SVG_NS + "circle")
    }
    return root, (w_mm, h_mm), (sx, sy), circles


# ---------------------------------------------------------------------------- PDF helpers


def _pdf_streams(data: bytes) -> list[bytes]:
    out = []
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            out.append(zlib.decompress(m.group(1)))
        except zlib.error:
            out.append(m.group(1))
    return out


def _pdf_path_bboxes(data: bytes) -> list[tuple[float, float, float, float]]:
    """Bounding boxes (pt) of every path built with m/l/c in the page content streams."""
    boxes = []
    for s in _pdf_streams(data):
        if b" m\n" not in s:
            continue
        operands: list[float] = []
        pts: list[tuple[float, float]] = []
        for tok in s.split():
            try:
                operands.append(float(tok))
                continue
            except ValueError:
                pass
            if tok in (b"m", b"l", b"c"):
                pts += list(zip(operands[0::2], operands[1::2]))
            elif tok in (b"f", b"f*", b"S", b"s", b"B", b"B*", b"n") and pts:
                p = np.array(pts)
                boxes.append((p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()))
                pts = []
            operands = []
    return boxes


def _pdf_circles_mm(data: bytes, diameter: float, tol: float = 0.01) -> np.ndarray:
    """Centres (mm, page frame y up) of the square-bounded paths of the given diameter."""
    out = []
    for x0, y0, x1, y1 in _pdf_path_bboxes(data):
        w, h = (x1 - x0) / PT_PER_MM, (y1 - y0) / PT_PER_MM
        if abs(w - diameter) < tol and abs(h - diameter) < tol:
            out.append(((x0 + x1) / 2 / PT_PER_MM, (y0 + y1) / 2 / PT_PER_MM))
    return np.array(out)


# ---------------------------------------------------------------------------- SVG


@pytest.mark.parametrize("paper", ["a4", "letter"])
def test_svg_physical_page_size(tmp_path, paper):
    out = write_target(Marker(), tmp_path / "t.svg", paper=paper)
    assert out == tmp_path / "t.svg" and out.is_file()
    _, (w, h), (sx, sy), _ = _svg_geometry(out)
    assert (w, h) == pytest.approx(PAPER_SIZES_MM[paper], abs=1e-6)
    assert sx == pytest.approx(1.0) and sy == pytest.approx(1.0)  # one user unit = 1 mm


def test_svg_ring_diameters_and_spacing_exact(tmp_path):
    _, _, _, circ = _svg_geometry(write_target(Marker(), tmp_path / "t.svg"))
    for i in range(3):
        cxo, cyo, ro, fo = circ[f"c{i}-outer"]
        cxi, cyi, ri, fi = circ[f"c{i}-inner"]
        assert 2 * ro == pytest.approx(20.0, abs=1e-9) and fo == "#000000"
        assert 2 * ri == pytest.approx(8.0, abs=1e-9) and fi == "#ffffff"
        assert (cxo, cyo) == pytest.approx((cxi, cyi), abs=1e-9)  # concentric
    c = np.array([circ[f"c{i}-outer"][:2] for i in range(3)])
    # Measurement level: centre spacing in physical millimetres.
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(25.000, abs=0.01)
    assert np.linalg.norm(c[2] - c[0]) == pytest.approx(40.000, abs=0.01)
    # Orientation: SVG y runs down the page, so the marker's +y (c2) is *up*: smaller SVG y.
    assert c[1, 0] - c[0, 0] == pytest.approx(25.0) and c[1, 1] == pytest.approx(c[0, 1])
    assert c[0, 1] - c[2, 1] == pytest.approx(40.0) and c[2, 0] == pytest.approx(c[0, 0])


def test_svg_plate_is_centred_and_clean(tmp_path):
    m = Marker()
    root, (w, h), _, circ = _svg_geometry(write_target(m, tmp_path / "t.svg"))
    plate = next(e for e in root.iter(SVG_NS + "polygon") if e.get("id") == "plate")
    pts = np.array([list(map(float, p.split(","))) for p in plate.get("points").split()])
    x0, y0, x1, y1 = m.plate
    assert pts[:, 0].max() - pts[:, 0].min() == pytest.approx(x1 - x0)
    assert pts[:, 1].max() - pts[:, 1].min() == pytest.approx(y1 - y0)
    assert pts.mean(axis=0) == pytest.approx((w / 2, h / 2))
    # c0 sits where the marker frame puts it relative to the plate (y up → SVG y down).
    c0 = np.array(circ["c0-outer"][:2])
    assert c0 == pytest.approx((pts[:, 0].min() - x0, pts[:, 1].max() + y0))
    # Nothing but the six ring disks is drawn inside the plate outline: text and axis
    # primitives all lie outside it, so a detector sees clean rings.
    px0, py0, px1, py1 = pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()
    for e in root.iter():
        if e.tag in (SVG_NS + "polyline", SVG_NS + "polygon") and e.get("id") != "plate":
            q = np.array([list(map(float, p.split(","))) for p in e.get("points").split()])
            inside = (q[:, 0] > px0) & (q[:, 0] < px1) & (q[:, 1] > py0) & (q[:, 1] < py1)
            assert not inside.any(), e.get("id")
        elif e.tag == SVG_NS + "text":
            x, y = float(e.get("x")), float(e.get("y"))
            assert not (px0 < x < px1 and py0 < y < py1), e.get("id")


def test_svg_contents(tmp_path):
    path = write_target(Marker(), tmp_path / "t.svg")
    root = ET.parse(path).getroot()
    ids = {e.get("id") for e in root.iter() if e.get("id")}
    assert {
        "plate",
        "scale-bar",
        "scale-tick-0",
        "scale-tick-50",
        "axis-x-shaft",
        "axis-x-head",
        "axis-y-shaft",
        "axis-y-head",
        "label-c0",
        "label-c1",
        "label-c2",
    } <= ids
    texts = {e.get("id"): e.text for e in root.iter(SVG_NS + "text")}
    assert [texts[f"label-c{i}"] for i in range(3)] == ["c0", "c1", "c2"]
    assert texts["scale-label"] == "50 mm"
    notes = " ".join(v for k, v in texts.items() if k.startswith("note"))
    assert "100%" in notes and "actual size" in notes and "ruler" in notes
    assert "20 mm" in notes and "8 mm" in notes and "c1 (25, 0)" in notes and "c2 (0, 40)" in notes
    # Scale bar: end ticks exactly 50 mm apart.
    ticks = {e.get("id"): e for e in root.iter(SVG_NS + "polyline")}
    tx = [float(ticks[f"scale-tick-{k}"].get("points").split()[0].split(",")[0]) for k in (0, 50)]
    assert tx[1] - tx[0] == pytest.approx(50.0, abs=1e-9)
    # Axis arrows point along +x (right) and the marker's +y (up the page = decreasing SVG y).
    shaft = {k: np.array([list(map(float, p.split(","))) for p in ticks[f"axis-{k}-shaft"].get("points").split()]) for k in "xy"}
    dx, dy = shaft["x"][1] - shaft["x"][0], shaft["y"][1] - shaft["y"][0]
    assert dx[0] > 0 and dx[1] == pytest.approx(0) and dy[1] < 0 and dy[0] == pytest.approx(0)


# ---------------------------------------------------------------------------- PDF


@pytest.mark.parametrize("paper, size_pt", [("a4", (595.28, 841.89)), ("letter", (612.0, 792.0))])
def test_pdf_mediabox_is_paper(tmp_path, paper, size_pt):
    data = write_target(Marker(), tmp_path / "t.pdf", paper=paper).read_bytes()
    assert data.startswith(b"%PDF")
    boxes = re.findall(rb"/MediaBox\s*\[\s*([-0-9.\s]+)\]", data)
    assert len(boxes) == 1
    x0, y0, x1, y1 = map(float, boxes[0].split())
    assert (x0, y0) == (0.0, 0.0)
    assert x1 == pytest.approx(size_pt[0], abs=0.1) and y1 == pytest.approx(size_pt[1], abs=0.1)
    assert b"/Subtype /Image" not in data  # vector only, nothing rasterised
    assert b"markerpose" in data  # Creator metadata


def test_pdf_ring_geometry_exact(tmp_path):
    data = write_target(Marker(), tmp_path / "t.pdf").read_bytes()
    outer = _pdf_circles_mm(data, 20.0)
    inner = _pdf_circles_mm(data, 8.0)
    assert len(outer) == 3 and len(inner) == 3
    outer = outer[np.lexsort((outer[:, 0], outer[:, 1]))]  # c0, c1 (same y, larger x), c2 (top)
    inner = inner[np.lexsort((inner[:, 0], inner[:, 1]))]
    np.testing.assert_allclose(inner, outer, atol=1e-3)
    c0, c1, c2 = outer
    np.testing.assert_allclose(c1 - c0, (25.0, 0.0), atol=0.01)
    np.testing.assert_allclose(c2 - c0, (0.0, 40.0), atol=0.01)  # y up on the page


# ---------------------------------------------------------------------------- both


@pytest.mark.parametrize("suffix", [".svg", ".pdf"])
def test_repeated_writes_identical(tmp_path, suffix):
    a = write_target(Marker(), tmp_path / f"a{suffix}").read_bytes()
    b = write_target(Marker(), tmp_path / f"b{suffix}").read_bytes()
    assert a == b


def test_custom_marker_geometry(tmp_path):
    m = Marker(outer_diameter=30.0, inner_diameter=12.0, c1=(40.0, 0.0), c2=(0.0, 55.0), margin=5.0)
    _, _, _, circ = _svg_geometry(write_target(m, tmp_path / "t.svg", paper="letter"))
    assert 2 * circ["c2-outer"][2] == pytest.approx(30.0) and 2 * circ["c2-inner"][2] == pytest.approx(12.0)
    c = np.array([circ[f"c{i}-outer"][:2] for i in range(3)])
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(40.0, abs=0.01)
    assert np.linalg.norm(c[2] - c[0]) == pytest.approx(55.0, abs=0.01)


def test_suffix_case_insensitive_and_str_path(tmp_path):
    out = write_target(Marker(), str(tmp_path / "T.SVG"))
    assert out.is_file() and ET.parse(out).getroot().tag == SVG_NS + "svg"


# ---------------------------------------------------------------------------- errors


@pytest.mark.parametrize("name", ["t.png", "t.eps", "t"])
def test_bad_suffix(tmp_path, name):
    with pytest.raises(ValueError, match=r"\.pdf.*\.svg"):
        write_target(Marker(), tmp_path / name)
    assert not (tmp_path / name).exists()


def test_bad_paper(tmp_path):
    with pytest.raises(ValueError, match="a4.*letter"):
        write_target(Marker(), tmp_path / "t.svg", paper="a3")


@pytest.mark.parametrize(
    "marker",
    [Marker(c2=(0.0, 250.0)), Marker(c1=(200.0, 0.0)), Marker(outer_diameter=90.0, inner_diameter=30.0, c1=(100.0, 0.0), c2=(0.0, 120.0))],
)
@pytest.mark.parametrize("suffix", [".svg", ".pdf"])
def test_marker_too_large(tmp_path, marker, suffix):
    with pytest.raises(ValueError, match="does not fit"):
        write_target(marker, tmp_path / f"t{suffix}")
    assert not (tmp_path / f"t{suffix}").exists()


def test_default_marker_fits_letter_and_a4(tmp_path):
    for paper in ("a4", "letter"):
        for suffix in (".svg", ".pdf"):
            assert write_target(Marker(), tmp_path / f"{paper}{suffix}", paper=paper).stat().st_size > 0
