"""Stereo calibration with an asymmetric circle grid (markerpose.calibration)."""

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import markerpose as mp
from markerpose import cli
from markerpose.calibration import CircleGrid, calibrate, find_grid
from markerpose.experiments.calibration_check import check, rendered_pairs
from markerpose.synth import Imaging


@pytest.fixture(scope="module")
def rendered():
    rig = mp.StereoRig.default()
    grid = CircleGrid(4, 11, 12.0)
    pairs, poses = rendered_pairs(rig, grid, n=8, seed=3, imaging=Imaging(supersample=4))
    return rig, grid, pairs, poses


def test_grid_layout_is_opencvs():
    g = CircleGrid(4, 11, 10.0)
    p = g.points3d
    assert p.shape == (44, 3) and np.allclose(p[:5, :2], [[0, 0], [20, 0], [40, 0], [60, 0], [10, 10]])
    assert g.radius == 2.5
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [-100.0, 0.0]])
    r = g.reflectance(xy)
    assert r[0] < 0.1 and r[1] > 0.5 and r[2] < 0.1 and np.isnan(r[3])
    with pytest.raises(ValueError, match="overlap"):
        CircleGrid(4, 11, 10.0, diameter=15.0)


def test_grid_found_where_it_was_rendered(rendered):
    rig, grid, pairs, poses = rendered
    img, T = pairs[0][0], poses[0]
    found = find_grid(img, grid)
    truth = rig.left.project(grid.points3d @ T[:3, :3].T + T[:3, 3])
    # Either end of the grid may come first (its two ends look alike): compare as sets.
    d = np.linalg.norm(found[:, None] - truth[None], axis=2).min(1)
    assert d.max() < 0.15  # px


def test_calibration_recovers_the_rig(rendered):
    """The issue's figures on a small set: focal lengths within 0.2 %, baseline within
    0.1 mm, RMS <= 0.15 px."""
    rig, grid, pairs, _ = rendered
    cal = calibrate(pairs, grid)
    c = check(rig, cal)
    assert max(c["f_left_rel_error"], c["f_right_rel_error"]) < 0.002
    assert c["baseline_mm_error"] < 0.1 and c["R_deg_error"] < 0.05
    assert max(cal.rms_left_px, cal.rms_right_px, cal.rms_stereo_px) <= 0.15
    # The calibrated volume: the box the grid's points filled, in the left camera's frame.
    lo, hi = cal.rig.volume
    assert np.all(hi - lo > 10) and 100 < lo[2] < hi[2] < 3000
    assert cal.rig.in_volume((lo + hi) / 2) and not cal.rig.in_volume(hi + 0.5 * (hi - lo))


def test_a_view_found_from_the_other_end_is_put_in_step(rendered):
    """The grid looks alike from both ends: a right view whose rows came in reverse is
    reordered to match the left view (else the stereo calibration pairs wrong circles)."""
    from markerpose.calibration import _consistent

    _, grid, pairs, _ = rendered
    a, b = find_grid(pairs[0][0], grid), find_grid(pairs[0][1], grid)
    reversed_rows = b.reshape(grid.rows, grid.cols, 2)[::-1].reshape(-1, 2)
    np.testing.assert_array_equal(_consistent(a, reversed_rows, grid), _consistent(a, b, grid))
    np.testing.assert_array_equal(_consistent(a, b, grid), b)


def test_too_few_pairs_is_a_clear_error(rendered):
    rig, grid, pairs, _ = rendered
    blank = np.full_like(pairs[0][0], 128)
    with pytest.raises(ValueError, match=r"found in both views of only 2 pairs; at least 6 are needed \(rejected: \[2, 3\]\)"):
        calibrate([pairs[0], pairs[1], (blank, pairs[2][1]), (pairs[3][0], blank)], grid)


def test_cli_pattern_and_calibrate(tmp_path, capsys, rendered):
    import cv2

    rig, grid, pairs, _ = rendered
    assert cli.main(["pattern", "--out", str(tmp_path / "g.svg"), "--grid", "4x11", "--spacing", "12"]) == 0
    root = ET.parse(tmp_path / "g.svg").getroot()
    circles = [e for e in root.iter() if e.tag.endswith("circle")]
    assert len(circles) == 44 and all(float(c.get("r")) == pytest.approx(3.0) for c in circles)
    xs = sorted({round(float(c.get("cx")), 3) for c in circles})
    assert np.allclose(np.diff(xs), 12.0)  # alternate rows offset by one spacing
    assert cli.main(["pattern", "--out", str(tmp_path / "g.pdf"), "--spacing", "40"]) == 2  # does not fit on A4
    assert "does not fit" in capsys.readouterr().err
    for side in "LR":
        (tmp_path / side).mkdir()
    for k, (a, b) in enumerate(pairs):
        cv2.imwrite(str(tmp_path / "L" / f"{k:02d}.png"), a)
        cv2.imwrite(str(tmp_path / "R" / f"{k:02d}.png"), b)
    cv2.imwrite(str(tmp_path / "L" / "99.png"), np.full_like(pairs[0][0], 128))  # no grid on the left
    cv2.imwrite(str(tmp_path / "R" / "99.png"), pairs[0][1])
    out = tmp_path / "rig.yaml"
    assert (
        cli.main(
            [
                "calibrate",
                str(tmp_path / "L"),
                str(tmp_path / "R"),
                "--grid",
                "4x11",
                "--spacing",
                "12",
                "--out",
                str(out),
                "--coverage",
                str(tmp_path / "cov.png"),
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert re.search(r"8 pairs used, 1 rejected; RMS reprojection error left 0\.0\d\d px", captured.out)
    assert "rejected 99.png: the 4x11 grid was not found in the left view" in captured.err
    loaded = mp.StereoRig.load(out)
    assert abs(loaded.baseline - rig.baseline) < 0.1 and (tmp_path / "cov.png").stat().st_size > 0
    # Every other pair: 00, 02, 04, 06 and the rejected 99.
    assert cli.main(["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "--spacing", "12", "--every", "2", "--quiet"]) == 2
    assert "found in both views of only 4 pairs" in capsys.readouterr().err
    assert cli.main(["calibrate", str(tmp_path / "L"), str(tmp_path / "R"), "--grid", "4by11"]) == 2
    assert "--grid must be COLSxROWS" in capsys.readouterr().err
