"""``markerpose track``: the marker through two image folders, two videos or two
cameras; one CSV row a frame, optionally a video, a live view and OpenIGTLink. With
``--tools``, several tools at once: one CSV row a frame and tool, each tool's pose in the
camera's frame or, with ``--reference``, in the reference tool's."""

from __future__ import annotations

import sys

from .common import EXIT_INTERRUPTED, add_marker_args, add_preset_args, add_rig_arg, add_set_arg, port, tracker


def _sinks(args, pose_tracker, stream) -> list:
    """The live view and the video file asked for; the stream is closed when one fails."""
    from ..video import ShowSink, VideoSink

    sinks = []
    try:
        if args.show:
            sinks.append(ShowSink(pose_tracker.rig))
        if args.rerun or args.rerun_save:
            from ..live3d import RerunSink

            sinks.append(RerunSink(pose_tracker.rig, save=args.rerun_save, image_every=args.rerun_images))
        if args.video:
            tools = list(pose_tracker.tools) if args.tools else ()
            notice = None if args.quiet else (lambda line: print(f"note: {line}", file=sys.stderr))
            sinks.append(VideoSink(args.video, pose_tracker.rig, stream.fps or args.fps, notice, tools))
    except ValueError:
        stream.close()
        raise
    return sinks


def _sender(args, stream, names=None):
    """The OpenIGTLink sender of --igtl, or None (``names``: the tools of --tools); the
    stream is closed when it fails."""
    if not args.igtl:
        return None
    from ..igtl import IGTLSender, IGTLToolsSender

    try:
        if names is None:
            send = IGTLSender(args.igtl_port, args.igtl_name, local_only=not args.igtl_public)
        else:
            send = IGTLToolsSender(args.igtl_port, names, args.reference, local_only=not args.igtl_public)
    except ValueError:
        stream.close()
        raise
    devices = repr(args.igtl_name) if names is None else ", ".join(repr(d) for d in send.devices.values())
    print(f"OpenIGTLink: serving TRANSFORM {devices} on port {args.igtl_port}, every frame with its status", file=sys.stderr)
    return send


def _check_reference(args, names: list) -> None:
    """``ValueError`` unless --reference names one of the tools."""
    if args.reference is not None and args.reference not in names:
        raise ValueError(f"--reference {args.reference}: no such tool; the tools are {', '.join(names)}")


def _tools_summary(s: dict) -> str:
    """Each tool's found share (and, relative to the reference, the share reported)."""
    parts = []
    for name, t in s["tools"].items():
        part = f"{name} found in {100 * t['found']:.1f} %"
        if name == s["reference"]:
            part += " (the reference)"
        elif s["reference"] is not None:
            part += f", {100 * t['reported']:.1f} % relative to {s['reference']}"
        parts.append(part)
    return "; ".join(parts)


