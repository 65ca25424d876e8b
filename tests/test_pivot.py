"""Pivot calibration: the math against the truth, its verdicts and refusals, the CLI."""

import csv

import cv2
import numpy as np
import pytest
import yaml

import markerpose as mp
from markerpose.cli import main
from markerpose.geometry import pose_rigid
from markerpose.pivot import pivot_calibration, pivoting_poses
from markerpose.synth import look_at_pose
from markerpose.video import CSV_HEADER, TIP_COLUMNS, TOOLS_CSV_HEADER, pose_row, read_track_csv

TIP = np.array([12.5, -110.0, -4.0])
PIVOT = np.array([10.0, 100.0, 560.0])
R0 = look_at_pose(PIVOT, 0, 0, 0)[:3, :3]


def _noisy(T, noise, rng, marker=mp.Marker()):
    X = marker.points3d @ T[:3, :3].T + T[:3, 3]
    return pose_rigid(X + rng.normal(0, noise, X.shape), marker.points3d)


def test_exact_poses_give_the_tip_and_pivot():
    T = pivoting_poses(TIP, PIVOT, 40, 30, np.random.default_rng(0), R0)
    r = pivot_calibration(T)
    np.testing.assert_allclose(r.tip_mm, TIP, atol=1e-8)
    np.testing.assert_allclose(r.pivot_mm, PIVOT, atol=1e-8)
    assert r.rmse_mm < 1e-8 and r.ok and r.inliers.all()


def test_noise_and_slipped_poses():
    rng = np.random.default_rng(1)
    T = np.stack([_noisy(Ti, 0.01, rng) for Ti in pivoting_poses(TIP, PIVOT, 200, 30, rng, R0)])
    slipped = np.arange(0, 200, 20)  # 5 %: the tip moved 3-8 mm
    T[slipped, :3, 3] += rng.uniform(3, 8, (len(slipped), 1)) * np.array([0.6, 0.8, 0.0])
    r = pivot_calibration(T)
    assert not r.inliers[slipped].any() and r.inliers.sum() >= 180
    assert np.linalg.norm(r.tip_mm - TIP) < 0.05 and np.linalg.norm(r.pivot_mm - PIVOT) < 0.05
    # The reported sd is the size of the error (within a factor 3 for one trial).
    assert np.linalg.norm(r.tip_mm - TIP) < 3 * r.tip_sd_mm + 0.005
    assert r.ok and 0.005 < r.rmse_mm < 0.2


def test_verdicts():
    rng = np.random.default_rng(2)
    few = pivot_calibration(pivoting_poses(TIP, PIVOT, 10, 30, rng, R0))
    assert few.verdict.startswith("too few poses")
    # Turning about one axis only leaves the tip along it undetermined.
    T = []
    for a in np.linspace(-0.5, 0.5, 40):
        R = cv2.Rodrigues(np.array([a, 0.0, 0.0]))[0] @ R0
        Ti = np.eye(4)
        Ti[:3, :3], Ti[:3, 3] = R, PIVOT - R @ TIP
        T.append(Ti)
    flat = pivot_calibration(np.stack(T))
    assert flat.verdict.startswith("too little rotation")


