"""``markerpose bench``: the pipeline's speed per configuration; or a rendered video
(``--sequence``) or the marker put down elsewhere between two frames (``--jumps``)."""

from __future__ import annotations


def cmd_bench(args):
    if args.sequence and args.jumps:
        raise ValueError("--sequence and --jumps are two runs: choose one")
    seed = {} if args.seed is None else {"seed": args.seed}
    if args.sequence:
        from ..experiments import sequence

        out = args.out or "markerpose-sequence"
        conf = {
            "frames": args.frames,
            "threads": args.threads,
            "passes": args.passes,
            "pace": not args.no_pace,
            "preset": args.preset,
            **seed,
        }
        res = sequence.main(conf, out, progress=not args.quiet)
        print(sequence.report(res))
        print(f"Wrote {out}/: report.md, results.json, sequence.png")
        return
    if args.jumps:
        from ..experiments import jumps

        out = args.out or "markerpose-jumps"
        res = jumps.main({"trials": args.trials, "threads": args.threads, **seed}, out, progress=not args.quiet)
        print(jumps.report(res))
        print(f"Wrote {out}/: report.md, results.json")
        return
    from ..experiments import bench

    conf = {
        "pairs": args.pairs,
        "blurred_pairs": args.blurred_pairs,
        "empty_pairs": args.empty_pairs,
        "repeats": args.repeats,
        "threads": args.threads,
        "configs": args.configs,
    }
    res = bench.main(conf, args.json, progress=not args.quiet)
    print(bench.report(res))


def register(sub) -> None:
    b = sub.add_parser("bench", help="speed of the stereo pipeline per configuration (interleaved, same frames)")
    b.add_argument("--pairs", type=int, default=8, help="rendered stereo pairs")
    b.add_argument("--blurred-pairs", type=int, default=4, help="pairs with 25 px motion blur (timed apart)")
    b.add_argument("--empty-pairs", type=int, default=4, help="marker-free pairs (time while the marker is out of view)")
    b.add_argument("--repeats", type=int, default=3, help="passes over the pairs (the first warms up)")
    b.add_argument("--threads", type=int, help="torch threads (default: all cores)")
    b.add_argument(
        "--configs", nargs="*", help="configuration names: presets or ablations, markerpose.experiments.configs (default: all available)"
    )
    b.add_argument("--json", help="also write the figures as JSON")
    b.add_argument(
        "--sequence",
        action="store_true",
        help="instead: a rendered 60 frames/s stereo video (still, by hand, fast, gone, dark), tracked and detected",
    )
    b.add_argument("--frames", type=int, default=240, help="--sequence: frames (default 240: four seconds)")
    b.add_argument(
        "--jumps",
        action="store_true",
        help="instead: the marker put down elsewhere between two frames, tracked with and without the search near the prediction",
    )
    b.add_argument("--trials", type=int, default=120, help="--jumps: trials (default 120; --threads, --seed and --out apply too)")
    b.add_argument("--seed", type=int, help="--sequence / --jumps: seed of the rendering (default 0 / 11)")
    b.add_argument(
        "--preset",
        default="default",
        help="--sequence: the configuration (a preset or an ablation) of track and estimate (default: default)",
    )
    b.add_argument(
        "--passes",
        type=int,
        default=2,
        help="--sequence: passes over the sequence per method, in alternating order (default 2; the statistics pool them)",
    )
    b.add_argument(
        "--no-pace", action="store_true", help="--sequence: hand the frames over back to back instead of at the stream's 60 frames/s"
    )
    b.add_argument("--out", help="--sequence / --jumps: output folder (default markerpose-sequence / markerpose-jumps)")
    b.add_argument("--quiet", action="store_true")
    b.set_defaults(func=cmd_bench)
