"""``markerpose track``: the marker through two image folders, two videos or two
cameras; one CSV row a frame, optionally a video, a live view and OpenIGTLink."""

from __future__ import annotations

import sys

from .common import add_marker_args, add_preset_args, add_rig_arg, add_set_arg, tracker


def _sinks(args, pose_tracker, stream) -> list:
    """The live view and the video file asked for; the stream is closed when one fails."""
    from ..video import ShowSink, VideoSink

    sinks = []
    try:
        if args.show:
            sinks.append(ShowSink(pose_tracker.rig))
        if args.video:
            sinks.append(VideoSink(args.video, pose_tracker.rig, stream.fps or args.fps))
    except ValueError:
        stream.close()
        raise
    return sinks


def _sender(args, stream):
    """The OpenIGTLink sender of --igtl, or None; the stream is closed when it fails."""
    if args.igtl is None:
        return None
    from ..video import IGTLSender

    try:
        send = IGTLSender(args.igtl, args.igtl_name, local_only=not args.igtl_public)
    except ValueError:
        stream.close()
        raise
    print(f"OpenIGTLink: serving TRANSFORM {args.igtl_name!r} on port {args.igtl}", file=sys.stderr)
    return send


def cmd_track(args):
    from ..video import open_stereo, track_stream

    pose_tracker = tracker(args)
    stream = open_stereo(args.left, args.right, args.fps)
    sinks = _sinks(args, pose_tracker, stream)
    send = _sender(args, stream)
    try:
        s = track_stream(pose_tracker, stream, args.out, args.jsonl, progress=not args.quiet, send=send, sinks=tuple(sinks))
    finally:
        if send is not None:
            send.close()
        for sink in sinks:
            sink.close()
    print(
        f"{'stopped: ' if s['stopped'] else ''}{s['frames']} frames, marker found in {100 * s['found']:.1f} % "
        f"({100 * s['tracked']:.0f} % of those tracked), {s['fps']:.1f} frames/s, longest gap {s['longest_gap']} frames; "
        f"wrote {s['csv']}" + (f" and {args.jsonl}" if args.jsonl else "")
    )


def register(sub) -> None:
    k = sub.add_parser("track", help="track the marker through two image folders, two videos or two cameras; one CSV row a frame")
    k.add_argument("left", help="left frames: a folder of images (sorted by name), a video file or a camera index")
    k.add_argument("right", help="right frames, the same kind")
    add_rig_arg(k)
    k.add_argument("--out", default="poses.csv", help="CSV, one row a frame (default poses.csv)")
    k.add_argument("--jsonl", help="also one JSON object a frame")
    k.add_argument("--video", help="also a video (mp4) of both views side by side with the marker's axes drawn")
    k.add_argument("--show", action="store_true", help="a live window with both views and the axes (q stops; needs a display)")
    k.add_argument(
        "--fps",
        type=float,
        default=60.0,
        help="frame rate of image folders, for timestamp_s (videos and cameras give their own; default 60)",
    )
    add_preset_args(k)
    k.add_argument(
        "--igtl",
        type=int,
        nargs="?",
        const=18944,
        metavar="PORT",
        help="serve the poses over OpenIGTLink (3D Slicer, PLUS) as TRANSFORM messages (port default 18944; the igtl extra)",
    )
    k.add_argument("--igtl-name", default="MarkerToTracker", help="the TRANSFORM's device name (default MarkerToTracker)")
    k.add_argument("--igtl-public", action="store_true", help="listen on the network interface, not only on 127.0.0.1")
    k.add_argument("--quiet", action="store_true", help="no progress bar")
    add_set_arg(k)
    add_marker_args(k)
    k.set_defaults(func=cmd_track)
