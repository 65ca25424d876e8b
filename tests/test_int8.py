"""Stage 1 in int8: the shipped quantized copy of the keypoint network (the default's;
preset ``default-float32`` without it) and the tool that makes it
(:func:`markerpose.nets.quantize_onnx`)."""

import json

import numpy as np
import pytest

import markerpose as mp
from markerpose import nets
from markerpose.experiments import configs
from markerpose.keypoints import KeypointNet
from markerpose.stages import propose
from markerpose.synth import Imaging, look_at_pose, render_stereo

POSES = ([10, 0, 600], [-40, 30, 450], [0, -20, 750])


def _frames():
    rig = mp.StereoRig.default()
    for seed, pose in enumerate(POSES):
        yield render_stereo(rig, look_at_pose(pose, 20 + 10 * seed, 40, 30 * seed), imaging=Imaging(alpha=0.6), seed=seed)


@pytest.mark.parametrize("stem", ["keypoints", "keypoints-mid", "keypoints-fast"])
def test_int8_stage1_finds_float32s_candidates(stem):
    """The quantized network's candidates near each ring centre are within a fraction of
    a pixel of the float32 network's, with scores within 0.1 (the standard, mid and fast
    networks)."""
    f32, i8 = KeypointNet(nets.default_weights(stem)), KeypointNet(nets.int8_weights(stem))
    for frame in _frames():
        grays = [np.asarray(im) for im in frame.images]
        for a, b, view in zip(f32.candidates(grays), i8.candidates(grays), frame.views):
            for c in view.centers:
                ka = np.argmin(np.linalg.norm(a[:, :2] - c, axis=1))
                kb = np.argmin(np.linalg.norm(b[:, :2] - c, axis=1))
                assert np.linalg.norm(a[ka, :2] - c) < 3.0  # stage 1 found the ring
                assert np.linalg.norm(a[ka, :2] - b[kb, :2]) < 0.5
                assert abs(a[ka, 2] - b[kb, 2]) < 0.1


@pytest.mark.parametrize("gain", [1.0, 2.2])
def test_the_default_int8_stage1_gives_float32s_poses(gain):
    """Stage 1 only proposes: the edge fit places the centres, so the poses agree to
    1e-3 mm, also on images brighter than the renderer's (the paper near 90 % of full
    scale, as cameras are often set), outside most of the calibration images' range."""
    rig = mp.StereoRig.default()
    ref, i8 = mp.MarkerPose(rig, preset="default-float32"), mp.MarkerPose(rig)
    stem = propose.NETWORKS[propose.default_conf["network"]]
    assert i8.detector.proposer.net.path == nets.int8_weights(stem) and ref.detector.proposer.net.path == nets.default_weights(stem)
    # The paper's configuration keeps its float32 network.
    assert mp.MarkerPose(rig, preset="paper").detector.proposer.net.path == nets.default_weights("keypoints")
    for frame in _frames():
        images = [np.clip(np.asarray(im, np.float32) * gain, 0, 255).astype(np.uint8) for im in frame.images]
        a, b = ref.estimate(*images), i8.estimate(*images)
        assert a is not None and b is not None
        assert np.linalg.norm(a.t - b.t) < 1e-3
        assert np.linalg.norm(a.t - frame.T_left_marker[:3, 3]) < 0.05


def test_int8_needs_the_shipped_weights_and_falls_back_to_float32_where_there_is_none(monkeypatch, tmp_path):
    rig = mp.StereoRig.default()
    with pytest.raises(ValueError, match="--int8 SRC DEST"):
        mp.MarkerPose(rig, propose={"int8": True, "weights": "mine.onnx"})
    with pytest.raises(ValueError, match="int8.*true, false or null"):
        mp.MarkerPose(rig, propose={"int8": "yes"})
    mine = mp.MarkerPose(rig, propose={"weights": str(nets.default_weights("keypoints-lite"))})
    assert mine.detector.proposer.net.path == nets.default_weights("keypoints-lite")  # your weights as given
    assert {"default", "default-float32"} <= set(configs.available())
    missing = tmp_path / "keypoints-int8.onnx"
    for module in (nets, configs, propose):
        monkeypatch.setattr(module, "int8_weights", lambda kind: missing)
    assert "default" in configs.available()
    assert mp.MarkerPose(rig).detector.proposer.net.path == nets.default_weights("keypoints-fast")
    with pytest.raises(ValueError, match="no int8 copy"):
        mp.MarkerPose(rig, propose={"int8": True})
    with pytest.raises(ValueError, match="not found.*--int8 SRC DEST"):
        nets.load_network(missing, "keypoints", None)


