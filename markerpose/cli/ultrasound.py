"""``markerpose ultrasound demo | reconstruct | calibrate | simulate | temporal``: freehand 3D
ultrasound with a tracked probe."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from .common import pixel, spacing


def cmd_ultrasound_demo(args):
    from ..experiments.ultrasound import experiment

    t0 = time.perf_counter()
    cmd = "markerpose ultrasound demo" + (" --quick" if args.quick else "") + f" --out {args.out}"
    if args.acquisitions is not None:
        cmd += f" --acquisitions {args.acquisitions}"
    path = experiment.main(
        args.out, quick=args.quick, seed=args.seed, jobs=args.jobs, acquisitions=args.acquisitions, progress=not args.quiet, command=cmd
    )
    print(f"wrote {path} and the plots and files beside it ({time.perf_counter() - t0:.0f} s)")


def cmd_ultrasound_reconstruct(args):
    from ..ultrasound.recording import reconstruct_recording

    s = reconstruct_recording(
        args.poses,
        args.images,
        args.calibration,
        args.out,
        seed_px=args.seed,
        fps=args.fps,
        time_offset_s=args.time_offset,
        max_gap_s=args.max_gap,
        voxel_mm=args.voxel_mm,
        progress=not args.quiet,
    )
    print(f"{s['frames_with_pose']} of {s['frames']} frames with a pose; wrote {', '.join(s['files'])} into {args.out}")
    if "cylinder" in s:
        c = s["cylinder"]
        print(f"cylinder: diameter {c['diameter_mm']:.3f} mm, RMS {c['rms_mm']:.3f} mm, {c['inliers']} of {c['points']} points")


def cmd_ultrasound_calibrate(args):
    from ..ultrasound.recording import calibrate_recording

    _, rep = calibrate_recording(
        args.poses, args.images, args.spacing, out=args.out, fps=args.fps, time_offset_s=args.time_offset, max_gap_s=args.max_gap
    )
    skipped = f" ({rep['no_pose']} without a pose, {rep['no_crossing']} without a clear crossing)" if rep["used"] < rep["frames"] else ""
    worst = max(rep["errors_mm"].items(), key=lambda kv: kv[1])
    print(
        f"calibrated from {rep['used']} of {rep['frames']} frames{skipped}: RMS {rep['rms_mm']:.3f} mm "
        f"(worst {worst[1]:.3f} mm, {worst[0]}); wrote {args.out}"
    )


def cmd_ultrasound_simulate(args):
    from ..experiments.ultrasound import write_simulated_recording

    if args.frames < 2:
        raise ValueError(f"--frames must be >= 2, got {args.frames}")
    t = write_simulated_recording(args.out, n_frames=args.frames, seed=args.seed, progress=not args.quiet)
    u, v = t["seed_px"]
    o, c = Path(args.out), Path(t["calibration"])
    sx, sy = t["spacing"]
    print(
        f"wrote a sweep ({t['camera_frames']} stereo pairs at 30 frames/s, {t['us_frames']} ultrasound frames) and a "
        f"cross-wire calibration session into {o}; the tube (diameter {t['diameter_mm']} mm) is at {u:.0f},{v:.0f} px "
        f"on the first ultrasound frame. Next:\n"
        f"  markerpose track {c / 'left'} {c / 'right'} --fps 1 --out {c / 'poses.csv'}\n"
        f"  markerpose ultrasound calibrate --poses {c / 'poses.csv'} --images {c / 'us'} --spacing {sx},{sy} --out {o / 'probe.yaml'}\n"
        f"  markerpose track {t['left']} {t['right']} --fps 30 --out {o / 'poses.csv'}\n"
        f"  markerpose ultrasound reconstruct --poses {o / 'poses.csv'} --images {t['us']} "
        f"--calibration {o / 'probe.yaml'} --seed {u:.0f},{v:.0f} --out {o / 'reconstruction'}"
    )


def cmd_ultrasound_temporal(args):
    from ..ultrasound.recording import temporal_recording

    r = temporal_recording(args.poses, args.images, args.calibration, fps=args.fps)
    print(
        f"the ultrasound frames' times need {1000 * r['offset_s']:+.1f} ± {1000 * r['sd_s']:.1f} ms to reach the cameras' clock "
        f"({r['frames']} frames; the two signals' RMS difference {r['rms']:.3f} of their sd"
        + ("" if r["calibrated"] else "; without --calibration the marker's own height is used, which the probe's rocking moves")
        + f"): use --time-offset {r['offset_s']:.4f} with calibrate and reconstruct"
    )
    if r["rms"] > 0.3:
        print(
            "warning: the line and the probe's height do not match well: move the probe straight up and down over a flat "
            "plate, its image across the plate, for a few cycles",
            file=sys.stderr,
        )


def _add_clock_args(p) -> None:
    """How the ultrasound frames' times meet the cameras' (reconstruct, calibrate)."""
    p.add_argument("--fps", type=float, help="frame rate of the ultrasound frames when there is no timestamps.csv")
    p.add_argument("--time-offset", type=float, default=0.0, help="seconds added to the ultrasound times to reach the cameras' clock")
    p.add_argument(
        "--max-gap", type=float, default=0.2, help="no pose is interpolated across a tracking gap longer than this, s (default 0.2)"
    )


def _register_demo(usub) -> None:
    ud = usub.add_parser("demo", help="the paper's tube experiment on simulated data: diameter vs the paper, report, plots, files")
    ud.add_argument("--out", default="markerpose-ultrasound", help="output folder (default: markerpose-ultrasound)")
    ud.add_argument("--quick", action="store_true", help="3 short acquisitions (about a minute) instead of 10 full ones")
    ud.add_argument("--acquisitions", type=int, help="number of seeded acquisitions (default 10; --quick 3)")
    ud.add_argument("--seed", type=int, default=0)
    ud.add_argument("--jobs", type=int, help="Ray workers where Ray is installed (default: every core; 1: in this process)")
    ud.add_argument("--quiet", action="store_true", help="no progress bar")
    ud.set_defaults(func=cmd_ultrasound_demo)


def _register_reconstruct(usub) -> None:
    ur = usub.add_parser(
        "reconstruct", help="a recorded sweep: poses.csv from markerpose track + ultrasound frames → sequence, volume, tube fit"
    )
    ur.add_argument("--poses", required=True, help="poses.csv written by markerpose track")
    ur.add_argument("--images", required=True, help="folder of ultrasound frames (sorted by name) with timestamps.csv (file,timestamp_s)")
    ur.add_argument("--calibration", required=True, help="probe calibration YAML (T_marker_image, spacing, image_size)")
    ur.add_argument("--out", default="markerpose-reconstruction", help="output folder (default: markerpose-reconstruction)")
    ur.add_argument("--seed", type=pixel, metavar="U,V", help="a pixel inside the tube on the first frame: segment it and fit a cylinder")
    _add_clock_args(ur)
    ur.add_argument("--voxel-mm", type=float, default=0.3, help="volume spacing, mm (default 0.3)")
    ur.add_argument("--quiet", action="store_true", help="no progress bars")
    ur.set_defaults(func=cmd_ultrasound_reconstruct)


def _register_calibrate(usub) -> None:
    uc = usub.add_parser(
        "calibrate", help="probe calibration from a recorded cross-wire session (poses.csv + ultrasound frames) → probe.yaml"
    )
    uc.add_argument("--poses", required=True, help="poses.csv written by markerpose track for the session")
    uc.add_argument(
        "--images", required=True, help="folder of ultrasound frames showing the wire crossing, with timestamps.csv (file,timestamp_s)"
    )
    uc.add_argument(
        "--spacing", required=True, type=spacing, metavar="SX,SY", help="pixel size in mm (lateral, depth), as the scanner reports it"
    )
    uc.add_argument("--out", default="probe.yaml", help="calibration file to write (default probe.yaml)")
    _add_clock_args(uc)
    uc.set_defaults(func=cmd_ultrasound_calibrate)


def _register_simulate(usub) -> None:
    usim = usub.add_parser(
        "simulate",
        help="write a simulated recording (a sweep and a cross-wire session: stereo and ultrasound frames) to try calibrate and reconstruct on",
    )
    usim.add_argument("--out", default="markerpose-us-recording", help="output folder (default: markerpose-us-recording)")
    usim.add_argument("--frames", type=int, default=30, help="ultrasound frames (15 frames/s; default 30)")
    usim.add_argument("--seed", type=int, default=0)
    usim.add_argument("--quiet", action="store_true", help="no progress bar")
    usim.set_defaults(func=cmd_ultrasound_simulate)


def _register_temporal(usub) -> None:
    ut = usub.add_parser(
        "temporal",
        help="the delay between the ultrasound frames and the cameras, from the probe moved up and down over a flat plate",
    )
    ut.add_argument("--poses", required=True, help="poses.csv written by markerpose track for the session")
    ut.add_argument("--images", required=True, help="folder of ultrasound frames of the plate, with timestamps.csv (file,timestamp_s)")
    ut.add_argument("--calibration", help="probe calibration YAML: the height of the image's centre, not the marker's (recommended)")
    ut.add_argument("--fps", type=float, help="frame rate of the ultrasound frames when there is no timestamps.csv")
    ut.set_defaults(func=cmd_ultrasound_temporal)


def register(sub) -> None:
    us = sub.add_parser("ultrasound", help="freehand 3D ultrasound with a tracked probe (the paper's section 5.3)")
    usub = us.add_subparsers(dest="ultrasound_command", required=True)
    _register_demo(usub)
    _register_reconstruct(usub)
    _register_calibrate(usub)
    _register_simulate(usub)
    _register_temporal(usub)
