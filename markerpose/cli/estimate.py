"""``markerpose estimate``: the marker's pose from a stereo pair of image files (JSON)."""

from __future__ import annotations

from .common import EXIT_NOT_FOUND, add_marker_args, add_preset_args, add_rig_arg, add_set_arg, tracker


def cmd_estimate(args):
    from ..formats import dumps
    from ..images import read_image

    pose_tracker = tracker(args)
    images = [read_image(p) for p in (args.left, args.right)]
    est = pose_tracker.estimate(*images)
    if est is None:
        print(dumps({"found": False}, None))
        return EXIT_NOT_FOUND
    print(dumps({"found": True, "T_left_marker": est.T, "points3d": est.points3d, "centers": est.centers, "residual_px": est.residual_px}))
    return 0


def register(sub) -> None:
    e = sub.add_parser("estimate", help="pose of the marker from a stereo pair of image files (JSON)")
    e.add_argument("left")
    e.add_argument("right")
    add_rig_arg(e)
    add_preset_args(e)
    add_set_arg(e)
    add_marker_args(e)
    e.set_defaults(func=cmd_estimate)
