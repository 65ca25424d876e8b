"""Unsynchronised cameras: the right view moved to the left view's time, the delay measured (markerpose.sync)."""

import csv
import re

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose import cli
from markerpose.experiments.sync import pose, render
from markerpose.results import Detection
from markerpose.sync import check_times, estimate_delay, motion, right_at_left_time
from markerpose.synth import clutter_background

DELAY = 0.025  # s: the right view's exposure after the left's
FPS = 30.0


def test_right_centres_are_read_off_their_path_at_the_left_time():
    """A parabola through three positions is exact for a steady acceleration; a line
    through two for a steady velocity."""

    def path(t):  # px: each of three centres with its own velocity and acceleration
        return (
            np.array([[100, 200], [300, 250], [150, 400]])
            + np.array([[40, -20], [10, 5], [-30, 60]]) * t
            + np.array([[8.0], [-5.0], [3.0]]) * t**2
        )

    t_prev, t_right, t_left = [0.0, 1 / 30], 2 / 30, 2 / 30 - 0.03
    m = motion([path(t) for t in t_prev], t_prev, (t_left, t_right))
    det = Detection(path(t_right), ellipses=[((x, y), (20, 10), 0.0) for x, y in path(t_right)])
    moved = right_at_left_time(det, m)
    np.testing.assert_allclose(moved.centers, path(t_left), atol=1e-9)
    np.testing.assert_allclose([e[0] for e in moved.ellipses], path(t_left), atol=1e-9)  # the outlines move with them
    line = motion([path(t_prev[1])], t_prev[1:], (t_left, t_right))
    assert len(line.right_prev) == 1  # one pair before: a line, first-order
    assert motion([], [], (0.0, 0.01)) is None and motion([path(0)], [0.0], None) is None
    for bad in ((0.0,), (0.0, float("nan")), "ab", None):
        with pytest.raises(ValueError, match="times"):
            check_times(bad)


def test_estimate_delay_from_projected_centres():
    """Centres projected from a moving marker (no images), the right view 25 ms late, with
    0.02 px of noise: the delay within 0.3 ms, its sd small and honest. (Projected centres
    are not ellipse centres: solved without the perspective-bias correction.)"""
    rig, marker = mp.StereoRig.default(), mp.Marker()
    rng = np.random.default_rng(3)
    times = np.arange(40) / FPS
    lefts, rights = [], []
    for t in times:
        X = lambda s: marker.points3d @ pose(s)[:3, :3].T + pose(s)[:3, 3]  # noqa: E731
        lefts.append(rig.project(X(t))[0] + rng.normal(0, 0.02, (3, 2)))
        rights.append(rig.project(X(t + DELAY))[1] + rng.normal(0, 0.02, (3, 2)))
    conf = {"bias_correction": False}
    found = estimate_delay(rig, marker, times, lefts, rights, solve_conf=conf)
    assert abs(found["delay_s"] - DELAY) < 3e-4 and found["sd_s"] < 3e-4
    assert abs(found["delay_s"] - DELAY) < 4 * found["sd_s"] + 2e-4
    assert found["residual_px"] < found["residual_px_at_zero"] / 5
    lefts[5] = np.full((3, 2), np.nan)  # a pair without the marker is left out
    assert estimate_delay(rig, marker, times, lefts, rights, solve_conf=conf)["pairs"] == 39
    with pytest.raises(ValueError, match="moving in only"):
        estimate_delay(rig, marker, times[:3], lefts[:3], rights[:3])


@pytest.fixture(scope="module")
def late(tmp_path_factory):
    """Ten rendered pairs at 30 frames/s of the marker moving ~60 mm/s, the right view
    exposed 25 ms after the left, as PNG folders."""
    rig, marker = mp.StereoRig.default(), mp.Marker()
    rng = np.random.default_rng(11)
    bgs = tuple(clutter_background(cam.image_size, rng) for cam in rig.cameras)
    frames = render(rig, marker, {"frames": 10, "fps": FPS, "exposure_ms": 4.0}, DELAY, rng, False, bgs)
    root = tmp_path_factory.mktemp("late")
    for side in "LR":
        (root / side).mkdir()
    for k, (_, images) in enumerate(frames):
        for side, img in zip("LR", images):
            cv2.imwrite(str(root / side / f"{k:03d}.png"), img)
    return root, frames


def test_track_with_times_gives_the_pose_at_the_left_time(late):
    """Compensated from the third pair on (two pairs before it): within 0.02 mm of the pose
    at the left view's time; taken as simultaneous, the same pairs are refused or millimetres off."""
    _, frames = late
    tracker = mp.MarkerPose(mp.StereoRig.default())
    with_times, without = [], []
    for t, (left, right) in frames:
        est = tracker.track(left, right, times=(t, t + DELAY))
        with_times.append(None if est is None else float(np.linalg.norm(est.t - pose(t)[:3, 3])))
    tracker.reset()
    for t, (left, right) in frames:
        est = tracker.track(left, right)
        without.append(None if est is None else float(np.linalg.norm(est.t - pose(t)[:3, 3])))
    assert all(e is not None and e < 0.02 for e in with_times[3:]), with_times
    assert all(e is None or e > 1.0 for e in without[3:]), without
    tracker.reset()  # times=None: as before (the first pairs, found cold, are the same poses)
    first = tracker.track(*frames[0][1])
    again = mp.MarkerPose(mp.StereoRig.default()).track(*frames[0][1], times=(0.0, DELAY))
    assert (first is None) == (again is None) and (first is None or np.allclose(first.T, again.T))


def test_cli_sync_then_track_with_the_delay(late, tmp_path, capsys):
    root, frames = late
    args = ["sync", str(root / "L"), str(root / "R"), "--fps", "30", "--quiet", "--json", str(tmp_path / "s.json")]
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    found = float(re.search(r"exposes ([+-][\d.]+) ± ([\d.]+) ms", out).group(1))
    assert abs(found - 1000 * DELAY) < 0.2, out  # the target: 2 ms
    assert "not synchronised enough for 0.1 mm; track with: markerpose track ... --right-delay" in out
    csv_out = tmp_path / "p.csv"
    track = ["track", str(root / "L"), str(root / "R"), "--fps", "30", "--right-delay", f"{found:.1f}", "--out", str(csv_out), "--quiet"]
    assert cli.main(track) == 0
    rows = list(csv.DictReader(csv_out.open()))
    assert all(r["valid"] == "1" for r in rows[3:])
    errors = [np.linalg.norm([float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] - pose(t)[:3, 3]) for r, (t, _) in zip(rows[3:], frames[3:])]
    assert max(errors) < 0.02, errors
    assert "rig check" not in capsys.readouterr().err  # a pair not compensated (the first found) is not taken for a moved camera
    assert cli.main(["track", str(root / "L"), str(root / "R"), "--right-delay", "5000", "--out", str(csv_out), "--quiet"]) == 2
    assert "--right-delay is in milliseconds" in capsys.readouterr().err
