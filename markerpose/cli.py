"""Command-line interface: thin commands over the package's functions."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .jit import CompileError
from .formats import dumps, write_json
from .presets import ORDER

EXIT_NOT_FOUND = 1
EXIT_BAD_INPUT = 2


def _rig(path):
    from .camera import StereoRig

    return StereoRig.default() if path is None else StereoRig.load(path)


def _marker(args):
    from .marker import Marker

    return Marker(
        outer_diameter=args.outer_diameter,
        inner_diameter=args.inner_diameter,
        c1=(args.c1, 0.0),
        c2=(0.0, args.c2),
        margin=args.margin,
    )


def _add_marker_args(p):
    g = p.add_argument_group("marker geometry (mm)")
    g.add_argument("--outer-diameter", type=float, default=20.0, help="black ring diameter (default 20)")
    g.add_argument("--inner-diameter", type=float, default=8.0, help="white inner disk diameter (default 8)")
    g.add_argument("--c1", type=float, default=25.0, help="distance c0→c1 along x (default 25)")
    g.add_argument("--c2", type=float, default=40.0, help="distance c0→c2 along y (default 40)")
    g.add_argument("--margin", type=float, default=10.0, help="plate margin around the rings (default 10)")


def cmd_demo(args):
    from .experiments import demo

    t0 = time.perf_counter()
    demo.main({"seed": args.seed, "alpha": args.alpha}, args.out, progress=not args.quiet)
    print(f"demo finished in {time.perf_counter() - t0:.1f} s")


def cmd_marker(args):
    from .marker import write_target

    path = write_target(_marker(args), args.out, paper=args.paper)
    print(f"wrote {path} ({args.paper}); print at 100% and check the 50 mm scale bar with a ruler")


def cmd_render(args):
    import cv2

    from .synth import Imaging, look_at_pose, render_stereo

    if args.repeat < 1:
        raise ValueError(f"--repeat must be >= 1, got {args.repeat}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    rig, marker = _rig(args.rig), _marker(args)
    T = look_at_pose([args.x, args.y, args.distance], args.tilt, args.tilt_axis, args.roll)
    imaging = Imaging(alpha=args.alpha, motion_blur=args.motion_blur, motion_angle=args.motion_angle)
    times = []
    for k in range(args.repeat):
        t0 = time.perf_counter()
        frame = render_stereo(rig, T, marker, imaging, seed=args.seed + k)
        times.append(time.perf_counter() - t0)
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "left.png"), frame.images[0])
    cv2.imwrite(str(out / "right.png"), frame.images[1])
    truth = {
        "T_left_marker": frame.T_left_marker.tolist(),
        "centers": [v.centers.tolist() for v in frame.views],
        "outer_ellipse_centers": [v.outer_centers.tolist() for v in frame.views],
    }
    write_json(out / "truth.json", truth)
    print(f"wrote {out}/left.png, right.png, truth.json")
    if args.repeat > 1:
        # The first call also builds each camera's undistortion grid (cached afterwards).
        print(f"render time per 1280x1024 stereo pair: median {np.median(times[1:]):.3f} s over {args.repeat - 1} "
              f"(first call {times[0]:.3f} s, builds the cached ray grid)")


def read_image(path) -> np.ndarray:
    """An image file as a numpy array, or ValueError naming the file (no OpenCV warning)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cannot read image {path}: no such file")
    img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot read image {path}: not an image format OpenCV can decode")
    return img


def cmd_estimate(args):
    tracker = _tracker(args)
    images = [read_image(p) for p in (args.left, args.right)]
    est = tracker.estimate(*images)
    if est is None:
        print(dumps({"found": False}, None))
        return EXIT_NOT_FOUND
    print(dumps({"found": True, "T_left_marker": est.T, "points3d": est.points3d, "centers": est.centers,
                 "residual_px": est.residual_px}))
    return 0


def _grid(args):
    from .calibration import CircleGrid

    try:
        cols, rows = (int(v) for v in str(args.grid).lower().split("x"))
    except ValueError:
        raise ValueError(f"--grid must be COLSxROWS (e.g. 4x11), got {args.grid!r}") from None
    return CircleGrid(cols, rows, args.spacing, args.diameter)


def cmd_pattern(args):
    from .marker import write_grid

    path = write_grid(_grid(args), args.out, paper=args.paper)
    print(f"wrote {path} ({args.paper}); print at 100% and check the 50 mm scale bar with a ruler")