def _stop_on_sigterm() -> None:
    """``kill -TERM`` stops a run as Ctrl-C does: every row kept, the summary printed."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)


def cmd_track(args):
    from ..video import check_output, open_stereo, track_stream, track_tools_stream

    if args.reference is not None and not args.tools:
        raise ValueError("--reference needs --tools: the reference is one of the tools")
    for path, what in ((args.out, "--out"), (args.jsonl, "--jsonl"), (args.video, "--video"), (args.rerun_save, "--rerun-save")):
        if path is not None:
            check_output(path, what)
    pose_tracker = tracker(args)
    names = list(pose_tracker.tools) if args.tools else None
    if names is not None:
        _check_reference(args, names)
    if args.igtl_port is not None and not args.igtl:
        raise ValueError("--igtl-port needs --igtl")
    if args.igtl and args.igtl_port is None:
        from ..igtl import DEFAULT_PORT

        args.igtl_port = DEFAULT_PORT
    delay = None if args.right_delay is None else args.right_delay / 1000.0
    if delay is not None and not abs(delay) <= 1.0:
        raise ValueError(f"--right-delay is in milliseconds, within ±1000, got {args.right_delay}")
    stream = open_stereo(args.left, args.right, args.fps, realtime=args.realtime)
    sinks = _sinks(args, pose_tracker, stream)
    send = _sender(args, stream, names)
    _stop_on_sigterm()
    try:
        if names is None:
            s = track_stream(
                pose_tracker, stream, args.out, args.jsonl, progress=not args.quiet, send=send, sinks=tuple(sinks), right_delay=delay
            )
        else:
            s = track_tools_stream(
                pose_tracker,
                stream,
                args.out,
                args.jsonl,
                progress=not args.quiet,
                reference=args.reference,
                send=send,
                sinks=tuple(sinks),
                right_delay=delay,
            )
    finally:
        if send is not None:
            send.close()
        for sink in sinks:
            sink.close()
    wrote = f"wrote {s['csv']}" + (f" and {args.jsonl}" if args.jsonl else "")
    check = pose_tracker.rig_check
    if check.fired is not None:
        print(f"warning: {check.fired} (fired at tracked pose {check.fired_at}; later poses have status 'rig changed')", file=sys.stderr)
    if names is not None:
        print(f"{'stopped: ' if s['stopped'] else ''}{s['frames']} frames, {s['fps']:.1f} frames/s; {_tools_summary(s)}; {wrote}")
    else:
        print(
            f"{'stopped: ' if s['stopped'] else ''}{s['frames']} frames, marker found in {100 * s['found']:.1f} % "
            f"({100 * s['tracked']:.0f} % of those tracked), {s['fps']:.1f} frames/s, longest gap {s['longest_gap']} frames; {wrote}"
        )
    if s["grab_offset_ms"] is not None:
        print(
            f"the two cameras were grabbed {s['grab_offset_ms']:+.1f} ms apart (median, right minus left): they are not "
            "synchronised, and their exposures may be up to a frame apart",
            file=sys.stderr,
        )
    return EXIT_INTERRUPTED if s["stopped"] else 0  # stopped (Ctrl-C, kill -TERM): every row kept, the run incomplete


def register(sub) -> None:
    from ..igtl import DEFAULT_PORT

    k = sub.add_parser("track", help="track the marker through two image folders, two videos or two cameras; one CSV row a frame")
    k.add_argument("left", help="left frames: a folder of images (sorted by name), a video file or a camera index")
    k.add_argument("right", help="right frames, the same kind")
    add_rig_arg(k)
    k.add_argument("--out", default="poses.csv", help="CSV, one row a frame (default poses.csv)")
    k.add_argument("--jsonl", help="also one JSON object a frame")
    k.add_argument(
        "--video",
        help="also a video of both views side by side with the marker's axes drawn, frames without it marked: "
        ".webm (VP9, plays in browsers), .mp4 or .avi",
    )
    k.add_argument(
        "--rerun", action="store_true", help="a live 3D view in rerun: the cameras, each tool's pose and path, the images (the rerun extra)"
    )
    k.add_argument("--rerun-save", metavar="FILE.rrd", help="the same view saved as a rerun recording (open it with: rerun FILE.rrd)")
    k.add_argument(
        "--rerun-images", type=int, default=1, metavar="K", help="--rerun: log the images every K-th frame (0: never; default 1)"
    )
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
        action="store_true",
        help="serve the poses over OpenIGTLink (3D Slicer, PLUS) as TRANSFORM messages with PLUS's status metadata, "
        "to any number of clients (the igtl extra)",
    )
    k.add_argument("--igtl-port", type=port, metavar="PORT", help=f"the OpenIGTLink port (default {DEFAULT_PORT})")
    k.add_argument(
        "--right-delay",
        type=float,
        metavar="MS",
        help="the right camera's exposure after the left's, ms (markerpose sync measures it): poses at the left view's time",
    )
    k.add_argument(
        "--realtime",
        action="store_true",
        help="replay folders and videos at their frame rate (videos' own, --fps for folders), not as fast as they are read",
    )
    k.add_argument(
        "--igtl-name",
        default="MarkerToTracker",
        help="the TRANSFORM's device name (default MarkerToTracker); ignored with --tools, where each tool's is NameToTracker "
        "(or NameToReference relative to --reference)",
    )
    k.add_argument("--igtl-public", action="store_true", help="listen on the network interface, not only on 127.0.0.1")
    k.add_argument("--quiet", action="store_true", help="no progress bar")
    add_set_arg(k)
    k.add_argument(
        "--tools",
        nargs="+",
        metavar="TOOL_FILE",
        help="track several tools (YAML tool files, e.g. from markerpose tools), given after LEFT RIGHT; "
        "the CSV has one row a frame and tool; the files define the geometry",
    )
    k.add_argument(
        "--reference",
        metavar="NAME",
        help="with --tools: report every other tool relative to this one (T_reference_tool); "
        "not at all in frames where the reference is not seen",
    )
    add_marker_args(k)
    k.set_defaults(func=cmd_track)
