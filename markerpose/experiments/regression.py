"""Behaviour kept, pair for pair: record every user preset's output, compare two records.

A restructuring of the pipeline must not change what it finds. ``record`` runs each user
preset's ``estimate()`` on the seeded held-out pairs (:mod:`.endtoend`'s sets) and
``track()`` through the rendered video of :mod:`.sequence`, and stores each call's pose
``T`` and ``centers`` (NaN where nothing was found), its ``source`` and ``why``.
``compare`` reports, per preset and set, the calls whose outcome differs and the largest
difference of ``T`` and ``centers`` where both found the marker::

    python -m markerpose.experiments.regression record before.npz
    python -m markerpose.experiments.regression compare before.npz after.npz

Only public names are used (``MarkerPose``, the presets by name, the sets' generators),
so one file records any checkout: run it with that checkout first on ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from tqdm import tqdm

from markerpose import Marker, MarkerPose, StereoRig
from markerpose.experiments import endtoend, sequence

USER_PRESETS = ("default", "paper", "paper-classical", "classical", "default-float32", "default-bf16")
SETS = ("standard", "dark_0.0625", "blur_25", "far", "marker_free")
NAN_T, NAN_C = np.full((4, 4), np.nan), np.full((2, 3, 2), np.nan)


def _runnable(preset: str, rig: StereoRig) -> MarkerPose | None:
    try:
        return MarkerPose(rig, preset=preset)
    except (ImportError, ValueError) as exc:  # default-bf16 needs the openvino extra
        print(f"skipped {preset}: {exc}", file=sys.stderr)
        return None


def _row(est, tracker) -> tuple:
    if est is None:
        return NAN_T, NAN_C, "", tracker.why or ""
    return est.T, est.centers, est.source, ""


def record(path: str, pairs: int = 100, frames: int = 240, presets=USER_PRESETS) -> None:
    rig, marker = StereoRig.default(), Marker()
    trackers = {p: t for p in presets if (t := _runnable(p, rig)) is not None}
    out: dict = {}

    def put(key, rows):
        T, C, src, why = zip(*rows)
        out[f"{key}/T"], out[f"{key}/centers"] = np.stack(T), np.stack(C)
        out[f"{key}/meta"] = np.array(json.dumps({"source": src, "why": why}))

    for name in SETS:
        rows: dict = {p: [] for p in trackers}
        for frame, _ in tqdm(endtoend.pairs(name, pairs, rig, marker), total=pairs, desc=name):
            for p, t in trackers.items():
                rows[p].append(_row(t.estimate(*frame.images), t))
        for p in trackers:
            put(f"{p}/{name}", rows[p])
    conf = {**sequence.default_conf, "frames": frames}  # the benchmark's seeded video
    video = [f.images for f, _, _ in sequence.render(conf, rig, marker, progress=False)]
    for p, t in trackers.items():
        t.reset()
        put(f"{p}/sequence-track", [_row(t.track(*images), t) for images in tqdm(video, desc=f"{p} track")])
    np.savez_compressed(path, **out)


def compare(a: str, b: str, tol: float = 1e-9) -> bool:
    """Print per preset and set how the two records differ; whether they agree within ``tol``."""
    A, B = np.load(a), np.load(b)
    keys = sorted({k.rsplit("/", 1)[0] for k in A.files} | {k.rsplit("/", 1)[0] for k in B.files})
    same = True
    for key in keys:
        if f"{key}/T" not in A.files or f"{key}/T" not in B.files:
            print(f"{key}: only in {'the first' if f'{key}/T' in A.files else 'the second'} record")
            continue
        Ta, Tb, Ca, Cb = A[f"{key}/T"], B[f"{key}/T"], A[f"{key}/centers"], B[f"{key}/centers"]
        fa, fb = np.isfinite(Ta[:, 0, 0]), np.isfinite(Tb[:, 0, 0])
        ma, mb = json.loads(str(A[f"{key}/meta"])), json.loads(str(B[f"{key}/meta"]))
        both = fa & fb
        dT = float(np.abs(Ta[both] - Tb[both]).max()) if both.any() else 0.0
        dC = float(np.abs(Ca[both] - Cb[both]).max()) if both.any() else 0.0
        outcome = int((fa != fb).sum())
        source = sum(x != y for x, y in zip(ma["source"], mb["source"]))
        why = sum(x != y for x, y in zip(ma["why"], mb["why"]))
        ok = outcome == 0 and source == 0 and dT <= tol and dC <= tol
        same &= ok
        print(
            f"{'ok  ' if ok else 'DIFF'} {key}: {len(fa)} calls, found {int(fa.sum())}/{int(fb.sum())}, outcome differs {outcome}, "
            f"source differs {source}, why differs {why}, max |dT| {dT:.2e}, max |dcenters| {dC:.2e}"
        )
    return same


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out")
    r.add_argument("--pairs", type=int, default=100)
    r.add_argument("--frames", type=int, default=240)
    r.add_argument("--presets", nargs="+", default=list(USER_PRESETS))
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    c.add_argument("--tol", type=float, default=1e-9)
    args = ap.parse_args(argv)
    if args.cmd == "record":
        record(args.out, args.pairs, args.frames, args.presets)
        return 0
    return 0 if compare(args.a, args.b, args.tol) else 1


if __name__ == "__main__":
    sys.exit(main())