def cmd_calibrate(args):
    from .calibration import calibrate, check, plot_coverage, rendered_pairs

    grid = _grid(args)
    if args.rendered:
        truth = _rig(None)
        pairs, _ = rendered_pairs(truth, grid, args.rendered, args.seed)
        names = list(range(len(pairs)))
    else:
        if not (args.left and args.right):
            raise ValueError("calibrate needs LEFT and RIGHT (image folders or videos), or --rendered N")
        from .video import open_stereo

        stream = open_stereo(args.left, args.right)
        try:
            pairs = [(a, b) for _, _, a, b in stream]
        finally:
            stream.close()
        names = list(range(len(pairs)))
    cal = calibrate(pairs, grid, names)
    out = Path(args.out)
    cal.rig.save(out)
    s = cal.summary()
    print(f"wrote {out}: {s['pairs_used']} pairs used ({len(s['pairs_rejected'])} rejected: {s['pairs_rejected'][:10]}); "
          f"RMS reprojection error left {s['rms_left_px']:.3f} px, right {s['rms_right_px']:.3f} px, stereo {s['rms_stereo_px']:.3f} px; "
          f"baseline {s['baseline_mm']:.2f} mm")
    if args.coverage:
        print(f"wrote {plot_coverage(cal, args.coverage)}: where the grid was seen in each image")
    if args.rendered:
        c = check(truth, cal)
        print("against the rig that rendered the images: focal lengths within "
              f"{100 * max(c['f_left_rel_error'], c['f_right_rel_error']):.4f} %, principal points within "
              f"{max(c['c_left_px_error'], c['c_right_px_error']):.2f} px, baseline within {c['baseline_mm_error']:.4f} mm, "
              f"rotation within {c['R_deg_error']:.4f}°")
    if max(s["rms_left_px"], s["rms_right_px"]) > 0.5:
        print("warning: RMS reprojection error above 0.5 px: check focus, motion blur, a flat print and the --grid/--spacing", file=sys.stderr)


def cmd_track(args):
    from .video import IGTLSender, ShowSink, VideoSink, open_stereo, track_stream

    tracker = _tracker(args)
    stream = open_stereo(args.left, args.right, args.fps)
    sinks = []
    try:
        if args.show:
            sinks.append(ShowSink(tracker.rig))
        if args.video:
            sinks.append(VideoSink(args.video, tracker.rig, stream.fps or args.fps))
    except ValueError:
        stream.close()
        raise
    send = None
    if args.igtl is not None:
        try:
            send = IGTLSender(args.igtl, args.igtl_name, local_only=not args.igtl_public)
        except ValueError:
            stream.close()
            raise
        print(f"OpenIGTLink: serving TRANSFORM {args.igtl_name!r} on port {args.igtl}", file=sys.stderr)
    try:
        s = track_stream(tracker, stream, args.out, args.jsonl, progress=not args.quiet, send=send, sinks=tuple(sinks))
    finally:
        if send is not None:
            send.close()
        for sink in sinks:
            sink.close()
    print(f"{'stopped: ' if s['stopped'] else ''}{s['frames']} frames, marker found in {100 * s['found']:.1f} % "
          f"({100 * s['tracked']:.0f} % of those tracked), {s['fps']:.1f} frames/s, longest gap {s['longest_gap']} frames; "
          f"wrote {s['csv']}" + (f" and {args.jsonl}" if args.jsonl else ""))


def cmd_bench(args):
    if args.sequence and args.jumps:
        raise ValueError("--sequence and --jumps are two runs: choose one")
    seed = {} if args.seed is None else {"seed": args.seed}
    if args.sequence:
        from .experiments import sequence

        out = args.out or "markerpose-sequence"
        conf = {"frames": args.frames, "threads": args.threads, "passes": args.passes, "pace": not args.no_pace, "preset": args.preset, **seed}
        res = sequence.main(conf, out, progress=not args.quiet)
        print(sequence.report(res))
        print(f"Wrote {out}/: report.md, results.json, sequence.png")
        return
    if args.jumps:
        from .experiments import jumps

        out = args.out or "markerpose-jumps"
        res = jumps.main({"trials": args.trials, "threads": args.threads, **seed}, out, progress=not args.quiet)
        print(jumps.report(res))
        print(f"Wrote {out}/: report.md, results.json")
        return
    from .experiments import bench

    conf = {"pairs": args.pairs, "blurred_pairs": args.blurred_pairs, "empty_pairs": args.empty_pairs, "repeats": args.repeats, "threads": args.threads, "configs": args.configs}
    res = bench.main(conf, args.json, progress=not args.quiet)
    print(bench.report(res))


def cmd_experiments(args):
    from .experiments import reproduce

    conf = dict(reproduce.QUICK) if args.quick else {}
    for key in ("trials", "pairs", "seed"):
        if getattr(args, key) is not None:
            conf[key] = getattr(args, key)
    if args.configs:
        conf["configs"] = tuple(args.configs)
    reproduce.main(conf, args.out, progress=not args.quiet)


def _need_torch():
    import importlib.util

    for name in ("torch", "onnx"):
        if importlib.util.find_spec(name) is None:
            raise ValueError(f"training needs {name}: pip install -e \".[train]\" (on a CPU machine, torch from the CPU index first; see the README)")


def _train(module, args, keys: tuple, **export_kw):
    conf = {k: getattr(args, k) for k in keys}
    t0 = time.perf_counter()
    best = module.main(conf, args.out, resume=args.resume, data_dir=args.data)
    print(f"best checkpoint: {best} ({(time.perf_counter() - t0) / 60:.1f} min)")
    if args.export:
        dest = module.export(best, args.export, **export_kw)
        print(f"exported the weights to {dest} and {dest.with_suffix('.onnx')}")


_TRAIN_KEYS = ("lr", "schedule", "epochs", "batch_size", "train_size", "val_size", "seed", "workers", "device", "init")


