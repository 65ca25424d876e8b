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


def _recorded_pairs(args) -> list:
    """The (left, right) images of LEFT and RIGHT."""
    if not (args.left and args.right):
        raise ValueError("calibrate needs LEFT and RIGHT (image folders or videos), or --rendered N")
    from ..video import open_stereo

    stream = open_stereo(args.left, args.right)
    try:
        return [(a, b) for _, _, a, b in stream]
    finally:
        stream.close()


def cmd_calibrate(args):
    from ..calibration import calibrate, plot_coverage

    the_grid = grid(args)
    if args.rendered:
        from ..experiments.calibration_check import check, rendered_pairs

        truth = rig(None)
        pairs, _ = rendered_pairs(truth, the_grid, args.rendered, args.seed)
    else:
        pairs = _recorded_pairs(args)
    cal = calibrate(pairs, the_grid, list(range(len(pairs))))
    out = Path(args.out)
    cal.rig.save(out)
    s = cal.summary()
    print(
        f"wrote {out}: {s['pairs_used']} pairs used ({len(s['pairs_rejected'])} rejected: {s['pairs_rejected'][:10]}); "
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
    cb.set_defaults(func=cmd_calibrate)
