"""``markerpose eval keypoints | ellipses | pipeline | blur-distance``: a network or the
whole pipeline on the held-out test sets; markdown tables on stdout."""

from __future__ import annotations

from .common import positive_int

# What each stage-1 decoding variant is called in the tables.
_DECODING_LABEL = {
    "head": "ID head (paper)",
    "layout": "marker layout (ours)",
    "head_stereo": "ID head, stereo thresholds",
    "layout_stereo": "marker layout, stereo thresholds",
    "layout_verify": "marker layout + ring evidence (ours)",
    "layout_verify_stereo": "marker layout + ring evidence, stereo thresholds",
    "layout_verify_look": "marker layout + ring evidence + second look at 2x (ours)",
    "layout_verify_align": "marker layout + ring evidence + alignment (ours)",
    "layout_verify_align_stereo": "marker layout + ring evidence + alignment, stereo thresholds",
    "layout_verify_align_look": "marker layout + ring evidence + alignment + second look at 2x (ours)",
}


def _print_detection(res: dict) -> None:
    """Per test set and decoding: detection, IDs, accuracy, false positives, time; then
    whether the candidates held the centres at all."""
    print(
        "| test set | views | IDs from | detected (all 3 within 8 px, right IDs) | ID accuracy | median px | p95 px | false positives | s/image |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    diag = []
    for name in next(iter(res.values())):
        for mode, per_set in res.items():
            r = per_set[name]
            print(
                f"| {name} | {r['n_views'] or r['n_negatives']} | {_DECODING_LABEL[mode]} | {r['detected']:.4f} | {r['id_accuracy']:.4f} | "
                f"{r['median_px']:.2f} | {r['p95_px']:.2f} | {r['false_positive']:.4f} | {r['seconds_per_image']:.3f} |"
            )
        if r["n_views"]:
            diag.append(f"| {name} | {r['candidates_found']:.4f} | {r['id_head_right']:.4f} |")
    print("\n| test set | all 3 centres among the candidates | ID head right at all 3 (of those) |")
    print("|---|---|---|")
    print("\n".join(diag))


def _print_by_ring_size(res: dict) -> None:
    """Detection of the best decodings by the outer ring's apparent size, per test set."""
    best_modes = [m for m in ("layout_verify_align", "layout_verify_align_look") if m in res]
    best_modes = best_modes or [m for m in ("layout_verify", "layout_verify_look") if m in res] or [next(iter(res))]
    for best in best_modes:
        sizes = {name: {b["bin"]: b for b in r["by_ring_size"]} for name, r in res[best].items() if r["n_views"]}
        bins = sorted({b for s in sizes.values() for b in s}, key=lambda b: float(b.split("-")[0]))
        print(
            f"\n{_DECODING_LABEL[best]}, single view: detected by the outer ring's apparent diameter in network-input px (x4 at 1280 px wide; views)"
        )
        print("| diameter | " + " | ".join(sizes) + " |")
        print("|---|" + "---|" * len(sizes))
        for b in bins:
            cells = [f"{s[b]['detected']:.3f} ({s[b]['n_views']})" if b in s else "—" for s in sizes.values()]
            print(f"| {b} | " + " | ".join(cells) + " |")


def _width_label(w) -> str:
    return f"{w[0]:g}, first four convolutions {w[1]:g}" if isinstance(w, tuple) else f"{w:g}"


def _print_speed(tk, weights) -> dict:
    """The paper-width and the shipped network timed; the table printed, its rows returned."""
    from ..keypoints import KeypointNet

    c = KeypointNet(weights).conf
    shipped = c["width"] if c.get("stem_width") is None else (c["width"], c["stem_width"])
    sp = tk.speed((1.0,) if shipped == 1.0 else (1.0, shipped))
    print("\n| network width | parameters | forward pass, stereo pair (2 x 320x240), ms | second look, one 640x480 view, ms |")
    print("|---|---|---|---|")
    for w, r in sp.items():
        print(
            f"| {_width_label(w)}{' (paper)' if w == 1.0 else ''}{' (shipped)' if w == shipped else ''} | {r['params']:,} | {r['pair_ms']:.1f} | {r['look_ms']:.1f} |"
        )
    return {_width_label(k): v for k, v in sp.items()}


def cmd_eval_keypoints(args):
    from ..train import keypoints as tk

    unknown = sorted(set(args.decodings or ()) - set(tk.DECODINGS))
    if unknown:
        raise SystemExit(f"unknown --decodings {unknown}; choose from {sorted(tk.DECODINGS)}")
    res = tk.evaluate(
        args.weights, args.data, args.sets, args.workers, decodings=tuple(args.decodings or tk.DECODINGS), second_look=args.second_look
    )
    _print_detection(res)
    _print_by_ring_size(res)
    if args.speed:
        res["speed"] = _print_speed(tk, args.weights)
    if args.json:
        from ..formats import write_json

        write_json(args.json, res)


def cmd_eval_ellipses(args):
    from ..train import ellipses as te

    res = te.evaluate(args.weights, args.data, args.sets, args.workers)
    print(
        "| test set | patches | IoU | centre fit | found | median px (true ellipse centre) | p95 px | median px (projected 3D centre) | p95 px |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in res.items():
        for fit in ("ellipse", "moments", "subpixel"):
            f = r[fit]
            print(
                f"| {name} | {r['n']} | {r['iou_mean']:.4f} | {fit} | {f['found']:.4f} | {f['median_px']:.3f} | {f['p95_px']:.3f} | "
                f"{f['median_px_vs_3d']:.3f} | {f['p95_px_vs_3d']:.3f} |"
            )
    for name, r in res.items():
        print(f"\n{name}: median centre error (px) by condition, and the perspective bias of the same patches")
        print("| bin | patches | bias median | bias max | fitEllipse vs true | vs 3D | sub-pixel vs true | vs 3D |")
        print("|---|---|---|---|---|---|---|---|")
        for b in r["by_condition"]:
            print(
                f"| {b['bin']} | {b['n']} | {b['bias_median']:.3f} | {b['bias_max']:.3f} | {b['ellipse_median']:.3f} | "
                f"{b['ellipse_median_3d']:.3f} | {b['subpixel_median']:.3f} | {b['subpixel_median_3d']:.3f} |"
            )
    if args.json:
        from ..formats import write_json

        write_json(args.json, res)


def cmd_eval_pipeline(args):
    from ..experiments import endtoend

    conf = {"pairs": args.pairs, "configs": args.configs, "single_view": args.single_view, "workers": args.workers}
    if args.sets:
        conf["sets"] = tuple(args.sets)
    res = endtoend.main(conf, args.json, progress=not args.quiet)
    print(endtoend.report(res))


def cmd_eval_blur_distance(args):
    from ..experiments import blurdistance

    conf = {"pairs": args.pairs, "path_poses": args.path_poses, "tight_margin": args.tight_margin}
    if args.lengths:
        conf["lengths"] = tuple(args.lengths)
    if args.configs:
        conf["configs"] = tuple(args.configs)
    res = blurdistance.main(conf, args.out, progress=not args.quiet)
    print(blurdistance.report(res))
    print(f"Wrote {args.out}/: report.md, results.json, blur-distance.png")


def cmd_eval_tools(args):
    from ..experiments import tools

    conf = {"pairs": args.pairs, "free": args.free, "tools": args.tools, "frames": args.frames, "speed_pairs": args.speed_pairs}
    if args.configs:
        conf["configs"] = tuple(args.configs)
    res = tools.main(conf, args.out, progress=not args.quiet)
    print(tools.report(res))
    print(f"Wrote {args.out}/: report.md, results.json" + (", tools.mp4, tools-video.png" if "video" in res else ""))


def _experiment(name: str, keys: tuple):
    """The handler of ``markerpose eval NAME``: the experiment module's ``main`` with the
    options ``keys`` as its settings, its report printed, its folder written."""

    def run(args):
        import importlib

        mod = importlib.import_module(f"..experiments.{name}", __package__)
        res = mod.main({k: getattr(args, k) for k in keys}, args.out, progress=not args.quiet)
        print(mod.report(res))
        print(f"Wrote {args.out}/: report.md, results.json")

    return run


def _add_experiment(esub, name: str, module: str, help: str, options: list) -> None:
    """``markerpose eval NAME``: the experiment ``module``'s settings ``options`` (dest,
    type, default, help) as options, ``--out`` (default markerpose-NAME) and ``--quiet``."""
    p = esub.add_parser(name, help=help)
    for dest, kind, default, text in options:
        p.add_argument(f"--{dest.replace('_', '-')}", dest=dest, type=kind, default=default, help=f"{text} (default {default:g})")
    p.add_argument("--out", default=f"markerpose-{name}", help="output folder: report.md, results.json")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_experiment(module, tuple(o[0] for o in options)))


def _eval_args(p, what: str):
    p.add_argument("--weights", help=f"{what} checkpoint (default: the shipped weights)")
    p.add_argument("--data", default="runs/data", help="cache of rendered sets")
    p.add_argument("--sets", nargs="*", help="subset of the test sets")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="also write the metrics as JSON")