def test_the_shipped_int8_file_loads_on_older_runtimes():
    """Only the default operator set is declared (the quantization tool declares every
    domain the installed runtime knows, which older ONNX Runtimes refuse), and the input
    is quantized over [0, 1] in steps of 1/255: each grey level exactly."""
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    model = onnx.load(str(nets.int8_weights("keypoints")))
    assert {o.domain for o in model.opset_import} <= {"", "ai.onnx"}
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == model.graph.input[0].name)
    assert inits[q.input[1]] == pytest.approx(1 / 255) and inits[q.input[2]] == 0


def test_quantize_onnx_keeps_the_metadata_and_refuses_what_it_cannot_quantize(tmp_path):
    pytest.importorskip("onnx")
    import onnx

    rng = np.random.default_rng(0)
    batches = [rng.random((2, 1, 240, 320), np.float32) for _ in range(2)]
    dest = nets.quantize_onnx(nets.WEIGHTS_DIR / "keypoints.onnx", tmp_path / "k8.onnx", batches)
    meta = json.loads(next(m.value for m in onnx.load(str(dest)).metadata_props if m.key == nets.META_KEY))
    src = json.loads(next(m.value for m in onnx.load(str(nets.WEIGHTS_DIR / "keypoints.onnx")).metadata_props if m.key == nets.META_KEY))
    assert meta["int8"] == {"calibration_inputs": 4}
    assert {o.domain for o in onnx.load(str(dest)).opset_import} <= {"", "ai.onnx"}
    assert {k: v for k, v in meta.items() if k != "int8"} == src  # format, width, tuned thresholds
    graph = onnx.load(str(dest)).graph
    inits = {i.name: i for i in graph.initializer}
    last = [n for n in graph.node if set(n.output) & {"det", "ids"}]
    assert len(last) == 2 and all(inits[n.input[1]].data_type == onnx.TensorProto.FLOAT for n in last)  # float logits
    assert sum(n.op_type == "QuantizeLinear" for n in graph.node) > 10  # the rest is int8
    net = KeypointNet(dest)  # loads as any markerpose keypoints model
    det, ids = net.logits(np.zeros((1, 240, 320), np.float32))
    assert det.shape == (1, 65, 30, 40) and ids.shape == (1, 4, 30, 40)
    with pytest.raises(ValueError, match="already quantized"):
        nets.quantize_onnx(dest, tmp_path / "again.onnx", batches)
    bare = onnx.load(str(nets.WEIGHTS_DIR / "keypoints.onnx"))
    del bare.metadata_props[:]
    onnx.save(bare, str(tmp_path / "bare.onnx"))
    with pytest.raises(ValueError, match="not a markerpose ONNX model"):
        nets.quantize_onnx(tmp_path / "bare.onnx", tmp_path / "x.onnx", batches)
    with pytest.raises(ValueError, match="calibration inputs"):
        nets.quantize_onnx(nets.WEIGHTS_DIR / "keypoints.onnx", tmp_path / "y.onnx", [])
    with pytest.raises(ValueError, match="not a markerpose keypoints model"):
        nets.quantizable_meta(nets.WEIGHTS_DIR / "ellipses.onnx", "keypoints")
    with pytest.raises(ValueError, match="not a readable ONNX model"):
        nets.quantizable_meta(nets.WEIGHTS_DIR / "keypoints.pt")
    with pytest.raises(ValueError, match="no such file"):
        nets.quantizable_meta(tmp_path / "none.onnx")


@pytest.mark.parametrize("stem, n_float, n_int8", [("keypoints-mid", 4 + 2, 6), ("keypoints-fast", 4 + 2, 6)])
def test_the_narrow_layers_stay_float32(stem, n_float, n_int8):
    """The shipped int8 copies of the mid and fast networks keep float32 where int8 runs
    slower (outputs under nets.INT8_MIN_CHANNELS channels: the stem; the convolution that
    reads the one-channel input) and for the logits; every other convolution takes int8
    weights."""
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(nets.int8_weights(stem)))
    inits = {i.name: i for i in model.graph.initializer}
    produced = {o: n for n in model.graph.node for o in n.output}
    kinds = {}
    for n in model.graph.node:
        if n.op_type != "Conv":
            continue
        w = n.input[1]
        if w in inits:  # a float32 weight
            kinds[n.name] = ("float", inits[w].dims[0])
        else:  # dequantized from int8
            q = inits[produced[w].input[0]]
            kinds[n.name] = ("int8" if q.data_type == onnx.TensorProto.INT8 else "?", q.dims[0])
    outputs = {o.name for o in model.graph.output}
    for n in model.graph.node:
        if n.op_type == "Conv":
            kind, channels = kinds[n.name]
            reads_input = model.graph.input[0].name in n.input
            float32 = channels < nets.INT8_MIN_CHANNELS or reads_input or bool(set(n.output) & outputs)
            assert kind == ("float" if float32 else "int8"), (n.name, kind, channels)
    assert sum(k == "float" for k, _ in kinds.values()) == n_float and sum(k == "int8" for k, _ in kinds.values()) == n_int8
