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


@needs_nets
def test_the_second_look_is_skipped_where_no_view_has_three_strong_candidates(rig):
    """A marker at 1.9 m (rings too small to be matched at the first look) still gets the
    second look: its rings score above ``second_look_min`` at the first. Clutter without the
    marker whose candidates all score under it does not (one forward pass, not two)."""
    from markerpose.experiments.endtoend import SETS, random_pairs

    proposer = propose.NeuralProposer(propose.default_conf, mp.Marker(), "stereo")
    far = render_stereo(rig, look_at_pose([-40, 20, 1900], 50, 30, 120), imaging=Imaging(alpha=0.6), seed=2)
    assert proposer.worth_second_look(proposer.candidates(Frame(list(far.images)).grays))
    weak = [np.array([[10.0, 10, 0.9], [50, 50, 0.25], [90, 90, 0.19]]), np.array([[10.0, 10, 0.9], [50, 50, 0.1]])]
    assert not proposer.worth_second_look(weak)
    # Two strong rings in a view (the third one shadowed, say) are worth it too.
    assert proposer.worth_second_look([np.array([[10.0, 10, 0.99], [50, 50, 0.85], [90, 90, 0.1]]), weak[1]])
    assert propose.NeuralProposer({**propose.default_conf, "second_look_min": 0.0}, mp.Marker(), "stereo").worth_second_look(weak)
    # Marker-free held-out pairs: most are decided after one look.
    tracker = mp.MarkerPose(rig)
    looks = []
    for f, _ in random_pairs({**SETS["marker_free"], "seed": 77}, 6, rig, mp.Marker()):
        assert tracker.estimate(*f.images) is None
        looks.append(proposer.worth_second_look(proposer.candidates(Frame(list(f.images)).grays)))
    assert sum(looks) <= 3, looks
