"""Hand-eye calibration: both setups against the truth, the CLI, bad input."""

import csv

import cv2
import numpy as np
import pytest
import yaml

from markerpose.cli import main
from markerpose.handeye import hand_eye, pair_by_time, simulated
from markerpose.video import CSV_HEADER, pose_row


def _scene(setup, n=20, seed=0, robot=(0.05, 0.01), tracker=(0.02, 0.005)):
    return simulated(setup, n, np.random.default_rng(seed), robot, tracker)


def _rot_deg(Ra, Rb):
    return np.degrees(np.linalg.norm(cv2.Rodrigues(Ra @ Rb.T)[0]))


@pytest.mark.parametrize("setup", ["eye-to-hand", "eye-in-hand"])
def test_both_setups_recover_the_truth(setup):
    X, Z, A, B = _scene(setup)
    for method, r in hand_eye(A, B, setup).items():
        assert _rot_deg(r.X[:3, :3], X[:3, :3]) < 0.05 and _rot_deg(r.Z[:3, :3], Z[:3, :3]) < 0.05, method
        assert np.linalg.norm(r.X[:3, 3] - X[:3, 3]) < 0.5 and np.linalg.norm(r.Z[:3, 3] - Z[:3, 3]) < 0.5, method
        assert r.summary()["translation_rms_mm"] < 0.5
    exact = hand_eye(*_scene(setup, robot=(0, 0), tracker=(0, 0))[2:], setup)["linear"]
    np.testing.assert_allclose(exact.X, _scene(setup)[0], atol=1e-6)


def test_bad_input():
    _, _, A, B = _scene("eye-to-hand")
    with pytest.raises(ValueError, match="at least 6"):
        hand_eye(A[:4], B[:4])
    with pytest.raises(ValueError, match="paired"):
        hand_eye(A, B[:-1])
    bad = A.copy()
    bad[3, :3, :3] *= 2
    with pytest.raises(ValueError, match="not a rotation"):
        hand_eye(bad, B)
    with pytest.raises(ValueError, match="setup"):
        hand_eye(A, B, "eye-on-hand")


def test_pairing_by_time():
    assert pair_by_time([0.0, 1.0, 2.0, 5.0], [0.005, 1.03, 2.001, 2.002], 0.02) == [(0, 0), (2, 2)]


class _E:
    def __init__(self, T):
        self.T, self.residual_px, self.cov = T, 0.1, None


def test_cli_handeye(tmp_path, capsys):
    X, Z, A, B = _scene("eye-to-hand", n=18, seed=3)
    with open(tmp_path / "robot.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp_s"] + [f"T{i}{j}" for i in range(4) for j in range(4)])
        for k, a in enumerate(A):
            w.writerow([f"{k * 2.0:.3f}", *(f"{v:.9g}" for v in a.ravel())])
    with open(tmp_path / "poses.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for k, b in enumerate(B):  # the tracker's clock 5 ms off; a frame without the marker between
            w.writerow(pose_row(2 * k, k * 2.0 + 0.005, _E(b)))
            w.writerow(pose_row(2 * k + 1, k * 2.0 + 1.0, None))
    out = tmp_path / "he.yaml"
    assert (
        main(
            [
                "handeye",
                "--robot",
                str(tmp_path / "robot.csv"),
                "--poses",
                str(tmp_path / "poses.csv"),
                "--setup",
                "eye-to-hand",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    r = yaml.safe_load(out.read_text())
    assert r["pairs"] == 18 and {"T_base_camera", "T_gripper_marker"} <= set(r)
    assert np.linalg.norm(np.array(r["T_base_camera"])[:3, 3] - Z[:3, 3]) < 0.5
    assert "| refined |" in capsys.readouterr().out
    # Clocks that do not meet: a clear error, nothing written.
    out2 = tmp_path / "none.yaml"
    args = ["handeye", "--robot", str(tmp_path / "robot.csv"), "--poses", str(tmp_path / "poses.csv"), "--setup", "eye-in-hand"]
    assert main(args + ["--tolerance", "0.001", "--out", str(out2)]) == 2
    assert "same clock" in capsys.readouterr().err and not out2.exists()
