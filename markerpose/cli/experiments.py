"""``markerpose experiments``: the paper's Section 5 with confidence intervals."""

from __future__ import annotations


def cmd_experiments(args):
    from ..experiments import reproduce

    conf = dict(reproduce.QUICK) if args.quick else {}
    for key in ("trials", "pairs", "seed"):
        if getattr(args, key) is not None:
            conf[key] = getattr(args, key)
    if args.configs:
        conf["configs"] = tuple(args.configs)
    reproduce.main(conf, args.out, progress=not args.quiet)


def register(sub) -> None:
    x = sub.add_parser("experiments", help="the paper's Section 5 with confidence intervals: report, plots, JSON")
    x.add_argument("--quick", action="store_true", help="2 trials, 6 pairs per level, Table 5 at 3 darkness levels (~5 min)")
    x.add_argument("--trials", type=int, help="robot-path placements (default 8)")
    x.add_argument("--pairs", type=int, help="random pairs per darkness / blur level (default 48)")
    x.add_argument("--seed", type=int, help="base seed (default 0)")
    x.add_argument(
        "--configs",
        nargs="*",
        help="configuration names: presets or ablations, markerpose.experiments.configs (default: the headline ones that can run)",
    )
    x.add_argument("--out", default="markerpose-experiments", help="output folder (default: markerpose-experiments)")
    x.add_argument("--quiet", action="store_true")
    x.set_defaults(func=cmd_experiments)
