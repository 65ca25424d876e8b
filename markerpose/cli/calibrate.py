"""``markerpose pattern`` and ``markerpose calibrate``: the circle grid printed, and the
stereo rig calibrated from pairs of images of it."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .common import rig


def grid(args):
    """The circle grid of --grid COLSxROWS, --spacing and --diameter."""
    from ..calibration import CircleGrid

    try:
        cols, rows = (int(v) for v in str(args.grid).lower().split("x"))
    except ValueError:
        raise ValueError(f"--grid must be COLSxROWS (e.g. 4x11), got {args.grid!r}") from None
    return CircleGrid(cols, rows, args.spacing, args.diameter)


def cmd_pattern(args):
    from ..marker import write_grid

    path = write_grid(grid(args), args.out, paper=args.paper)
    print(f"wrote {path} ({args.paper}); print at 100% and check the 50 mm scale bar with a ruler")


def _recorded_pairs(args):
    """(name, left, right) of LEFT and RIGHT, every ``--every``-th pair, read one at a time:
    named by the left image's file (folders) or ``frame K`` (videos). Returns (the pairs,
    how many there will be or None)."""
    if not (args.left and args.right):
        raise ValueError("calibrate needs LEFT and RIGHT (image folders or videos), or --rendered N")
    if args.every < 1:
        raise ValueError(f"--every must be 1 or more, got {args.every}")
    from ..video import open_stereo

    stream = open_stereo(args.left, args.right)
    files = getattr(stream.left, "files", None)

    def pairs():
        try:
            for k, _, a, b in stream:
                if k % args.every == 0:
                    yield (files[k].name if files is not None else f"frame {k}"), a, b
        finally:
            stream.close()

    return pairs(), None if stream.count is None else -(-stream.count // args.every)


def cmd_calibrate(args):
    from ..calibration import calibrate, plot_coverage

    the_grid = grid(args)
    from tqdm import tqdm

    if args.rendered:
        from ..experiments.calibration_check import check, rendered_pairs

        truth = rig(None)
        pairs, _ = rendered_pairs(truth, the_grid, args.rendered, args.seed)
        pairs, count = [(f"rendered {k}", a, b) for k, (a, b) in enumerate(pairs)], len(pairs)
    else:
        pairs, count = _recorded_pairs(args)
    cal = calibrate(tqdm(pairs, total=count, desc="find grid", unit="pair", disable=args.quiet), the_grid)
    out = Path(args.out)
    cal.rig.save(out)
    s = cal.summary()
    for name, why in list(cal.why_rejected.items())[:10]:
        print(f"rejected {name}: {why}", file=sys.stderr)
    if len(cal.why_rejected) > 10:
        print(f"... and {len(cal.why_rejected) - 10} more pairs rejected", file=sys.stderr)
    print(
        f"wrote {out}: {s['pairs_used']} pairs used, {len(s['pairs_rejected'])} rejected; "
        f"RMS reprojection error left {s['rms_left_px']:.3f} px, right {s['rms_right_px']:.3f} px, stereo {s['rms_stereo_px']:.3f} px; "
        f"baseline {s['baseline_mm']:.2f} mm"
    )
    if s["volume_mm"] is not None:
        lo, hi = s["volume_mm"]
        print(
            f"calibrated volume (where the grid was, left camera's frame): x {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}..{hi[1]:.0f}, "
            f"z {lo[2]:.0f}..{hi[2]:.0f} mm; poses beyond it (by 10 %) are rated 'outside the calibrated volume'"
        )
    if args.coverage:
        print(f"wrote {plot_coverage(cal, args.coverage)}: where the grid was seen in each image")
    if args.rendered:
        c = check(truth, cal)
        print(
            "against the rig that rendered the images: focal lengths within "
            f"{100 * max(c['f_left_rel_error'], c['f_right_rel_error']):.4f} %, principal points within "
            f"{max(c['c_left_px_error'], c['c_right_px_error']):.2f} px, baseline within {c['baseline_mm_error']:.4f} mm, "
            f"rotation within {c['R_deg_error']:.4f}°"
        )
    if max(s["rms_left_px"], s["rms_right_px"]) > 0.5:
        print(
            "warning: RMS reprojection error above 0.5 px: check focus, motion blur, a flat print and the --grid/--spacing", file=sys.stderr
        )


def register(sub) -> None:
    pt = sub.add_parser("pattern", help="write a printable asymmetric circle grid for calibration (PDF or SVG)")
    pt.add_argument("--out", default="grid.pdf", help="grid.pdf or grid.svg (default grid.pdf)")
    pt.add_argument("--grid", default="4x11", help="circles per row x rows, OpenCV's pattern size (default 4x11)")
    pt.add_argument("--spacing", type=float, default=15.0, help="OpenCV's square size, mm (default 15)")
    pt.add_argument("--diameter", type=float, default=None, help="circle diameter, mm (default: half the spacing)")
    pt.add_argument("--paper", default="a4", choices=["a4", "letter"])
    pt.set_defaults(func=cmd_pattern)

    cb = sub.add_parser("calibrate", help="calibrate the stereo rig from pairs of images of the circle grid; writes the rig file")
    cb.add_argument("left", nargs="?", help="left images: a folder (sorted by name) or a video")
    cb.add_argument("right", nargs="?", help="right images, the same kind")
    cb.add_argument("--grid", default="4x11", help="circles per row x rows, as printed (default 4x11)")
    cb.add_argument("--spacing", type=float, default=15.0, help="OpenCV's square size, mm, as printed (default 15)")
    cb.add_argument("--diameter", type=float, default=None, help=argparse.SUPPRESS)
    cb.add_argument("--out", default="rig.yaml", help="rig file to write (default rig.yaml)")
    cb.add_argument("--coverage", help="also a plot of where the grid was seen in each image (PNG)")
    cb.add_argument(
        "--rendered", type=int, metavar="N", help="instead of LEFT RIGHT: N rendered pairs of the built-in rig, checked against it"
    )
    cb.add_argument("--seed", type=int, default=0, help="--rendered: seed of the poses and the noise")
    cb.add_argument("--every", type=int, default=1, metavar="K", help="use every K-th pair (videos: frames near one another add little)")
    cb.add_argument("--quiet", action="store_true", help="no progress bar")
    cb.set_defaults(func=cmd_calibrate)
