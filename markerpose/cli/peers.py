"""``markerpose peers``: markerpose beside AprilTag 3, ArUco, ChArUco and STag."""

from __future__ import annotations

import time

from .common import positive_int


def cmd_peers(args):
    from ..peers import experiment

    t0 = time.perf_counter()
    cmd = "markerpose peers" + (" --quick" if args.quick else "") + f" --out {args.out}"
    if args.pairs is not None:
        cmd += f" --pairs {args.pairs}"
    if args.systems:
        cmd += " --systems " + " ".join(args.systems)
    if args.seed:
        cmd += f" --seed {args.seed}"
    if args.no_tuned:
        cmd += " --no-tuned"
    conf = experiment.plan(
        args.quick, pairs=args.pairs, seed=args.seed, systems=tuple(args.systems) if args.systems else None, tuned=not args.no_tuned
    )
    if args.spread:
        from pathlib import Path

        from ..formats import write_json

        cmd += f" --spread {args.spread}"
        res = experiment.spread(conf, args.spread, jobs=args.jobs, progress=not args.quiet)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "spread.json", res)
        (out / "spread.md").write_text(experiment.spread_markdown(res, cmd))
        print(experiment.spread_markdown(res, cmd))
        print(f"wrote {out / 'spread.md'} and spread.json ({time.perf_counter() - t0:.0f} s)")
        return
    doc = experiment.main(conf, args.out, jobs=args.jobs, command=cmd, progress=not args.quiet)
    print(f"wrote {doc['files'][0]} and the plots and results.json beside it ({time.perf_counter() - t0:.0f} s)")


def register(sub) -> None:
    pe = sub.add_parser("peers", help="markerpose beside AprilTag 3, ArUco, ChArUco and STag on the same rendered scenes")
    pe.add_argument("--out", default="markerpose-peers", help="output folder (default: markerpose-peers)")
    pe.add_argument("--quick", action="store_true", help="6 scenes per level instead of 40 (a few minutes)")
    pe.add_argument("--pairs", type=positive_int, help="scenes per darkness / blur level (default 40; --quick 6)")
    pe.add_argument(
        "--systems",
        nargs="+",
        choices=("markerpose", "apriltag", "apriltag-defaults", "aruco", "aruco-defaults", "charuco", "charuco-defaults", "stag"),
        help="systems to run (default: all installed)",
    )
    pe.add_argument(
        "--no-tuned",
        action="store_true",
        help="leave out the peers' further settings (AprilTag's decimation, sigma and sharpening, ArUco's refinements and "
        "thresholds, ChArUco's marker refinement, STag's error correction) and the best-per-condition section",
    )
    pe.add_argument("--seed", type=int, default=0)
    pe.add_argument(
        "--spread",
        type=positive_int,
        metavar="SEEDS",
        help="instead: the standard level under SEEDS seeds, each system's median position error per seed and "
        "markerpose's lead over the best peer with its spread (spread.md, spread.json)",
    )
    pe.add_argument("--jobs", type=positive_int, help="Ray workers (default: every core; 1: in this process)")
    pe.add_argument("--quiet", action="store_true", help="no progress bar")
    pe.set_defaults(func=cmd_peers)
