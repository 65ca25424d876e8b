"""Several tools in one MarkerPose: estimate_all / track_all, one stage 1 for all, identity
by 3D shape, claimed rings, relative poses, and the errors of a wrong tool list."""

import numpy as np
import pytest

import markerpose as mp
from markerpose.geometry import nearest_rotation, rotation_angle
from markerpose.keypoints import KeypointNet
from markerpose.synth import Imaging, look_at_pose, render_tools
from markerpose.tools import tool_set

# Three tools apart in both views of the default rig, tilted and turned differently.
POSES = (
    look_at_pose(np.array([-90.0, 40, 600]), 20, 30, 10),
    look_at_pose(np.array([10.0, -60, 650]), 25, 100, -20),
    look_at_pose(np.array([40.0, 60, 560]), 15, 200, 40),
)


@pytest.fixture(scope="module")
def tools():
    return tool_set(3)


@pytest.fixture(scope="module")
def scene(rig, tools):
    return render_tools(rig, list(zip(tools, POSES)), Imaging(alpha=0.7), seed=11)


@pytest.fixture(scope="module")
def several(rig, tools):
    return mp.MarkerPose(rig, markers=tools)


def _close(est, T, mm=0.3, deg=0.2):
    assert np.linalg.norm(est.t - T[:3, 3]) < mm
    assert np.rad2deg(rotation_angle(nearest_rotation(est.R), T[:3, :3])) < deg


def test_estimate_all_finds_each_tool_at_its_pose(several, scene, tools):
    found = several.estimate_all(*scene.images)
    assert list(found) == [t.name for t in tools]  # the tools' order
    for t, T in zip(tools, POSES):
        _close(found[t.name], T)
    assert several.whys == {} and several.why is None


def test_one_stage1_look_serves_every_tool(rig, tools, scene, monkeypatch):
    calls = []
    run = KeypointNet.candidates
    monkeypatch.setattr(KeypointNet, "candidates", lambda self, images, *a, **k: (calls.append(len(images)), run(self, images, *a, **k))[1])
    assert len(mp.MarkerPose(rig, markers=tools).estimate_all(*scene.images)) == 3
    assert calls == [2]  # one look at both views for the three tools


def test_the_tools_first_cold_hypotheses_are_refined_in_one_batch(rig, tools, scene, monkeypatch):
    """estimate_all refines every tool's first hypothesis in one edge-fit batch, and gives
    the poses, to the bit, that each tool refined alone gives; also where one tool hides
    part of another (whose first hypothesis then differs from the batch's), and with a
    tool's blurred-ring fits (charged to that tool's budget once)."""
    from markerpose import classical
    from markerpose.pipeline import MarkerPose

    hidden = render_tools(rig, [(tools[0], POSES[0]), (tools[1], look_at_pose(np.array([-75.0, 45, 640]), 20, 30, 10))], seed=12)
    blurred = render_tools(rig, list(zip(tools, POSES)), Imaging(alpha=0.7, motion_blur=22.0, motion_angle=30.0), seed=13)
    scenes = (scene, hidden, blurred)
    batched = mp.MarkerPose(rig, markers=tools)
    calls = []
    fit = classical.refine_ellipses_views
    monkeypatch.setattr(classical, "refine_ellipses_views", lambda *a, **k: (calls.append(len(a[0])), fit(*a, **k))[1])
    with_batch = [batched.estimate_all(*f.images) for f in scenes]
    assert calls[0] == 6  # the three tools' first hypotheses, both views, in the first call
    monkeypatch.setattr(MarkerPose, "_cold_together", lambda self, frame, tools, subs: None)
    alone = mp.MarkerPose(rig, markers=tools)
    for got, f in zip(with_batch, scenes):
        want = alone.estimate_all(*f.images)
        assert list(got) == list(want)
        for name in got:
            np.testing.assert_array_equal(got[name].T, want[name].T)
            assert [d.blur_px for d in got[name].detections] == [d.blur_px for d in want[name].detections]
    assert len(with_batch[0]) == len(with_batch[2]) == 3 and len(with_batch[1]) >= 1
    assert max(d.blur_px for e in with_batch[2].values() for d in e.detections) > 5


