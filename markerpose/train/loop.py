"""The training loop both networks share: Adam, an optional cosine decay, a progress bar,
per-epoch validation, best and last checkpoints, and resume.

Each network brings its batches, its loss and its validation (see
:mod:`markerpose.train.keypoints` and :mod:`markerpose.train.ellipses`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..formats import write_json


def fit(
    net,
    batches: Callable[[np.random.Generator], Iterator[tuple]],
    steps_per_epoch: int,
    loss_fn: Callable,
    validate: Callable[[object], dict],
    goodness: Callable[[dict], float],
    conf: dict,
    out: Path,
    resume: bool = False,
    describe: Callable[[dict], str] = str,
    extra: dict | None = None,
) -> Path:
    """Train ``net``; returns the path of the best checkpoint.

    Args:
        net: the torch module (already on ``conf["device"]``).
        batches: rng → iterator of input tuples for ``loss_fn`` (one epoch).
        steps_per_epoch: number of batches per epoch (for the bar and the schedule).
        loss_fn: (net, *batch) → (loss tensor, dict of named float terms).
        validate: net → metrics dict (run once per epoch, on a fixed set).
        goodness: metrics → the number to maximise for the best checkpoint.
        conf: ``lr``, ``schedule``, ``epochs``, ``seed``, ``device``, ``init`` (a checkpoint
            to start from, unless resuming); saved in checkpoints.
        out: folder for ``best.pt``, ``last.pt`` and ``history.json``.
        resume: continue from ``out/last.pt`` when it exists.
        describe: metrics → one line printed after each epoch.
        extra: more items saved in the checkpoints (e.g. the network's width).
    """
    import torch

    out.mkdir(parents=True, exist_ok=True)
    opt = torch.optim.Adam(net.parameters(), lr=conf["lr"])
    total = steps_per_epoch * conf["epochs"]
    if conf["schedule"] == "cosine":
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, total) / total)))
    else:
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    history, start, best = [], 0, -math.inf
    if resume and (out / "last.pt").is_file():
        ck = torch.load(out / "last.pt", map_location=conf["device"], weights_only=False)
        net.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        history, start, best = ck["history"], ck["epoch"], ck["best"]
        print(f"resumed from {out / 'last.pt'} after epoch {start}")
    elif conf.get("init"):
        net.load_state_dict(torch.load(conf["init"], map_location=conf["device"], weights_only=False)["state_dict"])
        print(f"initialised from {conf['init']}")

    for epoch in range(start, conf["epochs"]):
        rng = np.random.default_rng([conf["seed"], 7, epoch])  # the same epoch sees the same batches
        net.train()
        t0 = time.perf_counter()
        run: dict = {}
        bar = tqdm(batches(rng), total=steps_per_epoch, desc=f"epoch {epoch + 1}/{conf['epochs']}", unit="batch")
        for k, batch in enumerate(bar, 1):
            loss, terms = loss_fn(net, *batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            for key, v in terms.items():
                run[key] = run.get(key, v) + (v - run.get(key, v)) / min(k, 50)  # running mean, ~50 batches
            bar.set_postfix({k_: f"{v:.4f}" for k_, v in run.items()})
        net.eval()
        metrics = validate(net)
        metrics.update(epoch=epoch + 1, seconds=time.perf_counter() - t0, lr=sched.get_last_lr()[0], **run)
        history.append(metrics)
        print(f"epoch {epoch + 1}: {describe(metrics)} ({metrics['seconds']:.0f} s)")
        weights = {"state_dict": net.state_dict(), "conf": conf, "metrics": metrics, **(extra or {})}
        g = goodness(metrics)
        if g > best:
            best = g
            torch.save(weights, out / "best.pt")
        torch.save(
            {
                **weights,
                "optimizer": opt.state_dict(),
                "scheduler": sched.state_dict(),
                "epoch": epoch + 1,
                "history": history,
                "best": best,
            },
            out / "last.pt",
        )
        write_json(out / "history.json", history)
    if not (out / "best.pt").is_file():  # e.g. resumed after the last epoch
        torch.save(
            {"state_dict": net.state_dict(), "conf": conf, "metrics": history[-1] if history else {}, **(extra or {})}, out / "best.pt"
        )
    return out / "best.pt"


def export(checkpoint: str | Path, dest: str | Path, kind: str, keep: tuple = ()) -> Path:
    """Keep only what inference needs (float32 weights, metrics and those ``keep`` keys it
    has) from a checkpoint of the ``kind`` network ("keypoints" or "ellipses"), with the
    format entry the loader checks (:func:`markerpose.nets.load_checkpoint`)."""
    import torch

    from ..nets import FORMAT

    ck = torch.load(checkpoint, map_location="cpu", weights_only=False)
    slim = {
        "format": {"network": kind, "version": FORMAT},
        "state_dict": {k: v.float() if v.is_floating_point() else v for k, v in ck["state_dict"].items()},
    }
    slim["metrics"] = {k: v for k, v in ck.get("metrics", {}).items() if isinstance(v, (int, float, str))}
    slim.update({k: ck[k] for k in keep if k in ck})
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    torch.save(slim, dest)
    return dest


def to_onnx(weights: str | Path, dest: str | Path | None = None) -> Path:
    """The ONNX copy of an exported ``.pt`` weights file (what inference loads by default):
    the network with batch norm folded, and the file's other contents (format, width,
    tuned thresholds, metrics) in the model's metadata. ``dest`` defaults to the same
    name with ``.onnx``."""
    from .. import ellipses as es
    from .. import keypoints as kp
    from ..nets import candidate_copies, export_onnx, fuse_batchnorm, load_checkpoint, load_weights

    weights = Path(weights)
    import torch

    try:
        kind = torch.load(weights, map_location="cpu", weights_only=True)["format"]["network"]
    except Exception as exc:
        raise ValueError(f"{weights} is not an exported markerpose weights file (`markerpose train ... --export`)") from exc
    ckpt = load_checkpoint(weights, kind)
    if kind == "keypoints":
        net, shape, outputs, dynamic = (
            kp.network_for(ckpt),
            (1, 1, 240, 320),
            ("det", "ids"),
            True,
        )
    else:
        net, shape, outputs, dynamic = es.build_network(), (1, 1, es.PATCH, es.PATCH), ("logits",), False
    net.eval()
    load_weights(net, ckpt["state_dict"], weights)
    fuse_batchnorm(net)
    meta = {k: v for k, v in ckpt.items() if k not in ("state_dict", "format")}
    dest = Path(dest) if dest is not None else weights.with_suffix(".onnx")
    export_onnx(net, dest, shape, kind, meta, outputs, dynamic_hw=dynamic)
    if kind == "keypoints":
        candidate_copies(dest)  # what stage 1's candidates run: the ID head left out
    return dest


__all__ = ["export", "fit", "to_onnx"]