def test_bad_input():
    T = pivoting_poses(TIP, PIVOT, 30, 30, np.random.default_rng(3), R0)
    with pytest.raises(ValueError, match="2 pose"):
        pivot_calibration(T[:2])
    bad = T.copy()
    bad[4, :3, :3] *= 1.1  # not a rotation
    with pytest.raises(ValueError, match="not a rotation"):
        pivot_calibration(bad)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        pivot_calibration(T[:, :3])
    nan = T.copy()
    nan[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        pivot_calibration(nan)


def _write(path, rows, header):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def test_cli_pivot_writes_tip_and_tool(tmp_path, capsys):
    rng = np.random.default_rng(4)
    T = np.stack([_noisy(Ti, 0.01, rng) for Ti in pivoting_poses(TIP, PIVOT, 60, 30, rng, R0)])

    class E:  # what pose_row reads of an Estimate
        def __init__(self, T):
            self.T, self.residual_px, self.cov = T, 0.1, None

    rows = [pose_row(k, k / 30, E(Ti) if k % 7 else None) for k, Ti in enumerate(T)]
    _write(tmp_path / "poses.csv", rows, CSV_HEADER)
    tool = mp.Marker().save(tmp_path / "pointer.yaml")
    assert main(["pivot", str(tmp_path / "poses.csv"), "--out", str(tmp_path / "tip.yaml"), "--write-tool", str(tool)]) == 0
    out = yaml.safe_load((tmp_path / "tip.yaml").read_text())
    assert {"tip_mm", "pivot_mm", "rmse_mm"} <= set(out) and out["verdict"] == "ok"
    assert np.linalg.norm(np.array(out["tip_mm"]) - TIP) < 0.1
    assert np.linalg.norm(np.array(mp.Marker.load(tool).tip) - TIP) < 0.1
    assert "verdict: ok" in capsys.readouterr().out


def test_cli_pivot_refuses_unclear_input(tmp_path, capsys):
    T = pivoting_poses(TIP, PIVOT, 30, 30, np.random.default_rng(5), R0)

    class E:
        def __init__(self, T):
            self.T, self.residual_px, self.cov = T, 0.1, None

    long = []
    for k, Ti in enumerate(T):
        for name in ("pointer", "reference"):
            long.append(pose_row(k, k / 30, E(Ti))[:3] + [name, "camera"] + pose_row(k, k / 30, E(Ti))[3:])
    _write(tmp_path / "tools.csv", long, TOOLS_CSV_HEADER)
    assert main(["pivot", str(tmp_path / "tools.csv"), "--out", str(tmp_path / "tip.yaml")]) == 2
    assert "pointer, reference" in capsys.readouterr().err
    assert main(["pivot", str(tmp_path / "tools.csv"), "--tool", "pointer", "--out", str(tmp_path / "tip.yaml")]) == 0
    _write(tmp_path / "cut.csv", [pose_row(0, 0.0, E(T[0]))[:10]], CSV_HEADER)
    assert main(["pivot", str(tmp_path / "cut.csv")]) == 2
    assert "row 2" in capsys.readouterr().err
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a markerpose track CSV"):
        read_track_csv(tmp_path / "other.csv")


def test_tip_columns_follow_the_pose():
    T = look_at_pose(np.array([0.0, 0.0, 500.0]), 20, 30, 40)

    class E:
        def __init__(self):
            self.T, self.residual_px, self.cov = T, 0.1, np.diag([1e-4] * 3 + [1e-8] * 3)

    row = pose_row(3, 0.1, E(), tip=TIP)
    assert len(row) == len(CSV_HEADER) + len(TIP_COLUMNS)
    np.testing.assert_allclose([float(v) for v in row[-4:-1]], T[:3, :3] @ TIP + T[:3, 3], atol=1e-6)
    assert float(row[-1]) > np.sqrt(3e-4)  # the tip's sd: the origin's and the rotation's lever
    assert pose_row(3, 0.1, None, tip=TIP)[-4:] == [""] * 4


def test_pose_rows_that_are_not_rigid_are_refused(tmp_path):
    T = pivoting_poses(TIP, PIVOT, 5, 30, np.random.default_rng(6), R0)

    class E:
        def __init__(self, T):
            self.T, self.residual_px, self.cov = T, 0.1, None

    bad = T[3].copy()
    bad[:3, :3] *= 1.5
    rows = [pose_row(k, k / 30, E(Ti)) for k, Ti in enumerate([*T[:3], bad])]
    _write(tmp_path / "p.csv", rows, CSV_HEADER)
    with pytest.raises(ValueError, match="row 5: T00 … T33 is not a rigid transform"):
        read_track_csv(tmp_path / "p.csv")


def test_ultrasound_pixel_sizes_are_bounded(capsys):
    for bad in ("1e300,1e300", "0,0.1", "nan,0.1"):
        with pytest.raises(SystemExit):
            main(["ultrasound", "calibrate", "--poses", "p.csv", "--images", "us", "--spacing", bad, "--out", "probe.yaml"])
        err = capsys.readouterr().err
        assert "pixel size" in err or "finite" in err, err