def cmd_train_keypoints(args):
    if args.int8:  # no training: an int8 copy of ONNX weights (needs onnx, not torch)
        import importlib.util

        if importlib.util.find_spec("onnx") is None:
            raise ValueError("--int8 needs onnx: pip install -e \".[train]\"")
        from .train import keypoints

        src, dest = args.int8
        t0 = time.perf_counter()
        out = keypoints.quantize(src, dest, args.int8_images, args.workers)
        print(f"wrote the int8 copy of {src} to {out} ({(time.perf_counter() - t0) / 60:.1f} min)")
        return
    _need_torch()
    from .train import keypoints

    if args.retune:  # no training: the checkpoint's decoding thresholds tuned afresh
        if not args.export:
            raise SystemExit("--retune needs --export (where to write the re-tuned weights)")
        t0 = time.perf_counter()
        dest = keypoints.export(args.retune, args.export, data_dir=args.data, val_size=args.val_size, negatives=args.val_negatives)
        print(f"exported the weights to {dest} and {dest.with_suffix('.onnx')} ({(time.perf_counter() - t0) / 60:.1f} min)")
        return
    _train(keypoints, args, ("width", "stem_width", "background_weight", "steep_size", "small_boost", "window") + _TRAIN_KEYS, data_dir=args.data, val_size=args.val_size,
           negatives=args.val_negatives)


def cmd_train_ellipses(args):
    _need_torch()
    from .train import ellipses

    _train(ellipses, args, _TRAIN_KEYS)


def cmd_eval_ellipses(args):
    from .train import ellipses as te

    res = te.evaluate(args.weights, args.data, args.sets, args.workers)
    print("| test set | patches | IoU | centre fit | found | median px (true ellipse centre) | p95 px | median px (projected 3D centre) | p95 px |")
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
        write_json(args.json, res)


def cmd_eval_pipeline(args):
    from .experiments import endtoend

    conf = {"pairs": args.pairs, "configs": args.configs, "single_view": args.single_view, "workers": args.workers}
    if args.sets:
        conf["sets"] = tuple(args.sets)
    res = endtoend.main(conf, args.json, progress=not args.quiet)
    print(endtoend.report(res))


def cmd_eval_blur_distance(args):
    from .experiments import blurdistance

    conf = {"pairs": args.pairs}
    if args.lengths:
        conf["lengths"] = tuple(args.lengths)
    if args.configs:
        conf["configs"] = tuple(args.configs)
    res = blurdistance.main(conf, args.out, progress=not args.quiet)
    print(blurdistance.report(res))
    print(f"Wrote {args.out}/: report.md, results.json, blur-distance.png")


def cmd_eval_keypoints(args):
    from .train import keypoints as tk

    unknown = sorted(set(args.decodings or ()) - set(tk.DECODINGS))
    if unknown:
        raise SystemExit(f"unknown --decodings {unknown}; choose from {sorted(tk.DECODINGS)}")
    res = tk.evaluate(args.weights, args.data, args.sets, args.workers, decodings=tuple(args.decodings or tk.DECODINGS),
                      second_look=args.second_look)
    label = {
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
    print("| test set | views | IDs from | detected (all 3 within 8 px, right IDs) | ID accuracy | median px | p95 px | false positives | s/image |")
    print("|---|---|---|---|---|---|---|---|---|")
    diag = []
    for name in next(iter(res.values())):
        for mode, per_set in res.items():
            r = per_set[name]
            print(
                f"| {name} | {r['n_views'] or r['n_negatives']} | {label[mode]} | {r['detected']:.4f} | {r['id_accuracy']:.4f} | "
                f"{r['median_px']:.2f} | {r['p95_px']:.2f} | {r['false_positive']:.4f} | {r['seconds_per_image']:.3f} |"
            )
        if r["n_views"]:
            diag.append(f"| {name} | {r['candidates_found']:.4f} | {r['id_head_right']:.4f} |")
    print("\n| test set | all 3 centres among the candidates | ID head right at all 3 (of those) |")
    print("|---|---|---|")
    print("\n".join(diag))
    best_modes = [m for m in ("layout_verify_align", "layout_verify_align_look") if m in res]
    best_modes = best_modes or [m for m in ("layout_verify", "layout_verify_look") if m in res] or [next(iter(res))]
    for best in best_modes:
        sizes = {name: {b["bin"]: b for b in r["by_ring_size"]} for name, r in res[best].items() if r["n_views"]}
        bins = sorted({b for s in sizes.values() for b in s}, key=lambda b: float(b.split("-")[0]))
        print(f"\n{label[best]}, single view: detected by the outer ring's apparent diameter in network-input px (x4 at 1280 px wide; views)")
        print("| diameter | " + " | ".join(sizes) + " |")
        print("|---|" + "---|" * len(sizes))
        for b in bins:
            cells = [f"{s[b]['detected']:.3f} ({s[b]['n_views']})" if b in s else "—" for s in sizes.values()]
            print(f"| {b} | " + " | ".join(cells) + " |")
    if args.speed:
        from .keypoints import KeypointNet

        c = KeypointNet(args.weights).conf
        shipped = c["width"] if c.get("stem_width") is None else (c["width"], c["stem_width"])
        sp = tk.speed((1.0,) if shipped == 1.0 else (1.0, shipped))

        def label(w):
            return f"{w[0]:g}, first four convolutions {w[1]:g}" if isinstance(w, tuple) else f"{w:g}"

        print("\n| network width | parameters | forward pass, stereo pair (2 x 320x240), ms | second look, one 640x480 view, ms |")
        print("|---|---|---|---|")
        for w, r in sp.items():
            print(f"| {label(w)}{' (paper)' if w == 1.0 else ''}{' (shipped)' if w == shipped else ''} | {r['params']:,} | {r['pair_ms']:.1f} | {r['look_ms']:.1f} |")
        res["speed"] = {label(k): v for k, v in sp.items()}
    if args.json:
        write_json(args.json, res)


def _add_train_args(p, name: str, batch: int, size: int, unit: str):
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (default: the paper's 1e-4)")
    p.add_argument("--schedule", default="constant", choices=["constant", "cosine"], help="constant (paper) or cosine decay")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=batch)
    p.add_argument("--train-size", type=int, default=size, help=f"rendered training {unit}, cached")
    p.add_argument("--val-size", type=int, default=400)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="processes rendering the data")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    p.add_argument("--out", default=f"runs/{name}", help="checkpoints and history")
    p.add_argument("--data", default="runs/data", help="cache of rendered sets")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init", help="start from the weights of this checkpoint (fine-tuning) instead of at random")
    p.add_argument("--export", help="also write the best weights, slimmed, to this path")


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, got {n}")
    return n


