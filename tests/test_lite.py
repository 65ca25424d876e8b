"""The shipped stage-1 networks (the default's mid, ``default-lite``'s lite, the former
default's standard): the file each runs, the poses they give side by side, and the
settings that name the network and its input."""

from pathlib import Path

import numpy as np
import pytest

import markerpose as mp
from markerpose.experiments import configs
from markerpose.stages import propose
from markerpose.synth import Imaging, look_at_pose, render_stereo

POSES = ([10, 0, 600], [-40, 30, 450], [0, -20, 750])

needs_lite = pytest.mark.skipif(not propose.network_weights("lite").is_file(), reason="no shipped lite weights")


@needs_lite
def test_the_three_networks_give_the_same_poses():
    """Stage 1 only proposes: the edge fit places the centres, so where the default's fast
    network (in float32), default-lite and the former default's networks (mid, standard)
    find the marker the poses agree to 1e-3 mm; each runs its own file, the lite one the
    narrowest, the fast one as wide as the mid one from which it is distilled."""
    rig = mp.StereoRig.default()
    ref, lite = mp.MarkerPose(rig, preset="default-float32"), mp.MarkerPose(rig, preset="default-lite")
    former = configs.build("default-standard-net", rig)
    mid = configs.build("default-mid-net", rig, propose={"int8": False})
    trackers = (ref, lite, former, mid)
    nets = [tr.detector.proposer.net for tr in trackers]
    assert [n.path for n in nets] == [propose.network_weights(k) for k in ("fast", "lite", "standard", "mid")]
    assert nets[1].conf["width"] < nets[0].conf["width"] == nets[3].conf["width"] < nets[2].conf["width"]
    assert nets[1].conf["stem_width"] == nets[0].conf["stem_width"] == nets[3].conf["stem_width"] < nets[2].conf["stem_width"]
    assert nets[0].conf["stem"] == "strided" and nets[3].conf["stem"] == "pool"
    assert nets[0].isotropic and nets[1].isotropic and not nets[2].isotropic
    for seed, pose in enumerate(POSES):
        frame = render_stereo(rig, look_at_pose(pose, 20 + 10 * seed, 40, 30 * seed), imaging=Imaging(alpha=0.6), seed=seed)
        a, *others = (tr.estimate(*frame.images) for tr in trackers)
        assert a is not None and all(o is not None for o in others)
        assert all(np.linalg.norm(a.t - o.t) < 1e-3 for o in others)
        assert np.linalg.norm(a.t - frame.T_left_marker[:3, 3]) < 0.05


def test_the_paper_keeps_the_standard_network_and_a_wrong_network_name_is_refused():
    rig = mp.StereoRig.default()
    paper = mp.MarkerPose(rig, preset="paper").detector.proposer
    assert paper.net.path == propose.network_weights("standard") and not paper.net.isotropic
    with pytest.raises(ValueError, match="network"):
        mp.MarkerPose(rig, propose={"network": "tiny"})


def test_default_lite_is_listed_only_where_its_file_is(monkeypatch, tmp_path):
    if propose.network_weights("lite").is_file():
        assert "default-lite" in configs.available()
    real = configs.default_weights
    monkeypatch.setattr(configs, "default_weights", lambda kind: tmp_path / "none.onnx" if kind == "keypoints-lite" else real(kind))
    names = configs.available()
    assert "default-lite" not in names and "default" in names and "paper" in names
    assert isinstance(propose.network_weights("lite"), Path)


def test_int8_of_a_network_without_a_shipped_copy_says_how_to_make_one(monkeypatch, tmp_path):
    monkeypatch.setattr(propose, "int8_weights", lambda stem: tmp_path / f"{stem}-int8.onnx")
    with pytest.raises(ValueError, match="no int8 copy of the lite stage-1 network.*--int8 SRC DEST"):
        mp.MarkerPose(mp.StereoRig.default(), propose={"network": "lite", "int8": True})


@needs_lite
def test_isotropic_input_keeps_the_images_aspect_and_takes_views_of_two_sizes():
    """``propose.input`` "isotropic": 320 px wide at the image's aspect in whole cells
    (320x256 for 1280x1024, 640x512 at the second look); "paper": 320x240 whatever the image.
    Views of different sizes each get their own pass, and a ring is still found."""
    rig = mp.StereoRig.default()
    lite = mp.MarkerPose(rig, preset="default-lite").detector.proposer
    assert lite.net.isotropic and lite.look_size(1.0, (1024, 1280)) == (320, 256) and lite.look_size(2.0, (1024, 1280)) == (640, 512)
    assert lite.look_size(1.0, (960, 1280)) == (320, 240) and lite.look_size(1.0, (1200, 1600)) == (320, 240)
    paper = mp.MarkerPose(rig, propose={"network": "lite", "input": "paper"}).detector.proposer
    assert not paper.net.isotropic and paper.look_size(1.0, (1024, 1280)) == (320, 240)
    frame = render_stereo(rig, look_at_pose([0, 0, 500]), imaging=Imaging(alpha=0.8), seed=3)
    left, right = frame.images[0], frame.images[1][:960]  # the right view cropped: another aspect
    cands = lite.candidates([left, right])
    for cand, view in zip(cands, frame.views):
        assert min(np.linalg.norm(cand[:, :2] - view.centers[0], axis=1)) < 3.0
