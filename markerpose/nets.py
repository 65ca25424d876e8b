"""What both networks share at inference: loading a weights file safely, and batch norm
folded into the convolutions."""

from __future__ import annotations

import zipfile
from pathlib import Path

# The format of the exported weights files (``--export``): a ``format`` entry names the
# network and this number, so a file of the other network, of an older export or not of
# markerpose at all fails at load with a message rather than inside torch.
FORMAT = 1


def load_checkpoint(path: str | Path, kind: str, device: str = "cpu", required: tuple = ("state_dict",)) -> dict:
    """A weights file as a dict, or ``ValueError`` naming the file and what is wrong.

    Args:
        path: the file.
        kind: "keypoints" or "ellipses": the network it must be for. An exported file
            says so in its ``format`` entry ``{"network": kind, "version": FORMAT}``; a
            training checkpoint (``best.pt``/``last.pt``, no ``format``) is accepted
            when it has the ``required`` keys.
        required: keys the dict must have.
    """
    import pickle

    import torch

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{kind} weights not found: {path} (train them with `markerpose train {kind}`)")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError, AttributeError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path} is not a readable PyTorch weights file ({first[:160]})") from exc
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path} is not a markerpose {kind} weights file: holds a {type(ckpt).__name__}")
    fmt = ckpt.get("format")
    if fmt is not None and fmt != {"network": kind, "version": FORMAT}:
        raise ValueError(f"{path} is not a markerpose {kind} weights file of format {FORMAT}: its format is {fmt}")
    if fmt is None and "decode" in ckpt:
        raise ValueError(f"{path} was exported without a format entry (before format {FORMAT}): export it again")
    for key in required:
        if key not in ckpt:
            raise ValueError(f"{path} is not a markerpose {kind} weights file: no {key!r}")
    return ckpt


def load_weights(net, state_dict, path: str | Path) -> None:
    """``net.load_state_dict(state_dict)`` (strict: every weight must match), or ``ValueError``
    naming the file when the weights are for another network or another width."""
    try:
        net.load_state_dict(state_dict)
    except (RuntimeError, KeyError, TypeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0][:200]
        raise ValueError(f"{path}: the weights do not fit the network ({first})") from exc


def fuse_batchnorm(net):
    """``net`` (in eval mode) with every ``Conv2d`` followed by a ``BatchNorm2d`` inside an
    ``nn.Sequential`` replaced by one convolution that applies both (the norm becomes an
    ``nn.Identity``). Inference only: the outputs stay the same to float precision, the
    per-pixel norm pass over every feature map is gone. Returns ``net``, changed in place.
    """
    from torch import nn
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if net.training:
        raise ValueError("fuse_batchnorm is for inference: call net.eval() first")
    for seq in [m for m in net.modules() if isinstance(m, nn.Sequential)]:
        for k in range(len(seq) - 1):
            conv, bn = seq[k], seq[k + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[k], seq[k + 1] = fuse_conv_bn_eval(conv, bn), nn.Identity()  # keeps the weights' memory format
    return net


__all__ = ["FORMAT", "fuse_batchnorm", "load_checkpoint", "load_weights"]
