"""What runs the networks: ONNX Runtime (the default) or OpenVINO at float32 or bfloat16."""

import sys

import numpy as np
import pytest

import markerpose as mp
from markerpose import nets
from markerpose.experiments import configs
from markerpose.synth import Imaging, look_at_pose, render_stereo


def test_openvino_gives_onnxruntimes_poses():
    """Float32 on OpenVINO is the same network: the same centres to 1e-3 px. In bfloat16
    the networks' outputs move, but the edge fit places the centres: within 0.02 px."""
    pytest.importorskip("openvino")
    rig = mp.StereoRig.default()
    ort, f32, bf16 = mp.MarkerPose(rig), mp.MarkerPose(rig, backend="openvino"), mp.MarkerPose(rig, preset="default-bf16")
    assert (
        ort.detector.proposer.net.runner.backend,
        f32.refiner.net.runner.backend,
        bf16.detector.proposer.net.runner.backend,
        bf16.refiner.net.runner.backend,
    ) == ("onnxruntime", "openvino", "openvino-bf16", "openvino-bf16")
    for seed, pose in enumerate(([10, 0, 600], [-40, 30, 450], [0, -20, 750])):
        f = render_stereo(rig, look_at_pose(pose, 20 + 10 * seed, 40, 30 * seed), imaging=Imaging(alpha=0.6), seed=seed)
        a, b, c = ort.estimate(*f.images), f32.estimate(*f.images), bf16.estimate(*f.images)
        assert a is not None and b is not None and c is not None
        np.testing.assert_allclose(b.centers, a.centers, atol=1e-3)
        np.testing.assert_allclose(c.centers, a.centers, atol=0.02)


def test_a_missing_runtime_is_a_clear_error_and_its_preset_is_left_out(monkeypatch):
    monkeypatch.setitem(sys.modules, "openvino", None)  # importing it fails, as when it is not installed
    with pytest.raises(ValueError, match=r"pip install -e \".\[openvino\]\""):
        mp.MarkerPose(mp.StereoRig.default(), backend="openvino")
    assert not nets.have_backend("openvino-bf16") and nets.have_backend("onnxruntime")
    names = configs.available()
    assert "default" in names and "default-bf16" not in names


def test_openvino_runs_onnx_files_only():
    # The weights' kind is checked before OpenVINO is looked for: the same message without it.
    pt = {stage: {"weights": nets.WEIGHTS_DIR / f"{name}.pt"} for stage, name in (("propose", "keypoints"), ("refine", "ellipses"))}
    with pytest.raises(ValueError, match=r"\.pt: the openvino backend runs .onnx weights only"):
        mp.MarkerPose(mp.StereoRig.default(), backend="openvino", **pt)
    if nets.have_backend("openvino"):  # each network's own weights, named
        with pytest.raises(ValueError, match=r"keypoints\.pt: the openvino backend runs .onnx weights only"):
            mp.MarkerPose(mp.StereoRig.default(), backend="openvino", propose=pt["propose"])


def test_an_unknown_backend_is_refused():
    with pytest.raises(ValueError, match=r"backend must be one of \[.*got 'tensorrt'"):
        mp.MarkerPose(mp.StereoRig.default(), backend="tensorrt")
