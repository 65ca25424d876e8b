"""Training and evaluation of stage 1 (the SuperPoint-like centre + ID network).

Data: random scenes (:mod:`markerpose.train.scenes`) rendered once into a cached
``.npz`` (seeded by chunk, so the same seed gives the same set with any number of
workers), augmented afresh every epoch (:mod:`markerpose.train.augment`).
The held-out test sets (:data:`TEST_SETS`) have their own seeds and are never trained on.

Loss (paper §3.1): λ1·CE(location, 65 classes per cell) + λ2·CE(ID, 4 classes per cell);
Adam. Every epoch is validated (detection rate, ID accuracy, pixel error at full
resolution, false positives on marker-free images); the best and the last checkpoints
are kept, and ``resume`` continues from the last.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from .. import decode as dec
from .. import keypoints as kp
from ..nets import fuse_batchnorm
from .augment import augment
from .data import cached as data_cache
from .data import render_many
from .loop import export as export_checkpoint
from .loop import fit, to_onnx
from .scenes import sample

default_conf = {
    "width": 1.0,  # network width multiplier (1.0 = the paper's)
    "stem_width": None,  # multiplier of the first four convolutions (None: ``width``)
    "stem": "pool",  # how the encoder first halves the input (keypoints.STEMS)
    # Distillation (None: train on the labels): a stage-1 weights file (.pt) whose outputs
    # the network learns instead of the labels; it takes the teacher's widths, starts from
    # the teacher's weights where the shapes agree, and first fits its stem alone to the
    # teacher's stem features for ``stem_steps`` batches (a new stem in a trained network).
    "teacher": None,
    "stem_steps": 600,
    "stem_lr": 3e-3,
    "lr": 1e-4,  # Adam learning rate (the paper's)
    "schedule": "constant",  # "constant" (paper) or "cosine" decay to 0 over the run
    "epochs": 10,
    "batch_size": 16,
    "lambda_loc": 1.0,
    "lambda_id": 1.0,
    # Weight of the "no centre" / background class in both cross-entropies. Three target
    # cells face ~1200 background cells per image; unweighted (1.0, the paper), a short
    # training run settles on "background everywhere". 0.01 gives the targets about a
    # fifth of the loss.
    "background_weight": 0.01,
    "window": (192, 144),  # train on windows of the 320x240 images (None: whole images)
    "train_size": 12000,  # cached rendered images, augmented afresh each epoch
    # Extra training images of steeply tilted markers (tilt 55-80°, seed + 100). The other
    # view of a stereo pair often sees the marker ~10-20° steeper than the tilt drawn for
    # one camera, and stage 1 misplaces such rings most.
    "steep_size": 0,
    # Views whose outer rings look smaller than SMALL_RING_PX at the network input are
    # drawn this many times as often as the others (1: every view once per epoch, in a
    # random order): stage 1 misses small rings most.
    "small_boost": 1.0,
    "val_size": 400,
    "seed": 0,
    "workers": 2,  # processes rendering the cached sets
    "loader_workers": 1,  # processes augmenting the batches (1: in this process; more keep a GPU fed)
    "device": None,  # None: CUDA when present, else CPU
    "init": None,  # checkpoint whose weights start the run (fine-tuning); None: random
    "tolerance_px": 8.0,  # a centre is found when within this many full-resolution px
}

# Held-out sets: (seed, size, scene conf). Never trained on (the training set uses seed 0
# and the validation set seed 1; chunks are seeded by (seed, chunk)).
TEST_SETS = {
    "standard": (1001, 600, {"alpha": (0.25, 1.0), "blur": (0.0, 9.0), "inside": True, "p_occlude": 0.0}),
    "dark_0.0625": (1002, 300, {"alpha": 0.0625, "blur": (0.0, 9.0), "inside": True, "p_occlude": 0.0}),
    "blur_25": (1003, 300, {"alpha": (0.25, 1.0), "blur": 25.0, "inside": True, "p_occlude": 0.0}),
    "dark_0.039": (1004, 300, {"alpha": 0.039, "blur": (0.0, 9.0), "inside": True, "p_occlude": 0.0}),
    "negatives": (1005, 600, {"negative": True}),
}

STEEP = {"tilt": (55.0, 80.0)}  # scene conf of the extra steep training images
SMALL_RING_PX = 12.0  # outer-ring diameter at the network input below which ``small_boost`` applies


def make_targets(points: np.ndarray, labels: np.ndarray, size=kp.INPUT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Cell targets of the two heads from the ring centres of one image.

    Args:
        points: (3, 2) centres c0, c1, c2 in the network input's pixels (x, y).
        labels: (3,) int: 1 = visible (a target), 0 = absent, -1 = ambiguous (ignored
            by the loss: e.g. a ring half occluded or half outside the image).
        size: (W, H) of the network input.
    Returns:
        det: (H/8, W/8) int64 in 0..64 (64 = no centre) or -100 (ignored);
        ids: (H/8, W/8) int64 in 0..3 (3 = background) or -100.
    """
    w, h = size
    det = np.full((h // dec.CELL, w // dec.CELL), dec.CELL * dec.CELL, np.int64)
    ids = np.full((h // dec.CELL, w // dec.CELL), 3, np.int64)
    for i, ((x, y), lab) in enumerate(zip(np.asarray(points, np.float64), labels)):
        if lab == 0 or not (np.isfinite(x) and np.isfinite(y)):
            continue
        px, py = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))  # nearest pixel centre
        if not (0 <= px < w and 0 <= py < h):
            continue
        cy, cx = py // dec.CELL, px // dec.CELL
        if lab < 0:
            det[cy, cx], ids[cy, cx] = -100, -100
        else:
            det[cy, cx] = (py % dec.CELL) * dec.CELL + px % dec.CELL
            ids[cy, cx] = i
    return det, ids


def _render_chunk(args):
    seed, chunk, n, conf = args
    rng = np.random.default_rng([seed, chunk])
    conf = dict(conf or {})
    negative = conf.pop("negative", None)
    return [sample(rng, negative=negative, conf=conf) for _ in range(n)]


def generate(n: int, seed: int, conf: dict | None = None, workers: int = 2, desc: str = "render") -> dict:
    """Render ``n`` stage-1 samples into arrays (see :class:`~markerpose.train.scenes.Sample`).

    Returns:
        dict of arrays: image (N, 240, 320) uint8, points (N, 3, 2), labels (N, 3), alpha,
        blur, ring_px (N,), scale (N, 2).
    """
    out = render_many(_render_chunk, n, seed, conf, workers, desc, "img")
    return {
        "image": np.stack([s.image for s in out]),
        "points": np.stack([s.points for s in out]).astype(np.float32),
        "labels": np.stack([s.labels for s in out]).astype(np.int8),
        "alpha": np.array([s.alpha for s in out], np.float32),
        "blur": np.array([s.blur for s in out], np.float32),
        "ring_px": np.array([s.ring_px for s in out], np.float32),
        "scale": np.stack([s.scale for s in out]).astype(np.float32),
    }


def cached(path: Path, *, n: int, seed: int, conf: dict | None = None, workers: int = 2, desc: str = "render") -> dict:
    """Load a rendered stage-1 set from ``path`` (.npz) or render and save it."""
    return data_cache(path, {"n": n, "seed": seed, "conf": conf}, lambda: generate(n, seed, conf, workers, desc))


# --- evaluation ------------------------------------------------------------------------
def logits(net, images: np.ndarray, batch: int = 32, device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """Both heads' logits for a (N, 240, 320) uint8 stack: (N, 65, 30, 40), (N, 4, 30, 40).
    ``net``: a torch module, or a :class:`markerpose.nets.Runner` (ONNX Runtime or torch)."""
    from ..nets import Runner

    dets, ids = [], []
    if isinstance(net, Runner):
        for k in range(0, len(images), batch):
            d, i = net(images[k : k + batch].astype(np.float32)[:, None] / 255.0)
            dets.append(d)
            ids.append(i)
        return np.concatenate(dets), np.concatenate(ids)
    import torch

    net.eval()
    with torch.inference_mode():
        for k in range(0, len(images), batch):
            x = torch.from_numpy(images[k : k + batch].astype(np.float32) / 255.0)[:, None].to(device)
            d, i = net(x)
            dets.append(d.float().cpu().numpy())
            ids.append(i.float().cpu().numpy())
    return np.concatenate(dets), np.concatenate(ids)


DECODE_WORKERS = 2  # processes decoding a stack of views (export, evaluation)
_DECODE_CHUNK = 25  # views per job
_DECODE_JOB: tuple = ()  # (det, ID logits, images, conf) of the running decode_all, inherited by its workers


def _decode_views(bounds: tuple[int, int]) -> list:
    det, id_logits, images, conf = _DECODE_JOB
    c = {**dec.default_conf, **(conf or {})}
    needs_image = c["verify"] or c["align"]
    return [
        dec.decode(det[j], id_logits[j], conf, image=images[j].astype(np.float32) / 255.0 if needs_image else None) for j in range(*bounds)
    ]


def decode_all(det, id_logits, images, decode_conf: dict | None = None, desc: str | None = None, workers: int | None = None) -> list:
    """:func:`~markerpose.keypoints.decode` of every image of a stack: the heads' logits
    and the (N, 240, 320) uint8 inputs (which ``verify`` looks at), as arrays or lists; a
    progress bar labelled ``desc`` when given. ``workers`` processes (default
    :data:`DECODE_WORKERS`) share the views; the result does not depend on their number."""
    global _DECODE_JOB
    n = len(det)
    workers = DECODE_WORKERS if workers is None else workers
    jobs = [(k, min(k + _DECODE_CHUNK, n)) for k in range(0, n, _DECODE_CHUNK)]
    out: list = []
    _DECODE_JOB = (det, id_logits, images, decode_conf)
    try:
        with tqdm(total=n, desc=desc, unit="img", leave=False, disable=desc is None) as bar:
            if workers > 1 and len(jobs) > 1:
                # Forked (the views are inherited, not pickled). No cv2.setNumThreads in the
                # workers: it deadlocks on the thread pool a forked child inherits.
                with mp.get_context("fork").Pool(min(workers, len(jobs))) as pool:
                    for res in pool.imap(_decode_views, jobs):
                        out += res
                        bar.update(len(res))
            else:
                for job in jobs:
                    out += _decode_views(job)
                    bar.update(job[1] - job[0])
    finally:
        _DECODE_JOB = ()
    return out


def look_again(
    net, images: np.ndarray, preds: list, decode_conf: dict, device="cpu", desc: str | None = None, zoomed: dict | None = None
) -> list:
    """``preds`` with the views where nothing was found decoded again on their input
    enlarged ``decode_conf["second_look"]`` times (bilinear; the test sets are stored at
    320x240 only, so this sees less detail than KeypointNet's second look, which resizes
    the full-resolution image). Points are returned in the 320x240 input's pixels.

    ``zoomed``: a dict {view index: (enlarged input, det logits, ID logits)} shared by
    calls on the same images and zoom: views already in it are not run through the
    network again, and the new ones are added."""
    zoom = float(decode_conf.get("second_look", 1.0))
    again = [k for k, p in enumerate(preds) if p is None]
    if zoom <= 1 or not again:
        return list(preds)
    zoomed = {} if zoomed is None else zoomed
    new = [k for k in again if k not in zoomed]
    batches = range(0, len(new), 32)  # batch by batch: thousands of 640x480 logits are GBs
    for b in tqdm(batches, desc=desc and f"{desc}: network at {zoom:g}x", unit="batch", leave=False, disable=desc is None):
        chunk = new[b : b + 32]
        big = np.stack([cv2.resize(images[k], None, fx=zoom, fy=zoom, interpolation=cv2.INTER_LINEAR) for k in chunk])
        det, ids = logits(net, big, batch=2, device=device)  # 640x480 inputs run faster per view in pairs than in large batches
        zoomed.update({k: (big[j], det[j], ids[j]) for j, k in enumerate(chunk)})
    big, det, ids = zip(*(zoomed[k] for k in again))  # lists, not stacked copies
    found = decode_all(det, ids, big, kp.look_conf(decode_conf), desc=desc)
    out = list(preds)
    for k, f in zip(again, found):
        out[k] = None if f is None else ((f[0] + 0.5) / zoom - 0.5, f[1])
    return out


def predict(net, images: np.ndarray, decode_conf: dict | None = None, batch: int = 32, device="cpu"):
    """Decode every image of a (N, 240, 320) uint8 stack: list of (points (3, 2), score) or None."""
    return decode_all(*logits(net, images, batch, device), images, decode_conf)


# The decoding variants tuned at export (named by kp.tuned_key) and the thresholds
# :func:`tune_decoding` searches for each.
DECODINGS = {
    "head": {"ids": "head"},
    "layout": {"ids": "layout"},
    "layout_verify": {"ids": "layout", "verify": True},
    "layout_verify_align": {"ids": "layout", "verify": True, "align": True},
}
LOOKS = ("layout_verify", "layout_verify_align")  # the variants also tuned and evaluated with a second look
TUNING_GRID = {
    "head": {
        "threshold": (0.01, 0.02, 0.05),
        "min_id_prob": (0.1, 0.2, 0.3),
        "min_score": (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6),
    },
    "layout": {"threshold": (0.01, 0.02, 0.05), "min_score": (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6)},
    # The ring evidence (in [0, 1]) scales the scores down: a finer, lower grid. The
    # candidates' threshold is fixed at the lowest value tried, which won at both operating
    # points: each value searched costs a decoding of the validation set.
    "layout_verify": {"threshold": (0.005,), "min_score": tuple(round(0.01 * k, 2) for k in range(1, 41))},
}
TUNING_GRID["layout_verify_align"] = TUNING_GRID["layout_verify"]


def tune_decoding(
    net, data: dict, max_false_positive=0.005, device="cpu", decoding: str = "head", found: list | None = None, heads: tuple | None = None
):
    """The decoding thresholds (:data:`TUNING_GRID`) that detect the most views of ``data``
    (the validation set, with its marker-free views) with at most ``max_false_positive``
    false detections on its marker-free views.

    Args:
        max_false_positive: a budget, or a tuple of budgets (one decoding pass serves all).
        decoding: the decoding variant, a key of :data:`DECODINGS`.
        found: a list to which the predictions of each budget's chosen thresholds are
            appended (what :func:`predict` returns with them), for :func:`tune_second_look`.
        heads: the network's (det, ID) logits of ``data["image"]`` when already at hand.
    Returns:
        (decode conf, its metrics on ``data``), or a list of them for a tuple of budgets.
    """
    budgets = max_false_positive if isinstance(max_false_positive, (tuple, list)) else (max_false_positive,)
    det, id_logits = heads if heads is not None else logits(net, data["image"], device=device)
    grid = dict(TUNING_GRID[decoding])
    min_scores = grid.pop("min_score")
    best: list = [None] * len(budgets)
    for values in itertools.product(*grid.values()):
        dc = {**DECODINGS[decoding], **dict(zip(grid, values))}
        if dc["ids"] == "layout":  # the scoring these thresholds hold for travels with them
            dc["ratio_full"] = dec.default_conf["ratio_full"]
        if dc.get("align"):
            dc.update(
                {k: dec.default_conf[k] for k in ("align_top", "align_min_ratio", "align_orders", "align_cc_power", "align_move_rule")}
            )
        # The best triple does not depend on min_score: decode once at the grid's lowest
        # (which spares aligning triples that cannot reach it), then threshold.
        every = decode_all(det, id_logits, data["image"], {**dc, "min_score": min(min_scores)}, desc=f"tune {decoding}")
        for ms in min_scores:
            kept = [f if f is not None and f[1] >= ms else None for f in every]
            m = score(kept, data)
            for b, budget in enumerate(budgets):
                key = (np.nan_to_num(m["false_positive"]) <= budget, np.nan_to_num(m["detected"]), -np.nan_to_num(m["false_positive"]))
                if best[b] is None or key > best[b][0]:
                    best[b] = (key, {**dc, "min_score": ms}, m, kept)
    if found is not None:
        found.extend(b[3] for b in best)
    out = [(b[1], b[2]) for b in best]
    return out if isinstance(max_false_positive, (tuple, list)) else out[0]


def tune_second_look(
    net,
    data: dict,
    decode_conf: dict,
    zoom: float = 2.0,
    max_false_positive: float | None = None,
    device="cpu",
    first: list | None = None,
    zoomed: dict | None = None,
):
    """The second look's ``look_min_score`` that detects the most views of ``data`` (the
    validation set with its marker-free views) with both looks together within
    ``max_false_positive`` (default :data:`SINGLE_VIEW_FP`), the first look decoded with
    ``decode_conf`` (its predictions ``first`` when already at hand); ``zoomed`` as in
    :func:`look_again`.

    Returns:
        ({"second_look", "look_min_score"}, metrics of both looks on ``data``).
    """
    if max_false_positive is None:
        max_false_positive = SINGLE_VIEW_FP
    if first is None:
        first = predict(net, data["image"], decode_conf, device=device)
    grid = TUNING_GRID["layout_verify"]["min_score"]
    again = look_again(
        net,
        data["image"],
        first,
        {**decode_conf, "second_look": zoom, "look_min_score": min(grid)},
        device,
        desc="tune second look",
        zoomed=zoomed,
    )
    best = None
    for ms in grid:
        m = score([f if f is not None else a if a is not None and a[1] >= ms else None for f, a in zip(first, again)], data)
        key = (np.nan_to_num(m["false_positive"]) <= max_false_positive, np.nan_to_num(m["detected"]), -np.nan_to_num(m["false_positive"]))
        if best is None or key > best[0]:
            best = (key, {"second_look": zoom, "look_min_score": ms}, m)
    return best[1], best[2]


def score(preds: list, data: dict, tolerance_px: float = 8.0) -> dict:
    """Stage-1 metrics at full resolution.

    A view with all three rings labelled visible is *detected* when the decoder returns a
    triple whose every centre lies within ``tolerance_px`` of the same-ID ground truth.
    A failure counts as a failure (error = inf). On views with no labelled ring any
    returned triple is a false positive.

    Returns:
        dict: n_views, detected (fraction), id_accuracy (fraction of returned points
        nearest to the ground-truth centre of their own ID, among returned triples),
        median_px / p95_px (full-resolution error of the points of detected views),
        n_negatives, false_positive (fraction).
    """
    full = np.all(data["labels"] == 1, axis=1)
    none = np.all(data["labels"] == 0, axis=1)
    ok, errs, id_ok, id_n, fp = [], [], 0, 0, []
    for k, pred in enumerate(preds):
        if none[k]:
            fp.append(pred is not None)
        if not full[k]:
            continue
        gt = data["points"][k].astype(np.float64)
        if pred is None:
            ok.append(False)
            continue
        d = np.linalg.norm((pred[0] - gt) * data["scale"][k], axis=1)
        ok.append(bool(np.all(d <= tolerance_px)))
        if ok[-1]:
            errs += d.tolist()
        cross = np.linalg.norm((pred[0][:, None] - gt[None]) * data["scale"][k], axis=2)
        id_ok += int(np.sum(np.argmin(cross, axis=1) == np.arange(3)))
        id_n += 3
    e = np.array(errs) if errs else np.array([np.inf])
    return {
        "n_views": int(full.sum()),
        "detected": float(np.mean(ok)) if ok else float("nan"),
        "id_accuracy": id_ok / id_n if id_n else float("nan"),
        "median_px": float(np.median(e)),
        "p95_px": float(np.percentile(e, 95)) if errs else float("inf"),
        "n_negatives": int(none.sum()),
        "false_positive": float(np.mean(fp)) if fp else float("nan"),
    }


# --- training --------------------------------------------------------------------------
def crop(image: np.ndarray, points: np.ndarray, labels: np.ndarray, rng, size=(192, 144)):
    """A training window of ``size`` (multiples of 8): around the marker when it fits.

    The network is fully convolutional, so it can learn from windows and still run on
    the whole 320x240 image; most of a frame is background, so a window around the
    marker gives ~3x more training steps for the same compute. Rings cut by the window
    are ignored by the loss (centre within 3 px of its edge) or absent (outside).
    """
    h, w = image.shape
    cw, ch = size
    vis = labels != 0
    x0, y0 = int(rng.integers(0, w - cw + 1)), int(rng.integers(0, h - ch + 1))
    if vis.any() and rng.uniform() < 0.85:
        p = points[vis]
        lo = np.floor(p.min(0)).astype(int)
        hi = np.ceil(p.max(0)).astype(int)
        # Windows that hold all visible centres with a margin, if the marker is small enough.
        xs = (max(0, hi[0] + 8 - cw), min(w - cw, lo[0] - 8))
        ys = (max(0, hi[1] + 8 - ch), min(h - ch, lo[1] - 8))
        if xs[0] <= xs[1]:
            x0 = int(rng.integers(xs[0], xs[1] + 1))
        if ys[0] <= ys[1]:
            y0 = int(rng.integers(ys[0], ys[1] + 1))
    out = image[y0 : y0 + ch, x0 : x0 + cw]
    p = points - np.array([x0, y0], np.float32)
    lab = labels.copy()
    dist = np.minimum(np.minimum(p[:, 0], cw - 1 - p[:, 0]), np.minimum(p[:, 1], ch - 1 - p[:, 1]))
    lab[(dist < 0) | ~np.isfinite(dist)] = 0
    lab[(dist >= 0) & (dist < 3) & (lab == 1)] = -1
    return out, p, lab


def check_window(window) -> tuple[int, int] | None:
    """A training window (width, height) as a tuple, or None (whole images); ValueError
    unless both are positive multiples of 8 (the network's cells) within 320x240."""
    if window is None:
        return None
    w, h = (int(v) for v in window)
    if not (0 < w <= kp.INPUT_SIZE[0] and 0 < h <= kp.INPUT_SIZE[1] and w % 8 == 0 and h % 8 == 0):
        raise ValueError(f"the training window must be two multiples of 8 within {kp.INPUT_SIZE[0]}x{kp.INPUT_SIZE[1]}, got {w}x{h}")
    return w, h


def epoch_order(data: dict, rng, small_boost: float = 1.0) -> np.ndarray:
    """The training views of one epoch, as indices into ``data``: a permutation when
    ``small_boost`` is 1; otherwise as many views, drawn with replacement, those with a
    marker under :data:`SMALL_RING_PX` at the network input ``small_boost`` times as often."""
    n = len(data["ring_px"])
    if small_boost == 1.0:
        return rng.permutation(n)
    if small_boost <= 0:
        raise ValueError(f"small_boost must be > 0, got {small_boost}")
    size = data["ring_px"] / data["scale"][:, 0]
    w = np.where((data["ring_px"] > 0) & (size < SMALL_RING_PX), small_boost, 1.0)
    return rng.choice(n, n, replace=True, p=w / w.sum())


def _batch(data: dict, idx: np.ndarray, rng, window=None) -> tuple:
    """The views ``idx`` augmented (and cut to ``window``): images, location and ID targets."""
    imgs, dets, ids = [], [], []
    for j in idx:
        im, p, lab = augment(data["image"][j], data["points"][j], data["labels"][j], rng)
        if window is not None:
            im, p, lab = crop(im, p, lab, rng, window)
        d, i = make_targets(p, lab, size=(im.shape[1], im.shape[0]))
        imgs.append(im)
        dets.append(d)
        ids.append(i)
    return np.stack(imgs), np.stack(dets), np.stack(ids)


_BATCH_JOB: tuple = ()  # (data, window) of the running _batches, inherited by its forked workers


def _seeded_batch(job: tuple) -> tuple:
    idx, seed = job
    data, window = _BATCH_JOB
    return _batch(data, idx, np.random.default_rng(seed), window)


def _batches(data: dict, idx: np.ndarray, rng, bs: int, window=None, workers: int = 1):
    """One epoch's batches of ``bs`` views in the order ``idx``. ``workers`` > 1: augmented
    in that many forked processes (the views are inherited, not pickled), each batch from
    its own seed drawn from ``rng``, so the batches do not depend on the number of
    workers, but differ from those of one worker (one stream through the epoch), which
    is what the shipped weights were trained on."""
    global _BATCH_JOB
    starts = range(0, len(idx) - bs + 1, bs)
    if workers <= 1:
        for k in starts:
            yield _batch(data, idx[k : k + bs], rng, window)
        return
    jobs = [(idx[k : k + bs], int(s)) for k, s in zip(starts, rng.integers(0, 2**63, len(starts)))]
    _BATCH_JOB = (data, window)
    try:
        with mp.get_context("fork").Pool(workers) as pool:
            yield from pool.imap(_seeded_batch, jobs, chunksize=4)
    finally:
        _BATCH_JOB = ()


def main(
    conf: dict | None = None, out_dir: str | Path = "runs/keypoints", resume: bool = False, data_dir: str | Path = "runs/data"
) -> Path:
    """Train stage 1. Writes ``last.pt``, ``best.pt`` and ``history.json`` into ``out_dir``.

    Returns:
        the path of the best checkpoint (best detection rate minus false-positive rate).
    """
    import torch

    c = {**default_conf, **(conf or {})}
    c["window"] = check_window(c["window"])
    data_dir = Path(data_dir)
    c["device"] = c["device"] or ("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(c["seed"])
    train = cached(
        data_dir / f"kp_train_{c['seed']}_{c['train_size']}.npz",
        n=c["train_size"],
        seed=c["seed"],
        workers=c["workers"],
        desc="render train",
    )
    if c["steep_size"]:
        steep = cached(
            data_dir / f"kp_steep_{c['seed']}_{c['steep_size']}.npz",
            n=c["steep_size"],
            seed=c["seed"] + 100,
            conf=STEEP,
            workers=c["workers"],
            desc="render steep",
        )
        train = {k: np.concatenate([train[k], steep[k]]) for k in train}
    val = cached(data_dir / f"kp_val_{c['val_size']}.npz", n=c["val_size"], seed=1, workers=c["workers"], desc="render val")
    dev = c["device"]
    teacher = _teacher(c) if c["teacher"] else None
    net = kp.build_network(c["width"], c["stem_width"], c["stem"]).to(dev)
    w = c["background_weight"]
    ce_loc = torch.nn.CrossEntropyLoss(weight=torch.tensor([1.0] * 64 + [w], device=dev), ignore_index=-100)
    ce_id = torch.nn.CrossEntropyLoss(weight=torch.tensor([1.0, 1.0, 1.0, w], device=dev), ignore_index=-100)

    def batches(rng):
        return _batches(train, epoch_order(train, rng, c["small_boost"]), rng, c["batch_size"], c["window"], c["loader_workers"])

    def as_input(im):
        return torch.from_numpy(im.astype(np.float32) / 255.0)[:, None].to(dev)

    def loss_fn(net, im, det, ids):
        x = as_input(im)
        d_logits, i_logits = net(x)
        if teacher is not None:  # the teacher's distributions per cell, not the labels
            with torch.no_grad():
                d_t, i_t = teacher(x)
            l_loc = _soft_ce(d_logits, d_t)
            l_id = _soft_ce(i_logits, i_t)
        else:
            l_loc = ce_loc(d_logits, torch.from_numpy(det).to(dev))
            l_id = ce_id(i_logits, torch.from_numpy(ids).to(dev))
        return c["lambda_loc"] * l_loc + c["lambda_id"] * l_id, {"loc": l_loc.item(), "id": l_id.item()}

    if teacher is not None and not (resume and (Path(out_dir) / "last.pt").is_file()):
        _start_from_teacher(net, teacher, c, lambda rng: (as_input(b[0]) for b in batches(rng)))

    def describe(m):
        return (
            f"detected {m['detected']:.3f}  id acc {m['id_accuracy']:.3f}  median {m['median_px']:.2f} px  "
            f"fp {m['false_positive']:.3f}  loss loc {m['loc']:.3f} id {m['id']:.3f}"
        )

    return fit(
        net,
        batches,
        len(train["image"]) // c["batch_size"],
        loss_fn,
        lambda net: score(predict(net, val["image"], device=dev), val, c["tolerance_px"]),
        lambda m: np.nan_to_num(m["detected"]) - np.nan_to_num(m["false_positive"]),
        c,
        Path(out_dir),
        resume,
        describe,
        extra={"width": c["width"], "stem_width": c["stem_width"], "stem": c["stem"]},
    )


def _teacher(c: dict):
    """The distillation's teacher (eval mode, frozen); sets ``c``'s widths to its own."""
    from ..nets import load_checkpoint, load_weights

    ck = load_checkpoint(c["teacher"], "keypoints", required=("state_dict", "width"))
    teacher = kp.network_for(ck).to(c["device"]).eval()
    load_weights(teacher, ck["state_dict"], c["teacher"])
    for p in teacher.parameters():
        p.requires_grad_(False)
    c["width"], c["stem_width"] = float(ck["width"]), ck.get("stem_width")
    return teacher


def _soft_ce(logits, teacher_logits):
    """Cross-entropy of ``logits`` against the teacher's softmax over the classes (dim 1),
    averaged over the cells."""
    import torch

    return -(torch.softmax(teacher_logits, 1) * torch.log_softmax(logits, 1)).sum(1).mean()


def _start_from_teacher(net, teacher, c: dict, inputs) -> None:
    """``net`` takes the teacher's weights where the shapes agree, then its stem (the
    layers up to the first halving, which differ) alone learns the teacher's stem
    features: ``c["stem_steps"]`` batches of ``inputs(rng)`` (epochs of it as needed),
    Adam at ``c["stem_lr"]``, mean squared error."""
    import torch

    own, theirs = net.state_dict(), teacher.state_dict()
    same = {k: v for k, v in theirs.items() if k in own and own[k].shape == v.shape}
    net.load_state_dict(same, strict=False)
    stem_len = next(i for i, m in enumerate(teacher.encoder) if isinstance(m, torch.nn.MaxPool2d)) + 1
    stem, target = net.encoder[:stem_len], teacher.encoder[:stem_len]
    opt = torch.optim.Adam(stem.parameters(), lr=c["stem_lr"])
    net.train()
    bar = tqdm(total=c["stem_steps"], desc="stem on the teacher's features", unit="batch")
    epoch, run = 0, None
    while bar.n < c["stem_steps"]:
        for x in inputs(np.random.default_rng([c["seed"], 11, epoch])):
            with torch.no_grad():
                f = target(x)
            loss = torch.nn.functional.mse_loss(stem(x), f)
            opt.zero_grad()
            loss.backward()
            opt.step()
            run = loss.item() if run is None else run + (loss.item() - run) / 50
            bar.update()
            bar.set_postfix(mse=f"{run:.5f}")
            if bar.n >= c["stem_steps"]:
                break
        epoch += 1
    bar.close()


# False-positive budgets of the two operating points tuned at export, per view: a
# single image (the stage-1 target), and a view of a stereo pair, where a false triple
# must also match the other view along the epipolar lines and triangulate to the
# marker's shape (MarkerPose rejects it otherwise), so a looser threshold finds more.
SINGLE_VIEW_FP = 0.005
STEREO_FP = 0.10


# Marker-free validation images the export tunes on: many, so that the 0.5 % budget spans
# enough views for the tuned threshold to hold on held-out ones.
VAL_NEGATIVES = 3000


def validation_sets(data_dir: str | Path = "runs/data", val_size: int = 400, negatives: int = VAL_NEGATIVES, workers: int = 2) -> dict:
    """The validation set (seed 1) joined with marker-free views (seed 2): what the
    decoding thresholds are tuned on. Never the test sets."""
    val = cached(Path(data_dir) / f"kp_val_{val_size}.npz", n=val_size, seed=1, workers=workers, desc="render val")
    neg = cached(
        Path(data_dir) / f"kp_valneg_{negatives}.npz",
        n=negatives,
        seed=2,
        conf={"negative": True},
        workers=workers,
        desc="render val negatives",
    )
    return {k: np.concatenate([val[k], neg[k]]) for k in val}


def export(
    checkpoint: str | Path, dest: str | Path, data_dir: str | Path = "runs/data", val_size: int = 400, negatives: int | None = None
) -> Path:
    """The inference part of a stage-1 checkpoint (weights, width, metrics), with decoding
    thresholds tuned on the validation set (:func:`tune_decoding`; ``val_size`` views and
    ``negatives`` marker-free ones, default :data:`VAL_NEGATIVES`) for every variant of
    :data:`DECODINGS` and :data:`LOOKS`."""
    import torch

    negatives = VAL_NEGATIVES if negatives is None else negatives

    dest = export_checkpoint(checkpoint, dest, "keypoints", keep=("width", "stem_width", "stem"))
    slim = torch.load(dest, weights_only=True)
    net = kp.network_for(slim).eval()
    net.load_state_dict(slim["state_dict"])
    fuse_batchnorm(net)
    val = validation_sets(data_dir, val_size, negatives)
    slim["decode"], firsts, zoomed = {}, {}, {}
    heads = logits(net, val["image"])  # one forward pass serves every variant
    for name in DECODINGS:
        found: list = []
        tuned = tune_decoding(net, val, (SINGLE_VIEW_FP, STEREO_FP), decoding=name, found=found, heads=heads)
        firsts[name] = found[0]  # the single view's predictions, which the second look starts from
        for stereo, (dc, m) in zip((False, True), tuned):
            key = kp.tuned_key(dc["ids"], dc.get("verify", False), stereo, dc.get("align", False))  # what KeypointNet looks up
            slim["decode"][key] = dc
            print(
                f"decoding tuned on the validation set ({key}): {dc} → detected {m['detected']:.3f}, false positives {m['false_positive']:.3f}"
            )
    for name in LOOKS:
        dc, m = tune_second_look(net, val, slim["decode"][name], first=firsts[name], zoomed=zoomed)
        slim["decode"][name + "_look"] = dc
        print(
            f"second look tuned on the validation set ({name}_look): {dc} → detected {m['detected']:.3f}, false positives {m['false_positive']:.3f}"
        )
    torch.save(slim, dest)
    to_onnx(dest)  # what inference loads: the same network and thresholds
    return dest


INT8_IMAGES = 256  # rendered training images that calibrate the int8 copy's activations


def quantize(src: str | Path, dest: str | Path, n: int = INT8_IMAGES, workers: int = 2) -> Path:
    """An int8 copy of stage-1 ONNX weights (:func:`markerpose.nets.quantize_onnx`), its
    activations' ranges calibrated on the first ``n`` images of the training set (seed 0;
    never a held-out set), eight to a batch. The decoding thresholds are the source's."""
    from ..nets import candidate_copies, quantizable_meta, quantize_onnx

    quantizable_meta(src, "keypoints")  # before minutes of rendering
    if int(n) < 1:
        raise ValueError(f"the int8 calibration needs at least one image, got {n}")
    images = generate(int(n), seed=0, workers=workers, desc="render calibration")["image"]
    x = images.astype(np.float32)[:, None] / 255.0  # the network's input, as kp.to_input makes it
    out = quantize_onnx(src, dest, [x[i : i + 8] for i in range(0, len(x), 8)])
    candidate_copies(out)  # what stage 1's candidates run
    return out


def evaluate(
    weights: str | Path | None = None,
    data_dir: str | Path = "runs/data",
    sets: list | None = None,
    workers: int = 2,
    decodings=tuple(DECODINGS),
    second_look: float = 2.0,
) -> dict:
    """Metrics of a stage-1 checkpoint on the held-out test sets (rendered once, cached),
    per decoding variant (:data:`DECODINGS`) and operating point (single view; ``_stereo``:
    the looser thresholds MarkerPose uses on stereo pairs): ``{variant: {set: metrics}}``.
    One forward pass serves all. A variant whose thresholds the checkpoint lacks runs
    with the defaults. ``layout_verify_look``: ring evidence at the single-view
    thresholds with a second look ``second_look`` times larger (:func:`look_again`);
    ``layout_verify_align_look`` likewise with alignment."""
    net = kp.KeypointNet(weights)
    confs = {}
    for name in decodings:
        confs[name] = net.decode_conf(DECODINGS[name])
        confs[name + "_stereo"] = net.decode_conf(DECODINGS[name], stereo=True)
    for name in LOOKS:  # single-view thresholds, a second look where none is found
        if second_look > 1 and name in confs:
            confs[name + "_look"] = net.decode_conf({**DECODINGS[name], "second_look": second_look})
    res: dict = {mode: {} for mode in confs}
    for name in sets or TEST_SETS:
        seed, n, conf = TEST_SETS[name]
        data = cached(Path(data_dir) / f"kp_test_{name}.npz", n=n, seed=seed, conf=conf, workers=workers, desc=f"render {name}")
        t0 = time.perf_counter()
        det, id_logits = logits(net.runner, data["image"])
        t_net = time.perf_counter() - t0
        diag = candidate_recall(det, id_logits, data, net.conf)
        for mode, dc in confs.items():
            t0 = time.perf_counter()
            preds = look_again(
                net.runner,
                data["image"],
                decode_all(det, id_logits, data["image"], dc, desc=f"{name} {mode}"),
                dc,
                desc=f"{name} {mode} look",
            )
            res[mode][name] = {
                **score(preds, data),
                **diag,
                "seconds_per_image": (t_net + time.perf_counter() - t0) / n,
                "by_ring_size": by_ring_size(preds, data),
            }
    return res


# Bins of the outer ring's apparent diameter in network-input pixels (a 1280-px-wide
# frame is shrunk 4x: 12 input px = a 48 px ring at full resolution).
RING_SIZE_BINS = (0.0, 8.0, 12.0, 18.0, 26.0, np.inf)


def by_ring_size(preds: list, data: dict, bins=RING_SIZE_BINS) -> list[dict]:
    """Detection (:func:`score`) of the views with all three rings visible, by the outer
    ring's apparent diameter in network-input pixels: [{"bin", "n_views", "detected"}]."""
    size = data["ring_px"] / data["scale"][:, 0]
    full = np.all(data["labels"] == 1, axis=1)
    out = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        idx = np.nonzero(full & (size >= lo) & (size < hi))[0]
        if len(idx):
            sub = {k: data[k][idx] for k in ("points", "labels", "scale")}
            m = score([preds[j] for j in idx], sub)
            out.append({"bin": f"{lo:g}-{hi:g}", "n_views": len(idx), "detected": m["detected"]})
    return out


def candidate_recall(det: np.ndarray, id_logits: np.ndarray, data: dict, conf: dict, tolerance_px: float = 8.0) -> dict:
    """Where stage 1 loses a marker, before any ID decision: the share of views (all three
    rings visible) whose three centres are all among the candidates (NMS at the
    decoding threshold, best ``max_candidates``) within ``tolerance_px`` at full
    resolution, and among those the share where the ID head's most likely label at each
    true centre is its own ID."""
    c = {**dec.default_conf, **conf}
    full = np.nonzero(np.all(data["labels"] == 1, axis=1))[0]
    found = head_right = 0
    for j in full:
        gt, sc = data["points"][j].astype(np.float64), data["scale"][j]
        cand = dec.nms(dec.score_map(det[j]), c["nms_radius"], c["threshold"], c["max_candidates"])
        if len(cand) == 0 or not np.all(np.linalg.norm((cand[:, None, :2] - gt[None]) * sc, axis=2).min(0) <= tolerance_px):
            continue
        found += 1
        cy = np.clip((gt[:, 1] + 0.5).astype(int) // dec.CELL, 0, id_logits.shape[2] - 1)
        cx = np.clip((gt[:, 0] + 0.5).astype(int) // dec.CELL, 0, id_logits.shape[3] - 1)
        head_right += int(np.all(np.argmax(id_logits[j][:, cy, cx], axis=0) == np.arange(3)))
    return {
        "candidates_found": found / len(full) if len(full) else float("nan"),
        "id_head_right": head_right / found if found else float("nan"),
    }


def speed(widths=(1.0, 0.5, 0.25), runs: int = 20) -> dict:
    """Median milliseconds of one forward pass of a stereo pair (a batch of two 320x240
    inputs; ``pair_ms``) and of one 640x480 input (a second look at 2x; ``look_ms``) per
    network width — a multiplier, or (width, stem_width) — and the parameter counts
    (speed does not depend on the weights)."""
    import torch

    def median_ms(net, x):
        with torch.inference_mode():
            net(x)
            times = []
            for _ in range(runs):
                t0 = time.perf_counter()
                net(x)
                times.append(time.perf_counter() - t0)
        return 1000 * float(np.median(times))

    out = {}
    w0, h0 = kp.INPUT_SIZE
    for w in widths:
        net = kp.build_network(*(w if isinstance(w, tuple) else (w,))).eval()
        params = int(sum(p.numel() for p in net.parameters()))  # as trained and shipped
        fuse_batchnorm(net)  # as KeypointNet runs it
        out[w] = {
            "pair_ms": median_ms(net, torch.rand(2, 1, h0, w0)),
            "look_ms": median_ms(net, torch.rand(1, 1, 2 * h0, 2 * w0)),
            "params": params,
        }
    return out


__all__ = [
    "make_targets",
    "DECODE_WORKERS",
    "DECODINGS",
    "LOOKS",
    "RING_SIZE_BINS",
    "SMALL_RING_PX",
    "TEST_SETS",
    "TUNING_GRID",
    "VAL_NEGATIVES",
    "by_ring_size",
    "cached",
    "candidate_recall",
    "decode_all",
    "default_conf",
    "epoch_order",
    "evaluate",
    "export",
    "generate",
    "look_again",
    "main",
    "predict",
    "score",
    "speed",
    "tune_decoding",
    "tune_second_look",
    "validation_sets",
]
