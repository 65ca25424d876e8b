"""Batch norm folded into the convolutions: the same outputs, no norm layers left."""

import copy

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from markerpose import ellipses as es  # noqa: E402
from markerpose import keypoints as kp  # noqa: E402
from markerpose.nets import fuse_batchnorm  # noqa: E402


def _randomised(net, seed=0):
    """Batch-norm statistics and affines far from their initial values, in eval mode."""
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            n = m.num_features
            m.running_mean.copy_(torch.randn(n, generator=g))
            m.running_var.copy_(torch.rand(n, generator=g) * 2 + 0.2)
            m.weight.data.copy_(torch.randn(n, generator=g))
            m.bias.data.copy_(torch.randn(n, generator=g))
    return net.eval()


@pytest.mark.parametrize("build, shape", [
    (lambda: kp.build_network(0.5, 0.25), (2, 1, 240, 320)),
    (lambda: kp.build_network(0.25), (1, 1, 480, 640)),
    (es.build_network, (3, 1, 120, 120)),
])
def test_fused_network_gives_the_same_outputs(build, shape):
    net = _randomised(build())
    fused = fuse_batchnorm(copy.deepcopy(net))
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        a, b = net(x), fused(x)
    for u, v in zip(a if isinstance(a, tuple) else (a,), b if isinstance(b, tuple) else (b,)):
        assert u.shape == v.shape
        np.testing.assert_allclose(v.numpy(), u.numpy(), rtol=1e-4, atol=1e-4 * float(u.abs().max()))


def test_fusing_a_network_in_training_mode_is_an_error():
    with pytest.raises(ValueError, match="eval"):
        fuse_batchnorm(kp.build_network(0.25))