def test_a_batched_hypothesis_serves_only_the_same_points():
    """What the batch refined for a tool is taken once, and only for the very hypothesis
    (the same centres and score in each view): a tool whose candidates another tool's
    rings thinned refines its own."""
    from markerpose.frame import Frame

    pts = [(np.arange(6.0).reshape(3, 2), 0.9), (np.arange(6.0).reshape(3, 2) + 1, 0.9)]
    frame = Frame([np.zeros((8, 8), np.uint8)] * 2)
    frame.prelay("a", pts, ["left", "right"], 2)
    assert frame.prelaid("b", pts) is None
    assert frame.prelaid("a", [pts[0], (pts[1][0] + 0.5, 0.9)]) is None  # another hypothesis: and the kept one is gone
    assert frame.prelaid("a", pts) is None
    frame.prelay("a", pts, ["left", "right"], 2)
    assert frame.prelaid("a", [(p.copy(), s) for p, s in pts]) == (["left", "right"], 2)
    assert frame.prelaid("a", pts) is None  # once


def test_tools_share_the_networks(several):
    first, *others = several.tools.values()
    for tool in others:
        assert tool.detector.proposer.net.runner is first.detector.proposer.net.runner
        assert tool.refiner.net is first.refiner.net
        assert tool.detector.marker is tool.marker and tool.refiner.marker is tool.marker
    assert several.marker is first.marker and several.tracker is first.tracker


def test_track_all_follows_each_tool_and_finds_one_back(rig, tools):
    tracker = mp.MarkerPose(rig, markers=tools)
    scenes = []
    for k in range(4):
        poses = [(t, T.copy()) for t, T in zip(tools, POSES)]
        for _, T in poses:
            T[0, 3] += 1.5 * k
        if k == 2:
            poses = poses[:2]  # tool3 out of view
        scenes.append((render_tools(rig, poses, Imaging(alpha=0.7), seed=20 + k), poses))
    got, whys = [], []
    for f, _ in scenes:
        got.append(tracker.track_all(*f.images))
        whys.append(dict(tracker.whys))
    assert [e.source for e in got[1].values()] == ["tracked"] * 3
    assert set(got[2]) == {"tool1", "tool2"} and list(whys[2]) == ["tool3"]
    assert set(got[3]) == {"tool1", "tool2", "tool3"}  # back on its first pair
    for found, (_, poses) in zip(got, scenes):
        for t, T in poses:
            _close(found[t.name], T)
    tracker.reset()
    assert all(not t.tracker.history for t in tracker.tools.values())


def test_a_pair_without_tools_gives_an_empty_dict(rig, tools, several):
    far = look_at_pose(np.array([0.0, 3000, 1000]))  # out of both views
    pair = render_tools(rig, [(tools[0], far)], seed=3)
    assert several.estimate_all(*pair.images) == {}
    assert set(several.whys) == {t.name for t in tools} and several.why


def test_a_tool_alone_is_not_taken_for_another(rig, tools, several):
    """Only tool2 in view: its rings are tool2's, and no other tool's pose is made of them."""
    pair = render_tools(rig, [(tools[1], POSES[1])], seed=4)
    found = several.estimate_all(*pair.images)
    assert list(found) == ["tool2"]
    _close(found["tool2"], POSES[1])


def test_a_partly_hidden_tool_is_found_right_or_not_at_all(rig, tools, several):
    front = look_at_pose(np.array([-20.0, 0, 520]), 10, 0, 0)
    behind = look_at_pose(np.array([-45.0, 20, 640]), 15, 60, 30)
    pair = render_tools(rig, [(tools[0], front), (tools[1], behind)], seed=6)
    assert pair.truths["tool1"].fully_visible and not pair.truths["tool2"].fully_visible
    found = several.estimate_all(*pair.images)
    _close(found["tool1"], front)
    if "tool2" in found:
        _close(found["tool2"], behind)


def test_relative_poses(several, scene, tools):
    found = several.estimate_all(*scene.images)
    rel = mp.relative_poses(found, "tool1")
    assert set(rel) == {"tool2", "tool3"}
    for t, T in zip(tools[1:], POSES[1:]):
        truth = np.linalg.inv(POSES[0]) @ T
        assert np.linalg.norm(rel[t.name][:3, 3] - truth[:3, 3]) < 0.5
    assert mp.relative_poses({k: v for k, v in found.items() if k != "tool1"}, "tool1") == {}


