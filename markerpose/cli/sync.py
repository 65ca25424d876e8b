"""``markerpose sync``: how far apart two cameras expose, from a recording of the marker moving."""

from __future__ import annotations

import sys

from .common import add_marker_args, add_preset_args, add_rig_arg, add_set_arg, tracker


def measure(args) -> dict:
    """Track the recording with the loose limits (:data:`markerpose.sync.LOOSE`) and estimate the delay; the result of
    :func:`markerpose.sync.estimate_delay` with the marker's speed (mm/s) added."""
    import numpy as np
    from tqdm import tqdm

    from ..sync import LOOSE, estimate_delay
    from ..video import open_stereo

    loose = [(stage, key, value) for stage, keys in LOOSE.items() for key, value in keys.items()]
    args.settings = [*loose, *(args.settings or [])]  # the user's --set after: theirs win
    pose_tracker = tracker(args)
    stream = open_stereo(args.left, args.right, args.fps)
    nan = np.full((3, 2), np.nan)
    times, lefts, rights, origins = [], [], [], []
    try:
        for _, t, left, right in tqdm(stream, total=stream.count, desc="track", unit="pair", disable=args.quiet):
            est = pose_tracker.track(left, right)
            times.append(t)
            lefts.append(nan if est is None else est.detections[0].centers)
            rights.append(nan if est is None else est.detections[1].centers)
            origins.append(np.full(3, np.nan) if est is None else est.T[:3, 3])
    finally:
        stream.close()
    found = estimate_delay(pose_tracker.rig, pose_tracker.marker, times, lefts, rights, max_delay=args.max_delay_ms / 1000)
    t, X = np.array(times), np.array(origins)
    speed = np.linalg.norm(np.diff(X, axis=0), axis=1) / np.diff(t)
    speed = speed[np.isfinite(speed)]
    found["speed_mm_s"] = {"median": float(np.median(speed)), "p95": float(np.percentile(speed, 95))} if len(speed) else None
    found["frames"] = len(times)
    return found


def cmd_sync(args):
    found = measure(args)
    d, sd = 1000 * found["delay_s"], 1000 * found["sd_s"]
    print(
        f"the right camera exposes {d:+.2f} ± {sd:.2f} ms after the left ({found['pairs']} moving pairs of {found['frames']}; "
        f"RMS reprojection error {found['residual_px']:.3f} px at that delay, {found['residual_px_at_zero']:.3f} px taken as simultaneous)"
    )
    speed = found["speed_mm_s"]
    if speed is not None:
        err = speed["p95"] * abs(found["delay_s"])
        verdict = "synchronised enough" if err <= args.target_mm else "not synchronised enough"
        print(
            f"at this recording's speeds (p95 {speed['p95']:.0f} mm/s) the delay moves the marker {err:.3f} mm between the views: "
            f"{verdict} for {args.target_mm:g} mm"
            + ("" if err <= args.target_mm else f"; track with: markerpose track ... --right-delay {d:.1f}")
        )
    if found["speed_px_s"] < 20:
        print(
            "warning: the marker hardly moved in the images; move it across the view (e.g. up and down) and record again", file=sys.stderr
        )
    if args.json:
        from ..formats import write_json

        write_json(args.json, found)
        print(f"wrote {args.json}")


def register(sub) -> None:
    p = sub.add_parser("sync", help="measure how far apart the two cameras expose, from a recording of the marker moving (markerpose.sync)")
    p.add_argument("left", help="left frames: a folder of images (sorted by name) or a video file")
    p.add_argument("right", help="right frames, the same kind")
    add_rig_arg(p)
    p.add_argument("--fps", type=float, default=60.0, help="frame rate of image folders (videos give their own; default 60)")
    p.add_argument("--max-delay-ms", type=float, default=100.0, help="the largest delay searched, ms (default 100)")
    p.add_argument("--target-mm", type=float, default=0.1, help="the accuracy the verdict is for, mm (default 0.1)")
    p.add_argument("--json", help="also the result as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_preset_args(p)
    add_marker_args(p)
    add_set_arg(p)
    p.set_defaults(func=cmd_sync)
