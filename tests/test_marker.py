"""Tests for markerpose.marker: geometry of the three-ring marker and its printed reflectance."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from markerpose import Marker, StereoRig

BLACK, WHITE = 0.04, 0.85


class TestGeometry:
    def test_defaults_are_the_papers_target(self):
        m = Marker()
        assert (m.outer_diameter, m.inner_diameter) == (20.0, 8.0)
        assert (m.outer_radius, m.inner_radius) == (10.0, 4.0)
        assert m.c1 == (25.0, 0.0) and m.c2 == (0.0, 40.0)

    def test_points3d(self):
        m = Marker()
        P = m.points3d
        assert P.shape == (3, 3) and P.dtype == np.float64
        np.testing.assert_array_equal(P, [[0, 0, 0], [25, 0, 0], [0, 40, 0]])
        np.testing.assert_array_equal(m.centers2d, P[:, :2])

    def test_points3d_follow_parameters(self):
        m = Marker(c1=(30.0, 0.0), c2=(0.0, 55.0))
        np.testing.assert_array_equal(m.points3d, [[0, 0, 0], [30, 0, 0], [0, 55, 0]])

    def test_frame_convention(self):
        # c0 origin, c1 on +x, c2 on +y: z = x × y is +z (counter-clockwise in the marker plane).
        P = Marker().points3d
        z = np.cross(P[1] - P[0], P[2] - P[0])
        assert z[2] > 0 and z[0] == 0 and z[1] == 0

    def test_plate(self):
        m = Marker()
        assert m.plate == (-20.0, -20.0, 45.0, 60.0)
        assert Marker(margin=0.0).plate == (-10.0, -10.0, 35.0, 50.0)

    def test_plate_corners_counter_clockwise(self):
        corners = Marker().plate_corners3d
        assert corners.shape == (4, 3)
        np.testing.assert_array_equal(corners[:, 2], 0)
        x, y = corners[:, 0], corners[:, 1]
        area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
        assert area == pytest.approx(65.0 * 80.0)  # positive: counter-clockwise

    def test_frozen(self):
        with pytest.raises(dataclasses.FrozenInstanceError):
            Marker().margin = 3.0  # type: ignore[misc]

    def test_image_orientation_negative_signed_area(self):
        """DESIGN §2: a marker facing the camera shows c0 → c1 → c2 clockwise in a y-down image."""
        rig = StereoRig.default()
        R = np.diag([1.0, -1.0, -1.0])  # marker z toward the camera
        P = Marker().points3d @ R.T + [-10.0, 20.0, 500.0]
        for uv in rig.project(P):
            a, b = uv[1] - uv[0], uv[2] - uv[0]
            assert a[0] * b[1] - a[1] * b[0] < 0


class TestReflectance:
    def test_values(self):
        m = Marker()
        cases = {
            (0.0, 0.0): WHITE,  # hole of c0
            (25.0, 0.0): WHITE,  # hole of c1
            (0.0, 40.0): WHITE,  # hole of c2
            (7.0, 0.0): BLACK,  # ring c0
            (25.0, -9.0): BLACK,  # ring c1
            (-6.0, 40.0): BLACK,  # ring c2
            (12.5, 20.0): WHITE,  # paper between the rings
            (44.0, 59.0): WHITE,  # paper near the plate corner
        }
        xy = np.array(list(cases))
        np.testing.assert_array_equal(m.reflectance(xy), list(cases.values()))

    def test_off_plate_is_nan(self):
        m = Marker()
        x0, y0, x1, y1 = m.plate
        off = np.array([[x0 - 0.01, 0.0], [x1 + 0.01, 0.0], [0.0, y0 - 0.01], [0.0, y1 + 0.01], [100.0, 100.0]])
        assert np.all(np.isnan(m.reflectance(off)))
        on = np.array([[x0, y0], [x1, y1]])  # the edge belongs to the plate
        np.testing.assert_array_equal(m.reflectance(on), WHITE)

    def test_ring_boundaries(self):
        m = Marker()
        # Black annulus is inner < r <= outer.
        eps = 1e-9
        xy = np.array([[10.0, 0], [10.0 + eps, 0], [4.0, 0], [4.0 + eps, 0], [4.0 - eps, 0]])
        np.testing.assert_array_equal(m.reflectance(xy), [BLACK, WHITE, WHITE, BLACK, WHITE])

    def test_shape_preserved(self):
        m = Marker()
        xy = np.random.default_rng(0).uniform(-30, 70, (4, 5, 6, 2))
        out = m.reflectance(xy)
        assert out.shape == (4, 5, 6) and out.dtype == np.float64
        assert m.reflectance(np.array([0.0, 0.0])).shape == ()

    def test_custom_black_white(self):
        out = Marker().reflectance(np.array([[0.0, 0.0], [7.0, 0.0]]), black=0.1, white=0.9)
        np.testing.assert_array_equal(out, [0.9, 0.1])

    def test_ink_area(self):
        """Monte Carlo over the plate: the black fraction equals three annuli over the plate area."""
        m = Marker()
        x0, y0, x1, y1 = m.plate
        rng = np.random.default_rng(1)
        xy = rng.uniform([x0, y0], [x1, y1], (200_000, 2))
        frac = np.mean(m.reflectance(xy) == BLACK)
        expected = 3 * np.pi * (m.outer_radius**2 - m.inner_radius**2) / ((x1 - x0) * (y1 - y0))
        assert frac == pytest.approx(expected, abs=3e-3)


class TestValidation:
    @pytest.mark.parametrize("inner, outer", [(20.0, 20.0), (25.0, 20.0), (0.0, 20.0), (-1.0, 20.0)])
    def test_inner_outer(self, inner, outer):
        with pytest.raises(ValueError, match="0 < inner_diameter < outer_diameter"):
            Marker(outer_diameter=outer, inner_diameter=inner)

    def test_negative_margin(self):
        with pytest.raises(ValueError, match="margin must be >= 0"):
            Marker(margin=-1.0)

    @pytest.mark.parametrize(
        "kwargs",
        [
            {"c1": (15.0, 0.0)},  # c0-c1 closer than a diameter
            {"c2": (0.0, 20.0)},  # touching counts as overlapping
            {"c1": (25.0, 0.0), "c2": (18.0, 12.0)},  # c1-c2 overlap
            {"outer_diameter": 30.0, "inner_diameter": 8.0},  # big rings overlap c0-c1
        ],
    )
    def test_overlapping_rings(self, kwargs):
        with pytest.raises(ValueError, match="rings overlap"):
            Marker(**kwargs)

    @pytest.mark.parametrize(
        "kwargs",
        [
            {"c2": (0.0, -40.0)},  # mirror image: c2 on -y
            {"c1": (0.0, 40.0), "c2": (25.0, 0.0)},  # c1 and c2 swapped
            {"c1": (25.0, 0.0), "c2": (50.0, 0.0)},  # collinear: no frame
        ],
    )
    def test_wrong_handedness(self, kwargs):
        with pytest.raises(ValueError, match="counter-clockwise"):
            Marker(**kwargs)

    def test_valid_custom_marker(self):
        m = Marker(outer_diameter=12.0, inner_diameter=5.0, c1=(20.0, 0.0), c2=(3.0, 30.0), margin=0.0)
        assert m.reflectance(np.array([3.0, 30.0])) == WHITE


def test_package_version_matches_pyproject():
    import re
    from pathlib import Path

    import markerpose

    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert re.search(r'^version = "([^"]+)"', text, re.M).group(1) == markerpose.__version__


def test_a_tool_file_round_trips(tmp_path):
    tool = Marker(c1=(30.0, 0.0), c2=(-5.0, 45.0), outer_diameter=18.0, inner_diameter=7.0, margin=8.0, name="probe", tip=(10, -60, 0))
    path = tool.save(tmp_path / "probe.yaml")
    assert Marker.load(path) == tool and Marker.load(path).tip == (10.0, -60.0, 0.0)
    assert Marker.load(Marker().save(tmp_path / "marker.yaml")) == Marker()  # the paper's marker, named "marker"
    import yaml

    assert yaml.safe_load(path.read_text())["rings"] == [[0.0, 0.0], [30.0, 0.0], [-5.0, 45.0]]


@pytest.mark.parametrize(
    "text, says",
    [
        ("name: a\nrings: [[0, 0], [25, 0], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\n", r"missing \['plate_margin'\]"),
        (
            "name: a\nrings: [[0, 0], [25, 0], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\ncolor: red\n",
            r"unknown \['color'\]",
        ),
        ("name: a\nrings: [[0, 0], [25, 0]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n", r"rings must be 3 x 2 numbers"),
        (
            "name: a\nrings: [[1, 0], [25, 0], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n",
            "c0 must be at the origin",
        ),
        (
            "name: a\nrings: [[0, 0], [25, 3], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n",
            r"c1 must lie on the \+x axis",
        ),
        (
            "name: a\nrings: [[0, 0], [25, 0], [0, -40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n",
            r"c2 must lie in the \+y",
        ),
        (
            "name: a\nrings: [[0, 0], [25, 0], [0, 40]]\nouter_diameter: .nan\ninner_diameter: 8\nplate_margin: 5\n",
            "outer_diameter must be a number",
        ),
        ("name: 2 b\nrings: [[0, 0], [25, 0], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n", "name must be"),
        ("name: a\nrings: [[0, 0], [15, 0], [0, 40]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 5\n", "rings overlap"),
        ("- just\n- a list\n", "a tool file maps the keys"),
        ("name: [unclosed\n", "not YAML"),
        ("[" * 20000 + "]" * 20000, "nested too deeply|not a tool file"),
    ],
)
def test_a_bad_tool_file_names_itself_and_the_fault(tmp_path, text, says):
    path = tmp_path / "tool.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: .*({says})"):
        Marker.load(path)


def test_a_missing_tool_file_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="cannot read the tool file"):
        Marker.load(tmp_path / "nope.yaml")
