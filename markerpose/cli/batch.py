"""``markerpose batch``: many recordings tracked as ``track`` tracks one, on Ray where it is
installed (a local Ray by default, a cluster with ``--address``), resumable."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

from .common import EXIT_BAD_INPUT, add_marker_args, add_preset_args, add_rig_arg, add_set_arg, tracker


class TrackerFactory:
    """The MarkerPose of the command's options for a recording's rig (None: ``--rig``, or the
    built-in rig): sent to the workers, which build their own."""

    def __init__(self, args, threads: int | None):
        self.args, self.threads = args, threads

    def __call__(self, rig: str | None):
        args = copy.copy(self.args)
        args.rig = rig or self.args.rig
        if self.threads is not None and not any(stage == "threads" for stage, _, _ in args.settings or []):
            args.settings = [*(args.settings or []), ("threads", None, self.threads)]
        return tracker(args)


def cmd_batch(args):
    from ..batch import Job, find_recordings, run_batch, totals, write_summary
    from ..engine import ray_installed

    recordings = find_recordings(args.sources)
    use_ray = not args.serial and (args.address is not None or ray_installed())
    if not args.serial and not use_ray:
        print("Ray is not installed: the recordings run here, one after the other (pip install 'markerpose[ray]')", file=sys.stderr)
    factory = TrackerFactory(args, threads=1 if use_ray else None)  # on Ray each worker has one CPU
    factory(None)  # the options checked here, before any task: a bad --set or tool file fails once, not per recording
    if args.reference is not None and not args.tools:
        raise ValueError("--reference needs --tools: the reference is one of the tools")
    out = None if args.out is None else Path(args.out)
    jobs = [
        Job(
            rec,
            str(out / rec.name if out is not None else Path(rec.folder)),
            factory,
            fps=args.fps,
            right_delay=None if args.right_delay is None else args.right_delay / 1000.0,
            tools=bool(args.tools),
            reference=args.reference,
            jsonl=args.jsonl,
            probe=args.probe,
            time_offset_s=args.time_offset,
        )
        for rec in recordings
    ]
    rows = run_batch(
        jobs,
        force=args.force,
        use_ray=use_ray,
        address=args.address,
        workers=args.workers,
        max_retries=args.retries,
        progress=not args.quiet,
    )
    summary_dir = out if out is not None else Path(".")
    csv_path, md_path = write_summary(rows, summary_dir)
    for row in rows:
        if row["status"] == "failed":
            print(f"failed: {row['recording']}: {row['reason']}", file=sys.stderr)
    t = totals(rows)
    found = "" if t["found"] is None else f", the marker found in {100 * t['found']:.1f} % of them"
    print(
        f"{t['recordings']} recordings: {t['done']} tracked ({t['frames']} frames{found}), {t['skipped']} done before, "
        f"{t['failed']} failed; wrote {csv_path} and {md_path}"
    )
    return EXIT_BAD_INPUT if t["failed"] else 0


def register(sub) -> None:
    b = sub.add_parser(
        "batch",
        help="track many recordings as track does, on Ray where it is installed (this machine's cores, or a cluster with --address)",
    )
    b.add_argument(
        "sources",
        nargs="+",
        help="recording folders (left and right frames: left/ right/ or left.mp4 right.mp4, optionally rig.yaml and us/), "
        "folders of them, or list files (a recording folder or LEFT RIGHT [RIG] a line)",
    )
    b.add_argument("--out", help="outputs under OUT/<recording name>, and the summary there (default: in each recording's folder)")
    add_rig_arg(b)
    add_preset_args(b)
    add_set_arg(b)
    b.add_argument("--fps", type=float, default=60.0, help="frame rate of image folders, for timestamp_s (default 60)")
    b.add_argument("--right-delay", type=float, metavar="MS", help="the right camera's exposure after the left's, ms (as track)")
    b.add_argument("--jsonl", action="store_true", help="also poses.jsonl, one JSON object a frame")
    b.add_argument("--tools", nargs="+", metavar="TOOL_FILE", help="track several tools (as track --tools)")
    b.add_argument("--reference", metavar="NAME", help="with --tools: every other tool relative to this one")
    b.add_argument(
        "--probe",
        metavar="PROBE.yaml",
        help="probe calibration: reconstruct the ultrasound sweep (us/) of every recording that has one into reconstruction/",
    )
    b.add_argument("--time-offset", type=float, default=0.0, help="with --probe: seconds added to the ultrasound times (default 0)")
    b.add_argument("--address", help="a running Ray cluster (what ray start --head printed, or auto); default: a local Ray for this run")
    b.add_argument("--workers", type=int, help="the local Ray's workers (default: every core)")
    b.add_argument("--retries", type=int, default=3, help="runs again of a recording whose worker died (default 3)")
    b.add_argument("--serial", action="store_true", help="no Ray: the recordings one after the other in this process")
    b.add_argument("--force", action="store_true", help="track again the recordings that an earlier run finished")
    b.add_argument("--quiet", action="store_true", help="no progress bars")
    add_marker_args(b)
    b.set_defaults(func=cmd_batch)
