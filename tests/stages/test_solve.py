"""The solve stage (markerpose.stages.solve): triangulation, perspective-bias correction, pose."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.geometry import nearest_rotation, rotation_angle
from markerpose.results import Detection
from markerpose.stages import solve
from markerpose.synth import look_at_pose, render_stereo

PAPER = {"pose": "paper", "bias_correction": False}


@pytest.mark.parametrize("seed, pose", [(0, ([0, 0, 400], 50, 30, 10)), (1, ([40, -30, 700], 35, 120, 80))])
def test_bias_correction_and_the_rigid_pose_beat_the_papers_construction_on_exact_ellipse_centres(rig, seed, pose):
    T = look_at_pose(*pose)
    f = render_stereo(rig, T, seed=seed)
    marker = mp.Marker()
    dets = [Detection(centers=v.outer_centers.copy()) for v in f.views]  # exact ellipse centres: only the bias is left
    ours = solve.solve(rig, marker, *dets, solve.default_conf)
    paper = solve.solve(rig, marker, *dets, PAPER)
    err = {name: np.linalg.norm(e.t - T[:3, 3]) for name, e in (("ours", ours), ("paper", paper))}
    assert err["ours"] < 0.002 and err["paper"] > 5 * err["ours"], err
    assert np.degrees(rotation_angle(ours.R, T[:3, :3])) < 0.002
    np.testing.assert_allclose(ours.R @ ours.R.T, np.eye(3), atol=1e-12)  # the rigid fit is a rotation
    assert ours.residual_px < 0.01 and ours.source == "detected"
    # With the correction the centres are where the rings' 3D centres project.
    np.testing.assert_allclose(ours.centers, np.stack([v.centers for v in f.views]), atol=0.002)
    assert np.abs(paper.R @ paper.R.T - np.eye(3)).max() > 1e-9  # the paper's R = [x y x×y] is not orthonormal
    assert rotation_angle(nearest_rotation(paper.R), T[:3, :3]) < np.radians(0.5)


def test_reprojection_rms_measures_pixels_off_the_pose(rig):
    T = look_at_pose([0, 0, 560], 20, 0, 0)
    f = render_stereo(rig, T, seed=2)
    marker = mp.Marker()
    centers = np.stack([v.centers for v in f.views])
    assert solve.reprojection_rms(rig, marker, T, centers) < 1e-6
    moved = centers.copy()
    moved[0, 0] += [3.0, 4.0]  # one centre 5 px off: RMS over six centres
    assert solve.reprojection_rms(rig, marker, T, moved) == pytest.approx(5 / np.sqrt(6), rel=1e-6)