TOP_LEVEL = ("detector", "threads", "backend")  # settings of the whole pipeline, not of a stage


def _setting(text: str) -> tuple[str, str | None, object]:
    """``STAGE.KEY=VALUE`` (or ``KEY=VALUE`` for ``detector`` / ``threads`` / ``backend``) →
    (stage or key, key or None, value); the value is read as JSON (numbers, true, false,
    null, lists), anything else as a string."""
    import json

    name, sep, raw = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected STAGE.KEY=VALUE (e.g. track.lost_change=0), got {text!r}")
    try:
        value = json.loads(raw)
    except ValueError:
        value = raw
    stage, dot, key = name.partition(".")
    return (stage, key, value) if dot else (stage, None, value)


def _checked(stage: str, key: str, value, default):
    """``value`` if it has the type of the setting's ``default``, else ``ValueError``: a
    switch takes true or false (JSON's; ``False`` would be a string, and true), a number a
    number, a name a string; a setting whose default is None takes anything."""
    if isinstance(default, bool):
        ok, want = isinstance(value, bool), "true or false"
    elif isinstance(default, (int, float)):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
        want = "a finite number"
    elif isinstance(default, str):
        ok, want = isinstance(value, str), "a string"
    else:  # None: a weights file, a budget, ...
        return value
    if not ok:
        raise ValueError(f"--set {stage}.{key}: expected {want}, got {value!r}")
    return value


def _overrides(settings: list | None) -> dict:
    """--set settings → MarkerPose's overrides: one dict per stage, and top-level keys;
    ``ValueError`` (one line) for an unknown stage or setting, or a value of the wrong type."""
    from .presets import default_conf

    out: dict = {}
    for stage, key, value in settings or ():
        if stage in TOP_LEVEL:
            if key is not None:
                raise ValueError(f"--set {stage}.{key}: {stage} takes a value, e.g. --set {stage}=...")
            out[stage] = value
            continue
        if stage not in default_conf:
            known = [k for k in default_conf if k not in TOP_LEVEL]
            raise ValueError(f"--set {stage}{'.' + key if key else ''}: unknown stage {stage!r}; stages: {known}")
        if key is None:
            raise ValueError(f"--set {stage}: expected {stage}.KEY=VALUE")
        if key not in default_conf[stage]:
            raise ValueError(f"--set {stage}.{key}: unknown {stage} setting; known: {sorted(default_conf[stage])}")
        out.setdefault(stage, {})[key] = _checked(stage, key, value, default_conf[stage][key])
    return out


def _tracker(args):
    """The MarkerPose of a command's --rig, marker, --preset / --detector and --set."""
    from .pipeline import MarkerPose

    overrides = _overrides(args.settings)
    detector = overrides.pop("detector", args.detector)
    return MarkerPose(_rig(args.rig), _marker(args), preset=args.preset, detector=detector, **overrides)


def _add_set_arg(p) -> None:
    p.add_argument("--set", dest="settings", action="append", type=_setting, metavar="STAGE.KEY=VALUE",
                   help="a stage setting over the preset (README: stage settings), e.g. track.lost_change=0 or "
                        "match.max_fits=5; also threads=N, backend=NAME, detector=NAME; repeatable")


def _pixel(text: str) -> tuple[float, float]:
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers A,B, got {text!r}") from None
    return u, v


def cmd_ultrasound_demo(args):
    from .ultrasound import experiment

    t0 = time.perf_counter()
    cmd = "markerpose ultrasound demo" + (" --quick" if args.quick else "") + f" --out {args.out}"
    if args.acquisitions is not None:
        cmd += f" --acquisitions {args.acquisitions}"
    path = experiment.main(args.out, quick=args.quick, seed=args.seed, jobs=args.jobs, acquisitions=args.acquisitions,
                           progress=not args.quiet, command=cmd)
    print(f"wrote {path} and the plots and files beside it ({time.perf_counter() - t0:.0f} s)")