def test_one_marker_calls_refuse_several_tools(several, scene):
    for call in (lambda: several.estimate(*scene.images), lambda: several.track(*scene.images)):
        with pytest.raises(ValueError, match="_all"):
            call()
    with pytest.raises(ValueError, match="_all"):
        several.detect(scene.images[0])


def test_tool_lists_that_cannot_be_told_apart_are_refused(rig, tools, tmp_path):
    twin = mp.Marker(20.0, 8.0, tools[0].c1, tools[0].c2, name="twin")
    with pytest.raises(ValueError, match="'tool1' and 'twin'"):
        mp.MarkerPose(rig, markers=[tools[0], twin])
    with pytest.raises(ValueError, match="two tools named"):
        mp.MarkerPose(rig, markers=[tools[0], mp.Marker(20.0, 8.0, tools[1].c1, tools[1].c2, name="tool1")])
    with pytest.raises(ValueError, match="not both"):
        mp.MarkerPose(rig, tools[0], markers=tools)
    with pytest.raises(ValueError, match="non-empty"):
        mp.MarkerPose(rig, markers=[])
    with pytest.raises(ValueError, match="one marker|3D shape"):
        mp.MarkerPose(rig, markers=tools, preset="paper")  # the decoded detector
    with pytest.raises(ValueError, match="pose 'paper'"):
        mp.MarkerPose(rig, markers=tools, solve={"pose": "paper"})
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nrings: [[0, 0], [25, 0]]\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        mp.MarkerPose(rig, markers=[tools[0].save(tmp_path / "a.yaml"), bad])


def test_tool_files_load(rig, tools, tmp_path, scene):
    paths = [t.save(tmp_path / f"{t.name}.yaml") for t in tools]
    found = mp.MarkerPose(rig, markers=paths).estimate_all(*scene.images)
    assert list(found) == [t.name for t in tools]


def test_tracked_tools_fitted_in_one_batch_as_each_alone(rig, tools):
    """track_all fits every tracked tool's rings in one batch: the poses are those of each
    tool's own fit, to the last bit, and the batch runs instead of the tools' own fits."""
    batched, alone = mp.MarkerPose(rig, markers=tools), mp.MarkerPose(rig, markers=tools)
    alone._fit_together = lambda frame, expected: None
    calls = []
    fit = batched.refiner.from_ellipses_of
    batched.refiner.from_ellipses_of = lambda *a, **k: (calls.append(len(a[3])), fit(*a, **k))[1]
    for k in range(3):
        poses = [(t, T.copy()) for t, T in zip(tools, POSES)]
        for _, T in poses:
            T[1, 3] += 1.0 * k
        f = render_tools(rig, poses, Imaging(alpha=0.7), seed=40 + k)
        a, b = batched.track_all(*f.images), alone.track_all(*f.images)
        assert list(a) == list(b) == [t.name for t in tools]
        for n in a:
            np.testing.assert_array_equal(a[n].T, b[n].T)
            assert a[n].source == b[n].source == ("detected" if k == 0 else "tracked")
    assert calls == [3, 3]  # frames 1 and 2: one batch of the three tools


def test_rings_of_different_windows_fitted_in_one_edge_batch(rig, tools, scene, monkeypatch):
    """Tools whose ring gaps differ (other edge windows) share one batch of outer-edge fits,
    each ring with its own marker's window: the same fit as the ring's alone."""
    from markerpose import classical, edges

    assert len({classical._edge_windows(t)[1] for t in tools}) > 1
    from markerpose.geometry import ring_ellipses

    gray = classical.to_gray(scene.images[0])
    ellipses = [ring_ellipses(rig.cameras[0], scene.truths[t.name].T_left_marker, t.points3d, t.outer_radius) for t in tools]
    calls = []
    fit = edges.refine_edges
    monkeypatch.setattr(edges, "refine_edges", lambda *a, **k: (calls.append(len(a[2])), fit(*a, **k))[1])
    together = classical.refine_ellipses_views([gray] * 3, ellipses, tools[0], markers=list(tools), cameras=[rig.cameras[0]] * 3)
    assert calls[0] == 9  # the nine outer edges in one batch
    for t, e, (c, ok, _) in zip(tools, ellipses, together):
        alone = classical.refine_ellipses_views([gray], [e], t, cameras=[rig.cameras[0]])[0]
        assert ok.all()
        np.testing.assert_array_equal(c, alone[0])
