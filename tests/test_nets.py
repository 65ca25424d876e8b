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


@pytest.mark.parametrize(
    "build, shape",
    [
        (lambda: kp.build_network(0.5, 0.25), (2, 1, 240, 320)),
        (lambda: kp.build_network(0.25), (1, 1, 480, 640)),
        (es.build_network, (3, 1, 120, 120)),
    ],
)
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


def test_onnx_and_torch_give_the_same_centres():
    """The shipped ONNX files (inference) and .pt files (training) are the same networks:
    the pipeline's centres agree to 1e-3 px on fixed rendered pairs."""
    import markerpose as mp
    from markerpose.nets import WEIGHTS_DIR
    from markerpose.synth import Imaging, look_at_pose, render_stereo

    rig = mp.StereoRig.default()
    onnx = mp.MarkerPose(rig, propose={"weights": WEIGHTS_DIR / "keypoints.onnx"}, refine={"weights": WEIGHTS_DIR / "ellipses.onnx"})
    pt = mp.MarkerPose(rig, propose={"weights": WEIGHTS_DIR / "keypoints.pt"}, refine={"weights": WEIGHTS_DIR / "ellipses.pt"})
    assert onnx.detector.proposer.net.runner.backend == "onnxruntime" and pt.detector.proposer.net.runner.backend == "torch"
    for seed, pose in enumerate(([10, 0, 600], [-40, 30, 450], [0, -20, 750])):
        f = render_stereo(rig, look_at_pose(pose, 20 + 10 * seed, 40, 30 * seed), imaging=Imaging(alpha=0.6), seed=seed)
        a, b = onnx.estimate(*f.images), pt.estimate(*f.images)
        assert a is not None and b is not None
        np.testing.assert_allclose(a.centers, b.centers, atol=1e-3)
        np.testing.assert_allclose(a.T, b.T, atol=1e-4)