def cmd_peers(args):
    from .peers import experiment

    t0 = time.perf_counter()
    cmd = "markerpose peers" + (" --quick" if args.quick else "") + f" --out {args.out}"
    if args.pairs is not None:
        cmd += f" --pairs {args.pairs}"
    if args.systems:
        cmd += " --systems " + " ".join(args.systems)
    conf = experiment.plan(args.quick, pairs=args.pairs, seed=args.seed, systems=tuple(args.systems) if args.systems else None)
    doc = experiment.main(conf, args.out, jobs=args.jobs, command=cmd, progress=not args.quiet)
    print(f"wrote {doc['files'][0]} and the plots and results.json beside it ({time.perf_counter() - t0:.0f} s)")


def cmd_ultrasound_reconstruct(args):
    from .ultrasound.recording import reconstruct_recording

    s = reconstruct_recording(args.poses, args.images, args.calibration, args.out, seed_px=args.seed, fps=args.fps,
                              time_offset_s=args.time_offset, max_gap_s=args.max_gap, voxel_mm=args.voxel_mm,
                              progress=not args.quiet)
    print(f"{s['frames_with_pose']} of {s['frames']} frames with a pose; wrote {', '.join(s['files'])} into {args.out}")
    if "cylinder" in s:
        c = s["cylinder"]
        print(f"cylinder: diameter {c['diameter_mm']:.3f} mm, RMS {c['rms_mm']:.3f} mm, {c['inliers']} of {c['points']} points")


def cmd_ultrasound_calibrate(args):
    from .ultrasound.recording import calibrate_recording

    _, rep = calibrate_recording(args.poses, args.images, args.spacing, out=args.out, fps=args.fps,
                                 time_offset_s=args.time_offset, max_gap_s=args.max_gap)
    skipped = f" ({rep['no_pose']} without a pose, {rep['no_crossing']} without a clear crossing)" if rep["used"] < rep["frames"] else ""
    worst = max(rep["errors_mm"].items(), key=lambda kv: kv[1])
    print(f"calibrated from {rep['used']} of {rep['frames']} frames{skipped}: RMS {rep['rms_mm']:.3f} mm "
          f"(worst {worst[1]:.3f} mm, {worst[0]}); wrote {args.out}")


def cmd_ultrasound_simulate(args):
    from .ultrasound.recording import write_simulated_recording

    if args.frames < 2:
        raise ValueError(f"--frames must be >= 2, got {args.frames}")
    t = write_simulated_recording(args.out, n_frames=args.frames, seed=args.seed, progress=not args.quiet)
    u, v = t["seed_px"]
    o, c = Path(args.out), Path(t["calibration"])
    sx, sy = t["spacing"]
    print(f"wrote a sweep ({t['camera_frames']} stereo pairs at 30 frames/s, {t['us_frames']} ultrasound frames) and a "
          f"cross-wire calibration session into {o}; the tube (diameter {t['diameter_mm']} mm) is at {u:.0f},{v:.0f} px "
          f"on the first ultrasound frame. Next:\n"
          f"  markerpose track {c / 'left'} {c / 'right'} --fps 1 --out {c / 'poses.csv'}\n"
          f"  markerpose ultrasound calibrate --poses {c / 'poses.csv'} --images {c / 'us'} --spacing {sx},{sy} --out {o / 'probe.yaml'}\n"
          f"  markerpose track {t['left']} {t['right']} --fps 30 --out {o / 'poses.csv'}\n"
          f"  markerpose ultrasound reconstruct --poses {o / 'poses.csv'} --images {t['us']} "
          f"--calibration {o / 'probe.yaml'} --seed {u:.0f},{v:.0f} --out {o / 'reconstruction'}")


