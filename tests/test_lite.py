"""The lite stage-1 network (preset ``default-lite``): the shipped file it runs, the poses
it gives beside the default's, and the setting that names it."""

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
def test_default_lite_runs_the_lite_network_and_gives_the_defaults_poses():
    """Stage 1 only proposes: the edge fit places the centres, so where both find the
    marker the poses agree to 1e-3 mm; the lite network is the smaller one."""
    rig = mp.StereoRig.default()
    ref, lite = mp.MarkerPose(rig), mp.MarkerPose(rig, preset="default-lite")
    nets = ref.detector.proposer.net, lite.detector.proposer.net
    assert nets[0].path == propose.network_weights("standard") and nets[1].path == propose.network_weights("lite")
    assert nets[1].conf["width"] < nets[0].conf["width"] and nets[1].conf["stem_width"] < nets[0].conf["stem_width"]
    for seed, pose in enumerate(POSES):
        frame = render_stereo(rig, look_at_pose(pose, 20 + 10 * seed, 40, 30 * seed), imaging=Imaging(alpha=0.6), seed=seed)
        a, b = ref.estimate(*frame.images), lite.estimate(*frame.images)
        assert a is not None and b is not None
        assert np.linalg.norm(a.t - b.t) < 1e-3
        assert np.linalg.norm(b.t - frame.T_left_marker[:3, 3]) < 0.05


def test_the_paper_keeps_the_standard_network_and_a_wrong_network_name_is_refused():
    rig = mp.StereoRig.default()
    assert mp.MarkerPose(rig, preset="paper").detector.proposer.net.path == propose.network_weights("standard")
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
    paper = mp.MarkerPose(rig, propose={"network": "lite"}).detector.proposer
    assert not paper.net.isotropic and paper.look_size(1.0, (1024, 1280)) == (320, 240)
    frame = render_stereo(rig, look_at_pose([0, 0, 500]), imaging=Imaging(alpha=0.8), seed=3)
    left, right = frame.images[0], frame.images[1][:960]  # the right view cropped: another aspect
    cands = lite.candidates([left, right])
    for cand, view in zip(cands, frame.views):
        assert min(np.linalg.norm(cand[:, :2] - view.centers[0], axis=1)) < 3.0
