"""``markerpose marker``: a printable target at exact scale."""

from __future__ import annotations

from .common import add_marker_args, marker


def cmd_marker(args):
    from ..marker import write_target

    path = write_target(marker(args), args.out, paper=args.paper)
    print(f"wrote {path} ({args.paper}); print at 100% and check the 50 mm scale bar with a ruler")


def register(sub) -> None:
    m = sub.add_parser("marker", help="write a printable target (PDF or SVG) at exact scale")
    m.add_argument("--out", default="target.pdf", help="target.pdf or target.svg (default target.pdf)")
    m.add_argument("--paper", default="a4", choices=["a4", "letter"])
    add_marker_args(m)
    m.set_defaults(func=cmd_marker)
