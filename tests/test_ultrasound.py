"""Freehand ultrasound: simulator, segmentation, calibration, reconstruction, files, CLI."""

import json

import numpy as np
import pytest

from markerpose import cli, formats
from markerpose.experiments.ultrasound import (
    ProbeSetup,
    Transducer,
    crosswire_phantom,
    simulate_bmode,
    sweep_poses,
    tube_phantom,
)
from markerpose.geometry import rotation_about_axis
from markerpose.ultrasound import (
    ProbeCalibration,
    calibrate_probe,
    compound,
    fit_cylinder,
    interpolate_poses,
    point_target,
    sweep_normal,
    sweep_points,
    tracker_points,
)
from markerpose.ultrasound.probe import invert, rigid

D_TRUE = 15.82


def _random_rigid(rng, scale=50.0):
    R = rotation_about_axis(rng.normal(size=3), rng.uniform(0, np.pi))
    return rigid(R, rng.normal(size=3) * scale)


# --- simulator --------------------------------------------------------------------------
def test_bmode_tube_echo_at_the_interface():
    setup = ProbeSetup()
    tr = setup.transducer
    T = setup.nominal_image_pose()
    im = simulate_bmode(tube_phantom(), T, tr, rng=1)
    assert im.shape == (tr.size[1], tr.size[0]) and im.dtype == np.uint8
    # The column through the tube's axis: the brightest echo near the top of the tube lies
    # at the outer surface's depth.
    u = round(tr.size[0] / 2)
    col = im[:, u - 1 : u + 2].astype(float).mean(1)
    top_px = (setup.depth_mm - D_TRUE / 2) / tr.spacing[1]
    win = slice(int(top_px) - 8, int(top_px) + 9)
    peak = win.start + int(np.argmax(col[win]))
    assert abs(peak - top_px) <= 1.5
    # Water is dark; the echo is far above it; the tube's lumen is water too.
    assert col[peak] > 150 and np.median(im[:20]) < 60
    centre_px = int(setup.depth_mm / tr.spacing[1])
    assert np.median(im[centre_px - 5 : centre_px + 5, u - 5 : u + 5]) < 80


def test_bmode_is_seeded_and_shadows_below_air():
    tr = Transducer()
    T = ProbeSetup().nominal_image_pose()
    a = simulate_bmode(tube_phantom(), T, tr, rng=5)
    b = simulate_bmode(tube_phantom(), T, tr, rng=5)
    c = simulate_bmode(tube_phantom(), T, tr, rng=6)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    # Below the trough's outer wall there is air: nothing comes back but noise.
    deep = a[-8:]
    assert np.median(deep) < 60


def test_bmode_speckle_is_fully_developed():
    """A homogeneous scattering medium gives Rayleigh speckle: the envelope's mean over its
    standard deviation is 1.91."""
    from markerpose.experiments.ultrasound.bmode import Medium, Phantom

    tr = Transducer()
    im = simulate_bmode(Phantom(Medium("tissue", 0.05, 0.0)), ProbeSetup().nominal_image_pose(), tr, rng=3)
    env = 10 ** (im[60:200, 40:220].astype(float) / 255 * tr.dynamic_range_db / 20)
    assert 1.7 < env.mean() / env.std() < 2.2


def test_point_target_finds_the_wire_crossing():
    setup = ProbeSetup()
    tr = setup.transducer
    rng = np.random.default_rng(0)
    from markerpose.experiments.ultrasound import calibration_poses

    for T in calibration_poses(setup, rng, 5, elevation_sigma_mm=0.0):
        uv = point_target(simulate_bmode(crosswire_phantom(), T, tr, rng))
        truth = invert(T)[:3, 3][:2] / np.asarray(tr.spacing)
        assert uv is not None and np.linalg.norm(uv - truth) < 0.5  # px (0.15 mm)
    assert point_target(np.full((50, 60), 20, np.uint8)) is None


