"""The propose stage (markerpose.stages.propose): stage 1's candidates, its looks."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.frame import Frame
from markerpose.nets import default_weights
from markerpose.stages import propose
from markerpose.synth import Imaging, look_at_pose, render_stereo

needs_nets = pytest.mark.skipif(not default_weights("keypoints").is_file(), reason="no shipped weights")


@needs_nets
def test_each_ring_has_a_candidate_and_a_call_makes_each_input_once(rig):
    f = render_stereo(rig, look_at_pose([10, -20, 600], 35, 60, 15), imaging=Imaging(alpha=0.7), seed=5)
    proposer = propose.NeuralProposer(propose.default_conf, mp.Marker(), "stereo")
    assert proposer.looks() == (1.0, 2.0)
    frame = Frame(list(f.images))
    cand = proposer.candidates(frame.grays, kept=frame.looked)
    assert len(frame.looked) == 2  # one input per view at the first look
    for c, view in zip(cand, f.views):
        assert c.shape[1] == 3 and len(c) <= propose.MAX_CANDIDATES
        assert np.all(np.diff(c[:, 2]) <= 0)  # best first
        d = np.linalg.norm(c[None, :, :2] - view.centers[:, None], axis=2).min(1)
        assert np.all(d < 4.0), d  # each ring's centre within a few px of a candidate
    proposer.evidence(frame.grays[0], f.views[0].centers[None], kept=frame.looked)
    assert len(frame.looked) == 2  # the evidence looked where the look did


@needs_nets
def test_second_look_off_is_one_look():
    proposer = propose.NeuralProposer({**propose.default_conf, "second_look": 1.0}, mp.Marker(), "stereo")
    assert proposer.looks() == (1.0,)


def test_settings_are_checked():
    with pytest.raises(ValueError, match=r"propose.second_look must be a number >= 1, got 0.5"):
        propose.check_conf({**propose.default_conf, "second_look": 0.5})
    with pytest.raises(ValueError, match=r"unknown propose setting 'candidates'"):  # a constant now: MAX_CANDIDATES
        propose.check_conf({**propose.default_conf, "candidates": 8})
