"""``markerpose pivot``: a pointer's tip from a recording of the tool pivoting about it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from .common import EXIT_BAD_INPUT


def cmd_pivot(args):
    import numpy as np
    import yaml

    from ..marker import Marker
    from ..pivot import pivot_calibration
    from ..video import read_track_csv

    _, poses, frame = read_track_csv(args.poses, args.tool)
    found = [T for T in poses if T is not None]
    if len(found) < 3:
        raise ValueError(f"{args.poses}: {len(found)} pose(s) found of {len(poses)} rows; a pivot calibration needs the tool seen turning")
    res = pivot_calibration(np.stack(found))
    out = {**res.to_dict(), "tool": args.tool, "frame": frame, "poses_csv": str(args.poses)}
    path = Path(args.out)
    path.write_text(yaml.safe_dump(out, sort_keys=False, default_flow_style=None))
    tip = ", ".join(f"{v:.3f}" for v in res.tip_mm)
    pivot = ", ".join(f"{v:.3f}" for v in res.pivot_mm)
    print(f"tip ({tip}) mm in the marker's frame, sd {res.tip_sd_mm:.3f} mm")
    print(f"pivot ({pivot}) mm in the {'camera' if frame == 'camera' else frame + ' tool'}'s frame, sd {res.pivot_sd_mm:.3f} mm")
    print(
        f"RMSE {res.rmse_mm:.3f} mm over {int(res.inliers.sum())} of {len(found)} poses "
        f"({len(found) - int(res.inliers.sum())} rejected); rotation sd {res.spread_deg[0]:.1f}° / {res.spread_deg[1]:.1f}°"
    )
    print(f"verdict: {res.verdict}")
    print(f"wrote {path}")
    if args.write_tool:
        tool = Marker.load(args.write_tool)
        dataclasses.replace(tool, tip=tuple(float(v) for v in res.tip_mm)).save(args.write_tool)
        print(f"wrote the tip into {args.write_tool}")
    return 0 if res.ok else EXIT_BAD_INPUT


def register(sub) -> None:
    p = sub.add_parser(
        "pivot",
        help="a pointer's tip from a recording of the tool pivoting about it (track's CSV): tip in the marker frame, pivot point, RMSE",
    )
    p.add_argument("poses", help="markerpose track's CSV of the tool pivoting about its tip in a divot")
    p.add_argument("--out", default="tip.yaml", help="the result: tip_mm, pivot_mm, rmse_mm, ... (YAML; default tip.yaml)")
    p.add_argument("--tool", help="with several tools in the CSV: the tool's name")
    p.add_argument("--write-tool", metavar="TOOL.yaml", help="also write the tip into this tool file (track then adds tip columns)")
    p.set_defaults(func=cmd_pivot)
