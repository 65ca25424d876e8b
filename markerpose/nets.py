"""What both networks share at inference: batch norm folded into the convolutions."""

from __future__ import annotations


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


__all__ = ["fuse_batchnorm"]