def _register_networks(esub) -> None:
    ek = esub.add_parser("keypoints", help="stage 1 on the held-out sets (standard, dark, blur, negatives)")
    _eval_args(ek, "stage-1")
    ek.add_argument("--speed", action="store_true", help="also time the paper-width and the shipped network")
    ek.add_argument("--decodings", nargs="*", help="decoding variants (default: all): head layout layout_verify layout_verify_align")
    ek.add_argument("--second-look", type=float, default=2.0, help="zoom of the second look of the variants that have one (1 = none)")
    ek.set_defaults(func=cmd_eval_keypoints)
    ee = esub.add_parser("ellipses", help="stage 2 on the held-out patch sets (standard, dark, blur)")
    _eval_args(ee, "EllipSegNet")
    ee.set_defaults(func=cmd_eval_ellipses)


def _register_pipeline(esub) -> None:
    ep = esub.add_parser("pipeline", help="end to end on held-out stereo pairs: detection, centres, pose, per configuration")
    ep.add_argument("--pairs", type=int, default=200, help="pairs per set")
    ep.add_argument(
        "--sets",
        nargs="*",
        help="standard, dark_0.0625, blur_25, marker_free (the default), far (0.8-1.6 m), and realism (the nine realism_<effect> sets: shadow, light_gradient, defocus, gamma, jpeg, resample, toner, occluded_border, ring_object)",
    )
    ep.add_argument(
        "--configs", nargs="*", help="configuration names: presets or ablations, markerpose.experiments.configs (default: all available)"
    )
    ep.add_argument(
        "--single-view",
        action="store_true",
        help="also each view alone (tracker.detect): all three centres within the tolerance, right IDs",
    )
    ep.add_argument(
        "--workers", type=int, default=1, help="sets at once on Ray where it is installed (one thread each; figures unchanged; default 1)"
    )
    ep.add_argument("--json", help="also write the figures as JSON")
    ep.add_argument("--quiet", action="store_true")
    ep.set_defaults(func=cmd_eval_pipeline)
    eb = esub.add_parser(
        "blur-distance", help="the distances c0-c1 and c0-c2 under motion blur along c0-c1, per blur length and configuration; a robot path"
    )
    eb.add_argument("--pairs", type=positive_int, default=40, help="poses, each rendered at every blur length (default 40)")
    eb.add_argument("--lengths", type=float, nargs="+", help="blur lengths, px (default 0 5 9 13 17 21 25)")
    eb.add_argument(
        "--path-poses",
        type=int,
        default=20,
        help="also a robot path of this many poses 10 mm apart along c0 -> c1 at 560 mm, blurred in both views along the "
        "left view's travel (0: none; default 20)",
    )
    eb.add_argument(
        "--tight-margin",
        type=float,
        default=3.0,
        help="also the path with the plate this many mm beyond the rings' outer edges, on a dark ground (0: not; default 3)",
    )
    eb.add_argument(
        "--configs", nargs="*", help="configuration names: presets or ablations, markerpose.experiments.configs (default: default paper)"
    )
    eb.add_argument("--out", default="markerpose-blur-distance", help="output folder: report.md, results.json, blur-distance.png")
    eb.add_argument("--quiet", action="store_true")
    eb.set_defaults(func=cmd_eval_blur_distance)
    et = esub.add_parser("tools", help="several tools at once: held-out pairs with 2-4 tools, a tracked 3-tool video, the speed")
    et.add_argument("--pairs", type=positive_int, default=100, help="pairs with tools (default 100)")
    et.add_argument("--free", type=int, default=50, help="marker-free pairs (default 50)")
    et.add_argument("--tools", type=int, default=4, help="the tool set's size, 2 to 6; each pair shows 2 to this many (default 4)")
    et.add_argument("--frames", type=int, default=120, help="pairs of the 3-tool video (0: none; default 120)")
    et.add_argument("--speed-pairs", type=int, default=20, help="cold pairs timed (0: no timing; default 20)")
    et.add_argument("--configs", nargs="*", help="presets (default: default classical; the paper's decoded detector takes one marker)")
    et.add_argument("--out", default="markerpose-tools", help="output folder: report.md, results.json, tools.mp4, tools-video.png")
    et.add_argument("--quiet", action="store_true")
    et.set_defaults(func=cmd_eval_tools)
    experiments = (
        ("uncertainty", "uncertainty", "is Estimate.cov calibrated: chi-square coverage of the true errors per condition",
         [("pairs", positive_int, 60, "pairs per condition"),
          ("model_pairs", int, 60, "pairs (of their own) for the centres' error their fits do not show (0: none)")]),
        ("pivot", "pivot", "pivot calibration against the truth: simulated pivoting with noise and outliers, a rendered sequence",
         [("trials", positive_int, 20, "simulated calibrations per tracker noise"),
          ("frames", int, 120, "pairs of the rendered pivoting sequence (0: none)")]),
        ("handeye", "handeye", "hand-eye calibration against the truth: simulated eye-to-hand and eye-in-hand sessions",
         [("trials", positive_int, 50, "simulated sessions per setup and number of poses")]),
        ("rigcheck", "rigcheck", "the rig check on rendered sequences: a stable rig (false alarms), a right camera turned or shifted",
         [("stable", positive_int, 200, "pairs of the stable rig per condition"),
          ("before", positive_int, 10, "pairs before the change"),
          ("after", positive_int, 30, "pairs after the change")]),
        ("sync", "sync", "cameras not synchronised: a rendered hand-held video with the right view 0-33 ms late, compensated and not",
         [("frames", positive_int, 90, "frames per delay, at 30 frames/s")]),
        ("batch", "batch", "many recordings: track one after the other against batch, serial and on a local Ray, timed in one run",
         [("recordings", positive_int, 8, "rendered recordings"),
          ("frames", positive_int, 120, "pairs per recording"),
          ("workers", positive_int, 2, "the local Ray's workers")]),
        ("faults", "faults", "a seeded fault campaign: bad rig files, settings, images, folders, CSVs and numbers, each class in its own process",
         [("cases", positive_int, 45, "cases per class (eight classes)")]),
        ("temporal", "ultrasound.temporal",
         "the ultrasound-to-tracker delay on a simulated session (probe up and down over a plate), 0-150 ms",
         [("seconds", float, 6.0, "length of the session, s")]),
    )  # fmt: skip
    for name, module, text, options in experiments:
        _add_experiment(esub, name, module, text, options)


def register(sub) -> None:
    ev = sub.add_parser("eval", help="evaluate a network on the held-out test sets")
    esub = ev.add_subparsers(dest="what", required=True)
    _register_networks(esub)
    _register_pipeline(esub)