def _eval_args(p, what: str):
    p.add_argument("--weights", help=f"{what} checkpoint (default: the shipped weights)")
    p.add_argument("--data", default="runs/data", help="cache of rendered sets")
    p.add_argument("--sets", nargs="*", help="subset of the test sets")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="also write the metrics as JSON")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="markerpose", description="Stereo 6-DoF tracking of a three-ring marker (MarkerPose).")
    p.add_argument("--version", action="version", version=f"markerpose {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="the paper's robot experiments on synthetic frames; tables vs the paper")
    d.add_argument("--out", default="markerpose-demo", help="output folder (default: markerpose-demo)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--alpha", type=float, default=1.0, help="exposure gain (darkness), default 1")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=cmd_demo)

    m = sub.add_parser("marker", help="write a printable target (PDF or SVG) at exact scale")
    m.add_argument("--out", default="target.pdf", help="target.pdf or target.svg (default target.pdf)")
    m.add_argument("--paper", default="a4", choices=["a4", "letter"])
    _add_marker_args(m)
    m.set_defaults(func=cmd_marker)

    r = sub.add_parser("render", help="render a synthetic stereo pair with ground truth")
    r.add_argument("--out", default="render", help="output folder")
    r.add_argument("--rig", help="rig file (OpenCV YAML/XML); default: the built-in rig")
    r.add_argument("--distance", type=float, default=560.0, help="c0 depth, mm")
    r.add_argument("--x", type=float, default=0.0)
    r.add_argument("--y", type=float, default=0.0)
    r.add_argument("--tilt", type=float, default=30.0, help="plate tilt, degrees")
    r.add_argument("--tilt-axis", type=float, default=45.0)
    r.add_argument("--roll", type=float, default=0.0)
    r.add_argument("--alpha", type=float, default=1.0)
    r.add_argument("--motion-blur", type=float, default=0.0, help="kernel length, px")
    r.add_argument("--motion-angle", type=float, default=0.0)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--repeat", type=int, default=1, help="render N times and report the median time")
    _add_marker_args(r)
    r.set_defaults(func=cmd_render)

    e = sub.add_parser("estimate", help="pose of the marker from a stereo pair of image files (JSON)")
    e.add_argument("left")
    e.add_argument("right")
    e.add_argument("--rig", help="rig file (OpenCV YAML/XML with K1 dist1 K2 dist2 R t); default: the built-in rig")
    e.add_argument("--preset", default="default", choices=list(ORDER), help="pipeline configuration (default: default)")
    e.add_argument("--detector", choices=["neural", "classical"], help="shorthand: classical = --preset classical")
    _add_set_arg(e)
    _add_marker_args(e)
    e.set_defaults(func=cmd_estimate)

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
    cb.add_argument("--rendered", type=int, metavar="N", help="instead of LEFT RIGHT: N rendered pairs of the built-in rig, checked against it")
    cb.add_argument("--seed", type=int, default=0, help="--rendered: seed of the poses and the noise")
    cb.set_defaults(func=cmd_calibrate)

    k = sub.add_parser("track", help="track the marker through two image folders, two videos or two cameras; one CSV row a frame")
    k.add_argument("left", help="left frames: a folder of images (sorted by name), a video file or a camera index")
    k.add_argument("right", help="right frames, the same kind")
    k.add_argument("--rig", help="rig file (OpenCV YAML/XML with K1 dist1 K2 dist2 R t); default: the built-in rig")
    k.add_argument("--out", default="poses.csv", help="CSV, one row a frame (default poses.csv)")
    k.add_argument("--jsonl", help="also one JSON object a frame")
    k.add_argument("--video", help="also a video (mp4) of both views side by side with the marker's axes drawn")
    k.add_argument("--show", action="store_true", help="a live window with both views and the axes (q stops; needs a display)")
    k.add_argument("--fps", type=float, default=60.0, help="frame rate of image folders, for timestamp_s (videos and cameras give their own; default 60)")
    k.add_argument("--preset", default="default", choices=list(ORDER), help="pipeline configuration (default: default)")
    k.add_argument("--detector", choices=["neural", "classical"], help="shorthand: classical = --preset classical")
    k.add_argument("--igtl", type=int, nargs="?", const=18944, metavar="PORT",
                   help="serve the poses over OpenIGTLink (3D Slicer, PLUS) as TRANSFORM messages (port default 18944; the igtl extra)")
    k.add_argument("--igtl-name", default="MarkerToTracker", help="the TRANSFORM's device name (default MarkerToTracker)")
    k.add_argument("--igtl-public", action="store_true", help="listen on the network interface, not only on 127.0.0.1")
    k.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_set_arg(k)
    _add_marker_args(k)
    k.set_defaults(func=cmd_track)

    pe = sub.add_parser("peers", help="markerpose beside AprilTag 3, ArUco, ChArUco and STag on the same rendered scenes")
    pe.add_argument("--out", default="markerpose-peers", help="output folder (default: markerpose-peers)")
    pe.add_argument("--quick", action="store_true", help="6 scenes per level instead of 40 (a few minutes)")
    pe.add_argument("--pairs", type=_positive_int, help="scenes per darkness / blur level (default 40; --quick 6)")
    pe.add_argument("--systems", nargs="+", choices=("markerpose", "apriltag", "aruco", "charuco", "stag"), help="systems to run (default: all installed)")
    pe.add_argument("--seed", type=int, default=0)
    pe.add_argument("--jobs", type=_positive_int, help="processes (default: up to 2)")
    pe.add_argument("--quiet", action="store_true", help="no progress bar")
    pe.set_defaults(func=cmd_peers)

    us = sub.add_parser("ultrasound", help="freehand 3D ultrasound with a tracked probe (the paper's section 5.3)")
    usub = us.add_subparsers(dest="ultrasound_command", required=True)
    ud = usub.add_parser("demo", help="the paper's tube experiment on simulated data: diameter vs the paper, report, plots, files")
    ud.add_argument("--out", default="markerpose-ultrasound", help="output folder (default: markerpose-ultrasound)")
    ud.add_argument("--quick", action="store_true", help="3 short acquisitions (about a minute) instead of 10 full ones")
    ud.add_argument("--acquisitions", type=int, help="number of seeded acquisitions (default 10; --quick 3)")
    ud.add_argument("--seed", type=int, default=0)
    ud.add_argument("--jobs", type=int, help="processes (default: up to 2)")
    ud.add_argument("--quiet", action="store_true", help="no progress bar")
    ud.set_defaults(func=cmd_ultrasound_demo)
    ur = usub.add_parser("reconstruct", help="a recorded sweep: poses.csv from markerpose track + ultrasound frames → sequence, volume, tube fit")
    ur.add_argument("--poses", required=True, help="poses.csv written by markerpose track")
    ur.add_argument("--images", required=True, help="folder of ultrasound frames (sorted by name) with timestamps.csv (file,timestamp_s)")
    ur.add_argument("--calibration", required=True, help="probe calibration YAML (T_marker_image, spacing, image_size)")
    ur.add_argument("--out", default="markerpose-reconstruction", help="output folder (default: markerpose-reconstruction)")
    ur.add_argument("--seed", type=_pixel, metavar="U,V", help="a pixel inside the tube on the first frame: segment it and fit a cylinder")
    ur.add_argument("--fps", type=float, help="frame rate of the ultrasound frames when there is no timestamps.csv")
    ur.add_argument("--time-offset", type=float, default=0.0, help="seconds added to the ultrasound times to reach the cameras' clock")
    ur.add_argument("--max-gap", type=float, default=0.2, help="no pose is interpolated across a tracking gap longer than this, s (default 0.2)")
    ur.add_argument("--voxel-mm", type=float, default=0.3, help="volume spacing, mm (default 0.3)")
    ur.add_argument("--quiet", action="store_true", help="no progress bars")
    ur.set_defaults(func=cmd_ultrasound_reconstruct)
    uc = usub.add_parser("calibrate", help="probe calibration from a recorded cross-wire session (poses.csv + ultrasound frames) → probe.yaml")
    uc.add_argument("--poses", required=True, help="poses.csv written by markerpose track for the session")
    uc.add_argument("--images", required=True, help="folder of ultrasound frames showing the wire crossing, with timestamps.csv (file,timestamp_s)")
    uc.add_argument("--spacing", required=True, type=_pixel, metavar="SX,SY", help="pixel size in mm (lateral, depth), as the scanner reports it")
    uc.add_argument("--out", default="probe.yaml", help="calibration file to write (default probe.yaml)")
    uc.add_argument("--fps", type=float, help="frame rate of the ultrasound frames when there is no timestamps.csv")
    uc.add_argument("--time-offset", type=float, default=0.0, help="seconds added to the ultrasound times to reach the cameras' clock")
    uc.add_argument("--max-gap", type=float, default=0.2, help="no pose is interpolated across a tracking gap longer than this, s (default 0.2)")
    uc.set_defaults(func=cmd_ultrasound_calibrate)
    usim = usub.add_parser("simulate", help="write a simulated recording (a sweep and a cross-wire session: stereo and ultrasound frames) to try calibrate and reconstruct on")
    usim.add_argument("--out", default="markerpose-us-recording", help="output folder (default: markerpose-us-recording)")
    usim.add_argument("--frames", type=int, default=30, help="ultrasound frames (15 frames/s; default 30)")
    usim.add_argument("--seed", type=int, default=0)
    usim.add_argument("--quiet", action="store_true", help="no progress bar")
    usim.set_defaults(func=cmd_ultrasound_simulate)

    b = sub.add_parser("bench", help="speed of the stereo pipeline per configuration (interleaved, same frames)")
    b.add_argument("--pairs", type=int, default=8, help="rendered stereo pairs")
    b.add_argument("--blurred-pairs", type=int, default=4, help="pairs with 25 px motion blur (timed apart)")
    b.add_argument("--empty-pairs", type=int, default=4, help="marker-free pairs (time while the marker is out of view)")
    b.add_argument("--repeats", type=int, default=3, help="passes over the pairs (the first warms up)")
    b.add_argument("--threads", type=int, help="torch threads (default: all cores)")
    b.add_argument("--configs", nargs="*", help="preset names (default: all available)")
    b.add_argument("--json", help="also write the figures as JSON")
    b.add_argument("--sequence", action="store_true", help="instead: a rendered 60 frames/s stereo video (still, by hand, fast, gone, dark), tracked and detected")
    b.add_argument("--frames", type=int, default=240, help="--sequence: frames (default 240: four seconds)")
    b.add_argument("--jumps", action="store_true",
                   help="instead: the marker put down elsewhere between two frames, tracked with and without the search near the prediction")
    b.add_argument("--trials", type=int, default=120, help="--jumps: trials (default 120; --threads, --seed and --out apply too)")
    b.add_argument("--seed", type=int, help="--sequence / --jumps: seed of the rendering (default 0 / 11)")
    b.add_argument("--preset", default="default", help="--sequence: the preset of track and estimate (default: default)")
    b.add_argument("--passes", type=int, default=2,
                   help="--sequence: passes over the sequence per method, in alternating order (default 2; the statistics pool them)")
    b.add_argument("--no-pace", action="store_true",
                   help="--sequence: hand the frames over back to back instead of at the stream's 60 frames/s")
    b.add_argument("--out", help="--sequence / --jumps: output folder (default markerpose-sequence / markerpose-jumps)")
    b.add_argument("--quiet", action="store_true")
    b.set_defaults(func=cmd_bench)

    x = sub.add_parser("experiments", help="the paper's Section 5 with confidence intervals: report, plots, JSON")
    x.add_argument("--quick", action="store_true", help="2 trials, 6 pairs per level, Table 5 at 3 darkness levels (~5 min)")
    x.add_argument("--trials", type=int, help="robot-path placements (default 8)")
    x.add_argument("--pairs", type=int, help="random pairs per darkness / blur level (default 48)")
    x.add_argument("--seed", type=int, help="base seed (default 0)")
    x.add_argument("--configs", nargs="*", help="preset names (default: the headline ones that can run)")
    x.add_argument("--out", default="markerpose-experiments", help="output folder (default: markerpose-experiments)")
    x.add_argument("--quiet", action="store_true")
    x.set_defaults(func=cmd_experiments)

    t = sub.add_parser("train", help="train a network on rendered data")
    tsub = t.add_subparsers(dest="what", required=True)
    tk = tsub.add_parser("keypoints", help="stage 1: the SuperPoint-like centre + ID network")
    tk.add_argument("--width", type=float, default=1.0, help="layer-width multiplier (1 = the paper's network)")
    tk.add_argument("--stem-width", type=float, default=None, help="multiplier of the first four convolutions, at full and half resolution (default: --width)")
    tk.add_argument("--background-weight", type=float, default=0.01, help="weight of the background class in both losses (1 = plain CE)")
    tk.add_argument("--steep-size", type=int, default=0, help="extra rendered images of markers tilted 55-80° (cached)")
    tk.add_argument("--retune", metavar="CHECKPOINT", help="no training: export CHECKPOINT (with --export) with its decoding thresholds tuned afresh on the validation set")
    tk.add_argument("--int8", nargs=2, metavar=("SRC", "DEST"), help="no training: write an int8 copy of the .onnx weights SRC to DEST, calibrated on rendered training images")
    tk.add_argument("--int8-images", type=int, default=256, help="training images that calibrate --int8's activations")
    tk.add_argument("--val-negatives", type=int, default=None, help="marker-free validation images the export tunes the false-positive budget on (default 3000)")
    tk.add_argument("--window", type=int, nargs=2, default=[192, 144], metavar=("W", "H"),
                    help="training windows of the 320x240 images, multiples of 8 (default 192 144; 320 240: whole images)")
    tk.add_argument("--small-boost", type=float, default=1.0, help="draw views whose rings are under 12 input px this many times as often (1 = each view once per epoch)")
    _add_train_args(tk, "keypoints", batch=16, size=12000, unit="images")
    tk.set_defaults(func=cmd_train_keypoints)
    te = tsub.add_parser("ellipses", help="stage 2: EllipSegNet on 120x120 patches")
    _add_train_args(te, "ellipses", batch=32, size=11010, unit="patches (the paper had 11010)")
    te.set_defaults(func=cmd_train_ellipses)

    ev = sub.add_parser("eval", help="evaluate a network on the held-out test sets")
    esub = ev.add_subparsers(dest="what", required=True)
    ek = esub.add_parser("keypoints", help="stage 1 on the held-out sets (standard, dark, blur, negatives)")
    _eval_args(ek, "stage-1")
    ek.add_argument("--speed", action="store_true", help="also time the paper-width and the shipped network")
    ek.add_argument("--decodings", nargs="*", help="decoding variants (default: all): head layout layout_verify layout_verify_align")
    ek.add_argument("--second-look", type=float, default=2.0, help="zoom of the second look of the variants that have one (1 = none)")
    ek.set_defaults(func=cmd_eval_keypoints)
    ee = esub.add_parser("ellipses", help="stage 2 on the held-out patch sets (standard, dark, blur)")
    _eval_args(ee, "EllipSegNet")
    ee.set_defaults(func=cmd_eval_ellipses)
    ep = esub.add_parser("pipeline", help="end to end on held-out stereo pairs: detection, centres, pose, per configuration")
    ep.add_argument("--pairs", type=int, default=200, help="pairs per set")
    ep.add_argument("--sets", nargs="*", help="standard, dark_0.0625, blur_25, marker_free (the default), far (0.8-1.6 m), and realism (the nine realism_<effect> sets: shadow, light_gradient, defocus, gamma, jpeg, resample, toner, occluded_border, ring_object)")
    ep.add_argument("--configs", nargs="*", help="preset names (default: all available)")
    ep.add_argument("--single-view", action="store_true", help="also each view alone (tracker.detect): all three centres within the tolerance, right IDs")
    ep.add_argument("--workers", type=int, default=1, help="processes running sets at once (one torch thread each; figures unchanged)")
    ep.add_argument("--json", help="also write the figures as JSON")
    ep.add_argument("--quiet", action="store_true")
    ep.set_defaults(func=cmd_eval_pipeline)
    eb = esub.add_parser("blur-distance", help="the distance c0-c1 under motion blur along it, per blur length and configuration")
    eb.add_argument("--pairs", type=_positive_int, default=40, help="poses, each rendered at every blur length (default 40)")
    eb.add_argument("--lengths", type=float, nargs="+", help="blur lengths, px (default 0 5 9 13 17 21 25)")
    eb.add_argument("--configs", nargs="*", help="preset names (default: default paper)")
    eb.add_argument("--out", default="markerpose-blur-distance", help="output folder: report.md, results.json, blur-distance.png")
    eb.add_argument("--quiet", action="store_true")
    eb.set_defaults(func=cmd_eval_blur_distance)
    return p


def main(argv=None) -> int:
    """Run a command. Exit codes: 0 done, 1 the marker was not found (``estimate``), 2 bad
    input (a one-line message, no traceback), 130 interrupted."""
    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
        sys.stdout.flush()
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, CompileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:  # e.g. `markerpose estimate ... | head -3`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
