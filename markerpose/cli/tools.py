"""``markerpose tools``: a set of tools that the tracker tells apart, as files and printable targets."""

from __future__ import annotations

from pathlib import Path

from .common import positive_int


def cmd_tools(args):
    from ..marker import write_target
    from ..tools import MIN_DIFFERENCE_MM, least_difference, tool_set

    tools = tool_set(args.count)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for tool in tools:
        tool.save(out / f"{tool.name}.yaml")
        write_target(tool, out / f"{tool.name}.{args.format}", paper=args.paper)
        x0, y0, x1, y1 = tool.plate
        c2 = ", ".join(f"{v:.1f}" for v in tool.c2)
        print(f"{tool.name}: c1 ({tool.c1[0]:.1f}, 0), c2 ({c2}) mm, plate {x1 - x0:.0f} x {y1 - y0:.0f} mm")
    if len(tools) > 1:
        print(
            f"least layout difference between two tools: {least_difference(tools):.2f} mm (at least {MIN_DIFFERENCE_MM:g} mm tells them apart)"
        )
    print(f"wrote {len(tools)} tool files and targets to {out}/; print the targets at 100% and check each 50 mm scale bar")


def register(sub) -> None:
    t = sub.add_parser("tools", help="write a set of tools the tracker tells apart: tool files (YAML) and printable targets")
    t.add_argument("--count", type=positive_int, default=2, help="how many tools, 1 to 12 (default 2)")
    t.add_argument("--out", default="tools", help="folder for NAME.yaml and NAME.pdf of each tool (default tools)")
    t.add_argument("--paper", default="a4", choices=["a4", "letter"])
    t.add_argument("--format", default="pdf", choices=["pdf", "svg"], help="the targets' format (default pdf)")
    t.set_defaults(func=cmd_tools)
