"""Freehand reconstruction from a user's own recording.

Inputs:
- ``poses.csv`` from ``markerpose track`` (one row a camera frame: ``timestamp_s``,
  ``valid``, ``T00`` … ``T33`` = T_left_marker);
- a folder of ultrasound frames (PNG, JPEG, BMP, TIFF; sorted by name) with a
  ``timestamps.csv`` beside them (columns ``file,timestamp_s``, on the same clock as the
  cameras, or shifted by a known offset), or a frame rate;
- a probe calibration (:class:`ProbeCalibration` YAML).

Each ultrasound frame gets the pose interpolated at its time (none when the marker was lost
around it). Outputs: the tracked sweep as a PLUS sequence, the compounded volume, and with a
seed the segmented tube's points and cylinder fit.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from .. import formats
from .probe import ProbeCalibration
from .reconstruct import (
    compound,
    fit_cylinder,
    interpolate_poses,
    sweep_normal,
    tracker_points,
)
from .segment import RingSearch, sweep_points

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def read_track_csv(path: str | Path) -> tuple[np.ndarray, list]:
    """Times (s) and poses (4x4 T_left_marker, or None where not found) of a one-marker
    ``markerpose track`` CSV (:func:`markerpose.video.read_track_csv`)."""
    from ..video import read_track_csv as read

    times, poses, _ = read(path)
    return times, poses


def read_frames(folder: str | Path, fps: float | None = None) -> tuple[list[Path], np.ndarray]:
    """The ultrasound frames of ``folder`` and their times: from ``timestamps.csv``
    (``file,timestamp_s``) when present, else frame k at k / ``fps``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"{folder}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    ts_file = folder / "timestamps.csv"
    if ts_file.is_file():
        with open(ts_file, newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows or "file" not in rows[0] or "timestamp_s" not in rows[0]:
            raise ValueError(f"{ts_file}: needs the columns file,timestamp_s")
        by_name = {}
        for k, r in enumerate(rows):
            try:
                t = float(r["timestamp_s"])
            except (TypeError, ValueError):
                raise ValueError(f"{ts_file}: row {k + 2} has no time (file,timestamp_s)") from None
            if not np.isfinite(t):
                raise ValueError(f"{ts_file}: row {k + 2}: the time must be finite, got {r['timestamp_s']}")
            by_name[r["file"]] = t
        missing = [p.name for p in files if p.name not in by_name]
        if missing:
            raise ValueError(f"{ts_file}: no time for {len(missing)} frame(s), e.g. {missing[0]}")
        times = np.array([by_name[p.name] for p in files])
        back = np.nonzero(np.diff(times) <= 0)[0]
        if len(back):
            i = int(back[0])
            raise ValueError(
                f"{ts_file}: the times must increase with the frames' names: {files[i + 1].name} ({times[i + 1]:g} s) "
                f"is not after {files[i].name} ({times[i]:g} s)"
            )
        return files, times
    if fps is None:
        raise ValueError(f"{folder}: no timestamps.csv; give the frame rate (--fps)")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    return files, np.arange(len(files)) / fps


def _load_gray(path: Path, size) -> np.ndarray:
    im = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if im is None:
        raise ValueError(f"{path}: cannot read the image")
    if size is not None and (im.shape[1], im.shape[0]) != tuple(size):
        raise ValueError(f"{path}: {im.shape[1]}x{im.shape[0]} px, but the calibration is for {size[0]}x{size[1]}")
    return im


def reconstruct_recording(
    poses_csv,
    images,
    calibration,
    out_dir,
    seed_px=None,
    fps: float | None = None,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.2,
    voxel_mm: float = 0.3,
    search: RingSearch | None = None,
    progress: bool = True,
) -> dict:
    """Reconstruct a recorded sweep; writes ``sweep.igs.nrrd``, ``volume.nrrd`` and
    ``summary.json`` into ``out_dir`` (and, with ``seed_px``, ``points.ply`` and the
    cylinder fit in the summary).

    Args:
        poses_csv: the ``markerpose track`` CSV.
        images: folder of ultrasound frames (see :func:`read_frames`).
        calibration: :class:`ProbeCalibration` or a path to its YAML.
        out_dir: output folder.
        seed_px: (u, v) inside the tube on the first frame with a pose, to segment a tube.
        fps: frame rate of the ultrasound frames when there is no ``timestamps.csv``.
        time_offset_s: added to the ultrasound times to put them on the cameras' clock.
        max_gap_s: no pose is interpolated across a gap in tracking longer than this.
        voxel_mm: volume grid spacing.
    Returns:
        the summary (also written as ``summary.json``).
    """
    calib = calibration if isinstance(calibration, ProbeCalibration) else ProbeCalibration.load(calibration)
    p_times, p_poses = read_track_csv(poses_csv)
    files, times = read_frames(images, fps)
    times = times + time_offset_s
    poses = interpolate_poses(times, p_times, p_poses, max_gap_s)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a folder")
    frames = [_load_gray(p, calib.size) for p in files]
    n_posed = sum(T is not None for T in poses)
    if n_posed == 0:
        raise ValueError("no ultrasound frame falls inside the tracked span with a pose; check the clocks (--time-offset)")
    out.mkdir(parents=True, exist_ok=True)
    formats.write_sequence(out / "sweep.igs.nrrd", frames, times, poses, calib.image_to_probe)
    vol = compound(frames, poses, calib, voxel_mm=voxel_mm, progress=progress)
    formats.write_volume(out / "volume.nrrd", vol.data, vol.origin, vol.directions)
    summary = {
        "frames": len(frames),
        "frames_with_pose": n_posed,
        "volume_shape": list(vol.data.shape),
        "voxel_mm": voxel_mm,
        "volume_filled_fraction": vol.filled,
        "files": ["sweep.igs.nrrd", "volume.nrrd", "summary.json"],
    }
    if seed_px is not None:
        summary["cylinder"] = _tube(frames, poses, calib, seed_px, search, progress, out)
        summary["files"].append("points.ply")
    formats.write_json(out / "summary.json", summary)
    return summary


def _tube(frames: list, poses: list, calib: ProbeCalibration, seed_px, search: RingSearch | None, progress: bool, out: Path) -> dict:
    """The tube segmented from ``seed_px`` on the first posed frame on, its points written
    to ``out``/points.ply: the summary of the cylinder fitted to them."""
    first = next(k for k, T in enumerate(poses) if T is not None)
    posed = list(range(first, len(frames)))
    pts = sweep_points([frames[k] for k in posed], seed_px, calib.spacing, search, progress=progress)
    X, idx = tracker_points(pts, [poses[k] for k in posed], calib)
    if len(X) < 10:
        raise ValueError(f"the tube was not found from the seed {tuple(seed_px)}: {len(X)} points")
    fit = fit_cylinder(X, sweep_normal(poses, calib))
    formats.write_ply(out / "points.ply", X, np.asarray(posed)[idx], fit.inliers)
    return {
        "diameter_mm": fit.diameter,
        "radius_mm": fit.radius,
        "rms_mm": fit.rms,
        "axis_point_mm": fit.point,
        "axis_direction": fit.direction,
        "points": len(X),
        "inliers": int(fit.inliers.sum()),
    }


def calibrate_recording(
    poses_csv,
    images,
    spacing,
    out=None,
    fps: float | None = None,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.2,
    dynamic_range_db: float = 55.0,
) -> tuple[ProbeCalibration, dict]:
    """Probe calibration from a recorded cross-wire session: each ultrasound frame shows the
    wire crossing (found automatically, :func:`~markerpose.ultrasound.segment.point_target`)
    while the cameras track the probe. Frames without a pose or without a clear crossing
    are skipped and counted.

    Args:
        poses_csv: ``markerpose track`` CSV of the session.
        images: folder of the ultrasound frames (with ``timestamps.csv``, or ``fps``).
        spacing: (sx, sy) mm per pixel, as the scanner reports it for its depth setting.
        out: where to write the calibration YAML (None: not written).
    Returns:
        (calibration, report): the report has the frames used and skipped, the RMS and each
        frame's reconstruction error of the crossing (mm).
    """
    from .calibrate import calibrate_probe
    from .segment import point_target

    p_times, p_poses = read_track_csv(poses_csv)
    files, times = read_frames(images, fps)
    poses = interpolate_poses(times + time_offset_s, p_times, p_poses, max_gap_s)
    frames = [_load_gray(p, None) for p in files]
    sizes = {f.shape for f in frames}
    if len(sizes) != 1:
        raise ValueError(f"{images}: the frames differ in size ({sorted(sizes)})")
    pts = [point_target(f, dynamic_range_db=dynamic_range_db) for f in frames]
    h, w = frames[0].shape
    calib, P, err = calibrate_probe(poses, pts, spacing, (w, h))
    used = [f.name for f, T, p in zip(files, poses, pts) if T is not None and p is not None]
    report = {
        "frames": len(files),
        "used": len(used),
        "no_pose": sum(T is None for T in poses),
        "no_crossing": sum(p is None for p in pts),
        "rms_mm": calib.rms_mm,
        "point_mm": P,
        "errors_mm": dict(zip(used, err)),
    }
    if out is not None:
        calib.save(out)
    return calib, report


def temporal_recording(poses_csv: str | Path, images: str | Path, calibration: str | Path | None = None, fps: float | None = None) -> dict:
    """The offset (s) to add to a recording's ultrasound times to reach the cameras' clock, from
    a session of the probe moved up and down over a flat plate
    (:func:`markerpose.ultrasound.temporal.estimate_offset`): the line's depth in each frame
    against the probe's height (the image's centre at the line's depth with ``calibration``,
    else the marker's origin)."""
    from .temporal import estimate_offset, plate_depths, probe_heights

    times, poses = read_track_csv(poses_csv)
    files, us_times = read_frames(images, fps)
    calib = ProbeCalibration.load(calibration) if calibration is not None else None
    frames = [_load_gray(p, None if calib is None else calib.size) for p in files]
    depths = plate_depths(frames, 1.0)
    point = None
    if calib is not None:
        w = frames[0].shape[1]
        point = calib.pixels_to_marker([[(w - 1) / 2, float(np.nanmean(depths))]])[0]
    found = estimate_offset(us_times, depths, times, probe_heights(poses, point))
    return {**found, "calibrated": calib is not None}


__all__ = ["temporal_recording", "calibrate_recording", "read_frames", "read_track_csv", "reconstruct_recording"]