# --- reconstruction pieces ---------------------------------------------------------------
def test_fit_cylinder_recovers_an_exact_cylinder_with_outliers():
    rng = np.random.default_rng(3)
    d = np.array([0.3, -0.2, 0.93])
    d /= np.linalg.norm(d)
    e1 = np.cross(d, [1, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    p0 = np.array([10.0, -20.0, 500.0])
    a = rng.uniform(-0.7, 0.7, 2000) + np.where(rng.random(2000) < 0.5, 0, np.pi)  # top and bottom arcs
    s = rng.uniform(-25, 25, 2000)
    P = p0 + s[:, None] * d + 7.91 * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    P[:100] += rng.normal(0, 3, (100, 3))  # gross outliers
    fit = fit_cylinder(P, direction_hint=d + 0.05)
    assert abs(fit.radius - 7.91) < 1e-6
    assert abs(abs(fit.direction @ d) - 1) < 1e-10
    assert np.linalg.norm(np.cross(fit.point - p0, d)) < 1e-6
    assert fit.inliers[100:].all() and fit.inliers[:100].mean() < 0.2
    with pytest.raises(ValueError):
        fit_cylinder(P[:5])


def test_tube_diameter_from_true_poses():
    """Simulation → segmentation from one seed → 3D → cylinder: the floor the pose sources
    are compared against."""
    setup = ProbeSetup()
    tr = setup.transducer
    rng = np.random.default_rng(11)
    _, sweep = sweep_poses(setup, rng, n_frames=24, length_mm=20.0)
    images = [simulate_bmode(tube_phantom(), T, tr, rng) for T in sweep]
    seed = invert(sweep[0])[:3, 3][:2] / np.asarray(tr.spacing) + [4.0, -3.0]
    pts = sweep_points(images, seed, tr.spacing)
    assert all(len(p) > 20 for p in pts)
    calib = ProbeCalibration(setup.T_marker_image(), tr.spacing, tr.size)
    poses = [setup.marker_pose(T) for T in sweep]
    X, _ = tracker_points(pts, poses, calib)
    fit = fit_cylinder(X, sweep_normal(poses, calib))
    assert abs(fit.diameter - D_TRUE) < 0.05
    assert fit.rms < 0.05


def test_calibrate_probe_exact_and_noisy():
    rng = np.random.default_rng(2)
    T_mi = _random_rigid(rng, 60)
    P = np.array([5.0, -3.0, 550.0])
    spacing = (0.15, 0.12)
    poses, uvs = [], []
    for _ in range(20):
        uv = rng.uniform([30, 40], [220, 300])
        R = rotation_about_axis(rng.normal(size=3), rng.uniform(0, 0.6))
        # Choose the marker pose that puts the pixel exactly on P.
        T_li = rigid(R, [0, 0, 0])
        p_img = np.array([uv[0] * spacing[0], uv[1] * spacing[1], 0.0])
        T_li[:3, 3] = P - R @ p_img
        poses.append(T_li @ invert(T_mi))
        uvs.append(uv)
    calib, P_fit, _ = calibrate_probe(poses, uvs, spacing, (256, 334))
    assert np.abs(calib.T_marker_image - T_mi).max() < 1e-6 and np.linalg.norm(P_fit - P) < 1e-6
    assert calib.rms_mm < 1e-6 and calib.size == (256, 334)
    noisy = [uv + rng.normal(0, 0.5, 2) for uv in uvs]
    calib2, _, err2 = calibrate_probe(poses, noisy, spacing)
    assert 0.01 < calib2.rms_mm < 0.2 and len(err2) == 20
    with pytest.raises(ValueError, match="at least 6"):
        calibrate_probe(poses[:5], uvs[:5], spacing)


def test_interpolate_poses_midpoint_gaps_and_span():
    rng = np.random.default_rng(4)
    A, B = _random_rigid(rng), _random_rigid(rng)
    B[:3, :3] = A[:3, :3] @ rotation_about_axis([0, 0, 1], 0.2)
    out = interpolate_poses([0.05, 0.0, 0.1, -0.01, 0.11], [0.0, 0.1], [A, B])
    mid = out[0]
    assert np.allclose(mid[:3, 3], (A[:3, 3] + B[:3, 3]) / 2)
    assert np.allclose(mid[:3, :3], A[:3, :3] @ rotation_about_axis([0, 0, 1], 0.1))
    assert np.allclose(out[1], A) and np.allclose(out[2], B)
    assert out[3] is None and out[4] is None
    # A lost marker: no pose across a gap longer than max_gap_s.
    out = interpolate_poses([0.15, 0.45], [0.0, 0.1, 0.2, 0.3, 0.4, 0.5], [A, A, None, None, B, B], max_gap_s=0.15)
    assert out[0] is None and out[1] is not None


def test_compound_puts_each_pixel_where_its_pose_says():
    rng = np.random.default_rng(5)
    calib = ProbeCalibration(_random_rigid(rng, 30), (0.2, 0.2), (40, 30))
    poses, images = [], []
    for k in range(12):
        T = _random_rigid(np.random.default_rng(9), 10)
        T[:3, 3] += T[:3, :3] @ calib.T_marker_image[:3, :3] @ [0, 0, 0.5 * k]  # parallel slices 0.5 mm apart
        poses.append(T)
        images.append(np.full((30, 40), 10 * k + 5, np.uint8))
    vol = compound(images, poses, calib, voxel_mm=0.25, fill_iterations=0)
    for k in (0, 5, 11):
        X, _ = tracker_points([np.array([[20.0, 15.0]])], [poses[k]], calib)
        ijk = np.rint(np.linalg.solve(vol.directions, (X[0] - vol.origin))).astype(int)
        assert vol.data[tuple(ijk)] == 10 * k + 5
    with pytest.raises(ValueError):
        compound(images, [None] * 12, calib)


# --- files -------------------------------------------------------------------------------
def test_sequence_volume_and_cloud_round_trips(tmp_path):
    rng = np.random.default_rng(6)
    calib = ProbeCalibration(_random_rigid(rng, 30), (0.15, 0.12), (20, 16))
    frames = [rng.integers(0, 256, (16, 20), dtype=np.uint8) for _ in range(4)]
    poses = [_random_rigid(rng), None, _random_rigid(rng), _random_rigid(rng)]
    times = [0.0, 0.0667, 0.1333, 0.2]
    with pytest.raises(ValueError, match="igs.nrrd"):
        formats.write_sequence(tmp_path / "s.seq.nrrd", frames, times, poses, calib.image_to_probe)
    formats.write_sequence(tmp_path / "s.igs.nrrd", frames, times, poses, calib.image_to_probe)
    seq = formats.read_sequence(tmp_path / "s.igs.nrrd")
    assert np.array_equal(seq["images"], np.array(frames))
    assert np.allclose(seq["timestamps"], times)
    assert seq["probe_to_tracker"][1] is None
    for a, b in zip(seq["probe_to_tracker"], poses):
        assert (a is None) == (b is None) and (a is None or np.allclose(a, b, atol=1e-6))
    # The spacing travels inside ImageToProbe, as PLUS expects.
    i2p = seq["image_to_probe"][0]
    assert np.allclose(np.linalg.norm(i2p[:3, :3], axis=0), [0.15, 0.12, 1.0], atol=1e-8)
    assert np.allclose(i2p, calib.image_to_probe, atol=1e-8)

    poses = [_random_rigid(np.random.default_rng(9), 10) for _ in range(3)]
    vol = compound(frames[:3], poses, calib, voxel_mm=0.2)
    formats.write_volume(tmp_path / "v.nrrd", vol.data, vol.origin, vol.directions)
    data, origin, directions = formats.read_volume(tmp_path / "v.nrrd")
    assert np.array_equal(data, vol.data) and np.allclose(origin, vol.origin) and np.allclose(directions, vol.directions)
    assert np.allclose(np.linalg.norm(directions, axis=0), 0.2)

    P = rng.normal(size=(50, 3)) * 100
    formats.write_ply(tmp_path / "p.ply", P, np.arange(50), np.arange(50) % 3 > 0)
    cloud = formats.read_ply(tmp_path / "p.ply")
    assert np.allclose(np.column_stack([cloud["x"], cloud["y"], cloud["z"]]), P, atol=1e-4)
    assert np.array_equal(cloud["frame"], np.arange(50)) and np.array_equal(cloud["inlier"], np.arange(50) % 3 > 0)


# The fields vtkIGSIONrrdSequenceIO (SlicerIGSIO's reader) reads: the per-frame prefix, the
# image status it looks for, and what its writer always writes for a 2D image time series.
IGSIO_FRAME_PREFIX, IGSIO_IMAGE_STATUS = "Seq_Frame", "Status"
IGSIO_HEADER = ("dimension", "type", "sizes", "kinds", "encoding", "space dimension", "space directions", "space origin")


def test_sequence_file_as_igsio_and_independent_readers_take_it(tmp_path):
    """The sweep file read as SlicerIGSIO reads it (header fields by IGSIO's names, per-frame
    fields parsed from the raw text) and by pynrrd and SimpleITK (spacing, origin, size)."""
    import nrrd

    rng = np.random.default_rng(16)
    calib = ProbeCalibration(_random_rigid(rng, 30), (0.15, 0.12), (20, 16))
    frames = [rng.integers(0, 256, (16, 20), dtype=np.uint8) for _ in range(3)]
    poses = [_random_rigid(rng), None, _random_rigid(rng)]
    path = formats.write_sequence(tmp_path / "sweep.igs.nrrd", frames, [0.0, 0.05, 0.1], poses, calib.image_to_probe)
    text = path.read_bytes().split(b"\n\n", 1)[0].decode("ascii")
    fields = dict(line.split(": ", 1) if ": " in line else line.split(":=", 1) for line in text.splitlines()[1:] if line and line[0] != "#")
    assert all(f in fields for f in IGSIO_HEADER), sorted(fields)
    assert fields["sizes"].split() == ["20", "16", "3"] and fields["kinds"].split() == ["domain", "domain", "list"]
    assert fields["space dimension"] == "2" and fields["space directions"].split()[-1] == "none"
    frame = {k[len(IGSIO_FRAME_PREFIX) + 5 :]: v for k, v in fields.items() if k.startswith(IGSIO_FRAME_PREFIX + "0001_")}
    assert frame[IGSIO_IMAGE_STATUS] == "OK" and frame["ProbeToTrackerTransformStatus"] == "INVALID"
    T = np.array([float(v) for v in fields[IGSIO_FRAME_PREFIX + "0000_ProbeToTrackerTransform"].split()]).reshape(4, 4)
    np.testing.assert_allclose(T, poses[0], atol=1e-6)
    data, header = nrrd.read(str(path), index_order="C")
    assert data.shape == (3, 16, 20) and np.array_equal(data[2], frames[2])
    sitk = pytest.importorskip("SimpleITK")
    img = sitk.ReadImage(str(path))
    assert img.GetSize()[:2] == (20, 16) and img.GetSpacing()[:2] == (1.0, 1.0) and img.GetOrigin()[:2] == (0.0, 0.0)


def test_volume_file_is_ras_for_slicer_and_sitk(tmp_path):
    """volume.nrrd says its space (RAS, as OpenIGTLink transforms): pynrrd reads it back, and
    SimpleITK (which works in LPS) reports the origin and directions mirrored in x and y, as
    it must for a RAS file, with the right spacing."""
    import nrrd

    rng = np.random.default_rng(17)
    data = rng.integers(0, 255, (6, 5, 4), dtype=np.uint8)
    R = _random_rigid(rng)[:3, :3]
    directions, origin = R @ np.diag([0.2, 0.3, 0.4]), np.array([10.0, -20.0, 30.0])
    path = formats.write_volume(tmp_path / "v.nrrd", data, origin, directions)
    _, header = nrrd.read(str(path))
    assert header["space"] == "right-anterior-superior"
    sitk = pytest.importorskip("SimpleITK")
    img = sitk.ReadImage(str(path))
    flip = np.diag([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(img.GetSpacing(), [0.2, 0.3, 0.4], atol=1e-9)
    np.testing.assert_allclose(img.GetOrigin(), flip @ origin, atol=1e-9)
    np.testing.assert_allclose(np.array(img.GetDirection()).reshape(3, 3), flip @ R, atol=1e-9)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), data.transpose(2, 1, 0))


def test_probe_calibration_file(tmp_path):
    rng = np.random.default_rng(7)
    calib = ProbeCalibration(_random_rigid(rng, 30), (0.15, 0.12), (256, 334), 0.1)
    calib.save(tmp_path / "probe.yaml")
    back = ProbeCalibration.load(tmp_path / "probe.yaml")
    assert np.allclose(back.T_marker_image, calib.T_marker_image) and back.spacing == calib.spacing
    assert back.size == (256, 334) and back.rms_mm == pytest.approx(0.1)
    (tmp_path / "bad.yaml").write_text("%YAML:1.0\n---\nspacing: [0.1, 0.1]\n")
    with pytest.raises(ValueError, match="T_marker_image"):
        ProbeCalibration.load(tmp_path / "bad.yaml")
    with pytest.raises(ValueError, match="spacing"):
        ProbeCalibration(calib.T_marker_image, (0.0, 0.1))
    with pytest.raises(ValueError, match="rotation"):
        ProbeCalibration(np.diag([1.0, 1.0, 2.0, 1.0]), (0.1, 0.1))


# --- a recording, as a user would run it -------------------------------------------------
def test_calibrate_and_reconstruct_a_recording_from_the_cli(tmp_path, capsys):
    """The user's journey on a simulated recording: track the calibration session,
    calibrate, track the sweep, reconstruct."""
    from markerpose.experiments.ultrasound import write_simulated_recording

    truth = write_simulated_recording(tmp_path, n_frames=10, seed=1, calibration_frames=10, progress=False)
    cal = truth["calibration"]
    assert cli.main(["track", str(cal / "left"), str(cal / "right"), "--fps", "1", "--out", str(cal / "poses.csv"), "--quiet"]) == 0
    sx, sy = truth["spacing"]
    assert (
        cli.main(
            [
                "ultrasound",
                "calibrate",
                "--poses",
                str(cal / "poses.csv"),
                "--images",
                str(cal / "us"),
                "--spacing",
                f"{sx},{sy}",
                "--out",
                str(tmp_path / "probe.yaml"),
            ]
        )
        == 0
    )
    calib = ProbeCalibration.load(tmp_path / "probe.yaml")
    true_calib = ProbeCalibration.load(truth["true_calibration"])
    assert calib.size == true_calib.size and calib.rms_mm < 0.5
    corners = [[0, 0], [255, 0], [0, 333], [255, 333]]
    assert np.abs(calib.pixels_to_marker(corners) - true_calib.pixels_to_marker(corners)).max() < 1.5  # mm
    assert cli.main(["track", str(truth["left"]), str(truth["right"]), "--fps", "30", "--out", str(tmp_path / "poses.csv"), "--quiet"]) == 0
    u, v = truth["seed_px"]
    out = tmp_path / "rec"
    assert (
        cli.main(
            [
                "ultrasound",
                "reconstruct",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--images",
                str(truth["us"]),
                "--calibration",
                str(truth["true_calibration"]),
                "--seed",
                f"{u + 3:.1f},{v - 2:.1f}",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == summary["frames_with_pose"] == 10
    assert abs(summary["cylinder"]["diameter_mm"] - D_TRUE) < 0.1
    seq = formats.read_sequence(out / "sweep.igs.nrrd")
    setup = ProbeSetup()
    c = true_calib.pixels_to_marker([[128, 167]])[0]
    for T_est, T_pi in zip(seq["probe_to_tracker"], truth["T_phantom_image"]):
        # The pose interpolated at each ultrasound frame's time puts the image centre where
        # the truth does.
        T_true = setup.marker_pose(T_pi)
        assert np.linalg.norm(T_est[:3, :3] @ c + T_est[:3, 3] - (T_true[:3, :3] @ c + T_true[:3, 3])) < 0.1
    data, _, _ = formats.read_volume(out / "volume.nrrd")
    assert data.ndim == 3 and data.max() > 100
    cloud = formats.read_ply(out / "points.ply")
    assert cloud["x"].size > 100 and 0.5 * cloud["x"].size < cloud["inlier"].sum() <= cloud["x"].size
    # The estimated calibration reconstructs the same tube.
    assert (
        cli.main(
            [
                "ultrasound",
                "reconstruct",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--images",
                str(truth["us"]),
                "--calibration",
                str(tmp_path / "probe.yaml"),
                "--seed",
                f"{u:.1f},{v:.1f}",
                "--out",
                str(tmp_path / "rec2"),
                "--quiet",
            ]
        )
        == 0
    )
    d2 = json.loads((tmp_path / "rec2" / "summary.json").read_text())["cylinder"]["diameter_mm"]
    assert abs(d2 - D_TRUE) < 0.1
    # User errors: one line, exit 2.
    capsys.readouterr()
    good = ["--images", str(truth["us"]), "--calibration", str(truth["true_calibration"])]
    assert cli.main(["ultrasound", "reconstruct", "--poses", str(tmp_path / "nope.csv"), *good]) == 2
    assert (
        cli.main(
            [
                "ultrasound",
                "reconstruct",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--images",
                str(truth["left"]),
                "--calibration",
                str(truth["true_calibration"]),
            ]
        )
        == 2
    )
    assert (
        cli.main(
            [
                "ultrasound",
                "reconstruct",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--images",
                str(truth["us"]),
                "--calibration",
                str(tmp_path / "poses.csv"),
            ]
        )
        == 2
    )
    assert cli.main(["ultrasound", "reconstruct", "--poses", str(tmp_path / "poses.csv"), *good, "--time-offset", "100"]) == 2
    assert (
        cli.main(
            [
                "ultrasound",
                "calibrate",
                "--poses",
                str(tmp_path / "poses.csv"),
                "--images",
                str(truth["us"]),
                "--spacing",
                "0.15,0.15",
                "--out",
                str(tmp_path / "x.yaml"),
            ]
        )
        == 2
    )  # a sweep has no crossing
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 5 and all(line.startswith("error: ") for line in err)


def test_demo_writes_the_report_results_and_files(tmp_path):
    from markerpose.experiments.ultrasound import experiment

    plan = experiment.Plan(n_acquisitions=1, n_frames=16, n_calibration=10, seed=3)
    path = experiment.main(tmp_path, plan=plan, jobs=1, progress=False)
    res = json.loads((tmp_path / "results.json").read_text())
    for key in (
        "diameter_mm",
        "diameter_error_mm",
        "diameter_error_true_poses_mm",
        "diameter_error_paper_classical_mm",
        "calibration_rms_mm",
        "n_acquisitions",
    ):
        assert key in res and res[key] is not None, key
    assert res["n_acquisitions"] == 1
    assert abs(res["diameter_mm"] - D_TRUE) < 0.06 and res["diameter_error_mm"] < 0.06
    assert res["calibration_rms_mm"] < 0.5
    for name in (
        "report.md",
        "reconstruction.png",
        "residuals.png",
        "calibration.png",
        "frames.png",
        "diameters.png",
        "sweep.igs.nrrd",
        "volume.nrrd",
        "points.ply",
        "probe.yaml",
    ):
        assert (tmp_path / name).is_file(), name
    assert "15.999" in path.read_text()
    assert len(formats.read_sequence(tmp_path / "sweep.igs.nrrd")["images"]) == 16


def test_timestamps_files_with_a_missing_time_or_going_back_are_refused(tmp_path):
    import cv2

    from markerpose.ultrasound.recording import read_frames

    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), np.zeros((8, 8), np.uint8))
    (tmp_path / "timestamps.csv").write_text("file,timestamp_s\nf0.png,0.0\nf1.png\nf2.png,0.2\n")
    with pytest.raises(ValueError, match="row 3 has no time"):
        read_frames(tmp_path)
    (tmp_path / "timestamps.csv").write_text("file,timestamp_s\nf0.png,0.0\nf1.png,0.3\nf2.png,0.2\n")
    with pytest.raises(ValueError, match="f2.png .* is not after f1.png"):
        read_frames(tmp_path)
    (tmp_path / "timestamps.csv").write_text("file,timestamp_s\nf0.png,0.0\nf1.png,0.1\nf2.png,0.2\n")
    np.testing.assert_allclose(read_frames(tmp_path)[1], [0.0, 0.1, 0.2])


def test_temporal_calibration_finds_the_ultrasound_delay(tmp_path, capsys):
    """The probe moved up and down over a plate (simulated B-mode, the true marker poses as
    the tracker's, 3 s): the ultrasound clock 80 ms late is found within 5 ms with the probe
    calibration, through the CLI as a user runs it."""
    import csv as csvmod

    import cv2

    from markerpose.experiments.ultrasound import temporal as exp
    from markerpose.experiments.ultrasound.simulate import ProbeSetup
    from markerpose.ultrasound.temporal import estimate_offset
    from markerpose.video import CSV_HEADER, pose_row

    conf = {**exp.default_conf, "seconds": 3.0}
    setup, rng = ProbeSetup(), np.random.default_rng(4)
    wobble = np.column_stack([rng.uniform(0.1, 0.3, 3), [0.9, 1.7, 3.1], rng.uniform(0, 2 * np.pi, 3)])
    us = tmp_path / "us"
    us.mkdir()
    t_us = np.arange(0, conf["seconds"], 1 / 30)
    with open(us / "timestamps.csv", "w", newline="") as f:
        w = csvmod.writer(f)
        w.writerow(["file", "timestamp_s"])
        for k, t in enumerate(t_us):
            img = exp.simulate_bmode(exp.plate_phantom(), exp.image_pose(setup, t, conf, wobble), setup.transducer, rng)
            cv2.imwrite(str(us / f"{k:04d}.png"), img)
            w.writerow([f"{k:04d}.png", f"{t + 0.080:.6f}"])  # the ultrasound clock 80 ms late

    class E:
        def __init__(self, T):
            self.T, self.residual_px, self.cov = T, 0.1, None

    t_cam = np.arange(0.011, conf["seconds"], 1 / 30)
    with open(tmp_path / "poses.csv", "w", newline="") as f:
        w = csvmod.writer(f)
        w.writerow(CSV_HEADER)
        for k, t in enumerate(t_cam):
            w.writerow(pose_row(k, t, E(setup.marker_pose(exp.image_pose(setup, t, conf, wobble)))))
    ProbeCalibration(setup.T_marker_image(), setup.transducer.spacing, setup.transducer.size).save(tmp_path / "probe.yaml")
    args = ["ultrasound", "temporal", "--poses", str(tmp_path / "poses.csv"), "--images", str(us)]
    assert cli.main([*args, "--calibration", str(tmp_path / "probe.yaml")]) == 0
    out = capsys.readouterr().out
    offset = float(out.split("need ")[1].split(" ")[0])
    assert abs(offset + 80.0) < 5.0, out
    assert "use --time-offset -0.0" in out
    with pytest.raises(ValueError, match="at least 10 frames"):
        estimate_offset([0.0, 0.1], [1.0, 2.0], [0.0, 0.1], [1.0, 2.0])
