"""``markerpose train keypoints | ellipses``: a network trained on rendered data."""

from __future__ import annotations

import time

_TRAIN_KEYS = ("lr", "schedule", "epochs", "batch_size", "train_size", "val_size", "seed", "workers", "device", "init")


def _need_torch():
    import importlib.util

    for name in ("torch", "onnx"):
        if importlib.util.find_spec(name) is None:
            raise ValueError(
                f'training needs {name}: pip install -e ".[train]" (on a CPU machine, torch from the CPU index first; see the README)'
            )


def _train(module, args, keys: tuple, **export_kw):
    conf = {k: getattr(args, k) for k in keys}
    t0 = time.perf_counter()
    best = module.main(conf, args.out, resume=args.resume, data_dir=args.data)
    print(f"best checkpoint: {best} ({(time.perf_counter() - t0) / 60:.1f} min)")
    if args.export:
        dest = module.export(best, args.export, **export_kw)
        print(f"exported the weights to {dest} and {dest.with_suffix('.onnx')}")


def _quantize(args):
    """--int8: no training, an int8 copy of ONNX weights (needs onnx, not torch)."""
    import importlib.util

    if importlib.util.find_spec("onnx") is None:
        raise ValueError('--int8 needs onnx: pip install -e ".[train]"')
    from ..train import keypoints

    src, dest = args.int8
    t0 = time.perf_counter()
    out = keypoints.quantize(src, dest, args.int8_images, args.workers)
    print(f"wrote the int8 copy of {src} to {out} ({(time.perf_counter() - t0) / 60:.1f} min)")


def cmd_train_keypoints(args):
    if args.int8:
        return _quantize(args)
    _need_torch()
    from ..train import keypoints

    if args.retune:  # no training: the checkpoint's decoding thresholds tuned afresh
        if not args.export:
            raise SystemExit("--retune needs --export (where to write the re-tuned weights)")
        t0 = time.perf_counter()
        dest = keypoints.export(args.retune, args.export, data_dir=args.data, val_size=args.val_size, negatives=args.val_negatives)
        print(f"exported the weights to {dest} and {dest.with_suffix('.onnx')} ({(time.perf_counter() - t0) / 60:.1f} min)")
        return
    _train(
        keypoints,
        args,
        (
            "width",
            "stem_width",
            "stem",
            "teacher",
            "stem_steps",
            "background_weight",
            "steep_size",
            "small_boost",
            "window",
            "loader_workers",
        )
        + _TRAIN_KEYS,
        data_dir=args.data,
        val_size=args.val_size,
        negatives=args.val_negatives,
    )


def cmd_train_ellipses(args):
    _need_torch()
    from ..train import ellipses

    _train(ellipses, args, _TRAIN_KEYS)


def _add_train_args(p, name: str, batch: int, size: int, unit: str):
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (default: the paper's 1e-4)")
    p.add_argument("--schedule", default="constant", choices=["constant", "cosine"], help="constant (paper) or cosine decay")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=batch)
    p.add_argument("--train-size", type=int, default=size, help=f"rendered training {unit}, cached")
    p.add_argument("--val-size", type=int, default=400)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="processes rendering the data: Ray's where it is installed (1: this process)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    p.add_argument("--out", default=f"runs/{name}", help="checkpoints and history")
    p.add_argument("--data", default="runs/data", help="cache of rendered sets")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init", help="start from the weights of this checkpoint (fine-tuning) instead of at random")
    p.add_argument("--export", help="also write the best weights, slimmed, to this path")


def _register_keypoints(tsub) -> None:
    tk = tsub.add_parser("keypoints", help="stage 1: the SuperPoint-like centre + ID network")
    tk.add_argument("--width", type=float, default=1.0, help="layer-width multiplier (1 = the paper's network)")
    tk.add_argument(
        "--stem-width",
        type=float,
        default=None,
        help="multiplier of the first four convolutions, at full and half resolution (default: --width)",
    )
    tk.add_argument(
        "--stem",
        default="pool",
        choices=["pool", "strided", "pointwise"],
        help="how the encoder first halves the input: pool (the paper's two 3x3 convolutions and a max-pool), strided (one 4x4 convolution of stride 2, then a 3x3 at half resolution) or pointwise (the same with a 1x1 in place of the 3x3)",
    )
    tk.add_argument(
        "--teacher",
        metavar="WEIGHTS",
        help="distil: learn the outputs of this stage-1 .pt file instead of the labels, with its widths, starting from its weights where the shapes agree",
    )
    tk.add_argument(
        "--stem-steps", type=int, default=600, help="with --teacher: batches that first fit the stem alone to the teacher's stem features"
    )
    tk.add_argument("--background-weight", type=float, default=0.01, help="weight of the background class in both losses (1 = plain CE)")
    tk.add_argument("--steep-size", type=int, default=0, help="extra rendered images of markers tilted 55-80° (cached)")
    tk.add_argument(
        "--retune",
        metavar="CHECKPOINT",
        help="no training: export CHECKPOINT (with --export) with its decoding thresholds tuned afresh on the validation set",
    )
    tk.add_argument(
        "--int8",
        nargs=2,
        metavar=("SRC", "DEST"),
        help="no training: write an int8 copy of the .onnx weights SRC to DEST, calibrated on rendered training images",
    )
    tk.add_argument("--int8-images", type=int, default=256, help="training images that calibrate --int8's activations")
    tk.add_argument(
        "--val-negatives",
        type=int,
        default=None,
        help="marker-free validation images the export tunes the false-positive budget on (default 3000)",
    )
    tk.add_argument(
        "--window",
        type=int,
        nargs=2,
        default=[192, 144],
        metavar=("W", "H"),
        help="training windows of the 320x240 images, multiples of 8 (default 192 144; 320 240: whole images)",
    )
    tk.add_argument(
        "--small-boost",
        type=float,
        default=1.0,
        help="draw views whose rings are under 12 input px this many times as often (1 = each view once per epoch)",
    )
    tk.add_argument(
        "--loader-workers",
        type=int,
        default=1,
        help="processes augmenting the batches (1: this process; more keep a GPU fed, with other random draws than 1)",
    )
    _add_train_args(tk, "keypoints", batch=16, size=12000, unit="images")
    tk.set_defaults(func=cmd_train_keypoints)


def register(sub) -> None:
    t = sub.add_parser("train", help="train a network on rendered data")
    tsub = t.add_subparsers(dest="what", required=True)
    _register_keypoints(tsub)
    te = tsub.add_parser("ellipses", help="stage 2: EllipSegNet on 120x120 patches")
    _add_train_args(te, "ellipses", batch=32, size=11010, unit="patches (the paper had 11010)")
    te.set_defaults(func=cmd_train_ellipses)
