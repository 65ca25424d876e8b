"""The benchmark and the end-to-end evaluation run and report what they measured."""

import itertools

import numpy as np
import pytest

import markerpose as mp
from markerpose.experiments import bench, endtoend


def test_bench_runs_and_reports_every_configuration():
    res = bench.main(
        {"pairs": 1, "blurred_pairs": 1, "empty_pairs": 1, "repeats": 2, "configs": ["paper-classical", "classical-subpixel"]},
        progress=False,
    )
    assert set(res["configs"]) == {"paper-classical", "classical-subpixel"}
    assert res["reference"] == "paper-classical"
    assert res["configs"]["paper-classical"]["speed_vs_reference"] == 1.0
    assert res["configs"]["classical-subpixel"]["found"] == 1.0
    assert res["configs"]["classical-subpixel"]["marker_free_ms"] > 0
    assert res["configs"]["classical-subpixel"]["blur_25_ms"] > 0
    assert res["configs"]["classical-subpixel"]["false_poses"] == 0
    inc = res["configs"]["classical-subpixel"]["inconsistent"]
    assert set(inc) == {"left view twice", "right view twice", "views swapped", "right view shifted 40 px"}
    assert all(v["worst_ms"] > 0 for v in inc.values()) and "Inconsistent pairs" in bench.report(res)
    assert "classical-subpixel" in bench.report(res)


def test_end_to_end_counts_detections_and_errors():
    res = endtoend.main({"pairs": 2, "sets": ("standard",), "configs": ["classical"], "single_view": True}, progress=False)
    s = res["sets"]["standard"]["classical"]
    assert s["pairs"] == 2 and s["detected"] == 1.0 and s["returned_wrong"] == 0.0
    assert s["single_views"] == 4 and s["single_view_detected"] == 1.0
    assert "Each view alone" in endtoend.report(res)
    assert s["center_median_px"] < 0.1 and s["t_median_mm"] < 0.05
    assert "standard" in endtoend.report(res) and "| tilt " in endtoend.report(res)


def test_end_to_end_workers_give_the_same_figures(tmp_path):
    """--workers runs the sets in processes; the figures are those of one process."""
    import json

    conf = {"pairs": 2, "sets": ("marker_free", "standard"), "configs": ["classical"]}
    one = endtoend.main(conf, progress=False)
    two = endtoend.main({**conf, "workers": 2}, tmp_path / "e2e.json", progress=False)  # reported in SETS order
    assert json.loads((tmp_path / "e2e.json").read_text())["sets"].keys() == {"standard", "marker_free"}
    assert list(two["sets"]) == ["standard", "marker_free"]
    assert endtoend.report(two) == endtoend.report(one)
    with pytest.raises(ValueError):
        endtoend.main({**conf, "workers": 0}, progress=False)
    with pytest.raises(ValueError, match="unknown set"):
        endtoend.main({**conf, "sets": ("standart",)}, progress=False)


def test_far_set_lies_beyond_the_working_volume():
    import markerpose as mp

    rig, m = mp.StereoRig.default(), mp.Marker()
    conds = [cd for _, cd in endtoend.pairs("far", 3, rig, m)]
    assert all(800 <= cd["distance"] <= 1600 for cd in conds)
    assert all(350 <= cd["distance"] <= 800 for _, cd in endtoend.pairs("standard", 3, rig, m))


def test_marker_free_set_counts_false_poses_and_detections():
    import numpy as np

    from markerpose.camera import StereoRig
    from markerpose.marker import Marker

    rig, marker = StereoRig.default(), Marker()
    frames = [f for f, _ in endtoend.pairs("marker_free", 2, rig, marker)]
    assert not any(v.in_image.any() for f in frames for v in f.views)  # no ring of the marker in view
    assert all(f.images[0].std() > 10 and not np.array_equal(f.images[0], f.images[1]) for f in frames)  # clutter, per view

    class Claims:  # a tracker that always claims the marker
        def estimate(self, left, right):
            return object()

        def detect(self, image, view=0):
            return object() if view == 0 else None

    r = endtoend.evaluate_marker_free(Claims(), frames[0], single_view=True)
    assert r == {"false_pose": True, "false_views": 1}
    s = endtoend.summarize_marker_free([r, {"false_pose": False, "false_views": 0}])
    assert s == {"pairs": 2, "false_poses": 0.5, "single_views": 4, "single_view_false": 0.25}

    res = endtoend.main({"pairs": 2, "sets": ("marker_free",), "configs": ["classical"], "single_view": True}, progress=False)
    s = res["sets"]["marker_free"]["classical"]
    assert s["pairs"] == 2 and s["false_poses"] == 0.0 and s["single_views"] == 4
    assert "false poses" in endtoend.report(res)


def test_a_pose_returned_with_a_centre_off_counts_as_wrong_not_just_missed():
    import numpy as np

    ok = {"detected": True, "err": np.full(6, 0.01), "err3d": np.full(6, 0.01), "t_mm": 0.01, "r_deg": 0.01}
    off = {"detected": False, "err": np.array([0.01] * 5 + [3.4]), "err3d": np.full(6, 0.5), "t_mm": 2.3, "r_deg": 6.7}
    none = {"detected": False, "err": np.full(6, np.inf), "err3d": np.full(6, np.inf), "t_mm": np.inf, "r_deg": np.inf}
    s = endtoend.summarize([ok, off, none, ok])
    assert s["detected"] == 0.5 and s["returned_wrong"] == 0.25


def test_confidence_intervals():
    import math

    from markerpose.experiments.reproduce import mean_ci, wilson

    ci = mean_ci([1.0, 2.0, 3.0, float("inf")])  # failures (inf) are not averaged in
    assert ci["n"] == 3 and ci["mean"] == 2.0
    assert math.isclose(ci["hi"] - ci["mean"], 4.303 * 1.0 / math.sqrt(3), rel_tol=1e-6)  # t(0.975, 2)
    assert math.isnan(mean_ci([5.0])["lo"]) and mean_ci([])["n"] == 0
    w = wilson(50, 100)
    assert w["p"] == 0.5 and math.isclose(w["lo"], 0.4038, abs_tol=1e-3) and math.isclose(w["hi"], 0.5962, abs_tol=1e-3)
    w = wilson(10, 10)
    assert w["hi"] == 1.0 and 0.69 < w["lo"] < 0.73  # never 0-width at 100 %


def test_experiments_write_report_plots_and_json(tmp_path):
    import json

    from markerpose.experiments import reproduce

    conf = {
        "trials": 1,
        "pairs": 2,
        "alphas": (1.0,),
        "detection_alphas": (1.0, 0.0625),
        "blurs": (0.0, 25.0),
        "configs": ("paper-classical", "classical"),
    }
    res = reproduce.main(conf, tmp_path, progress=False)
    for f in ("report.md", "results.json", "displacement.png", "rotation.png", "detection.png", "accuracy.png"):
        assert (tmp_path / f).stat().st_size > 0
    t1 = res["tables"]["classical"]["table1"]
    assert t1["failed"] == 0 and t1["mae"]["mean"] < 0.01  # mm: sub-pixel + bias on perfect synthetic data
    paper_t1 = res["tables"]["paper-classical"]["table1"]
    assert paper_t1["mae"]["mean"] > t1["mae"]["mean"]
    assert set(res["levels"]["alpha"]) == {"1.0", "0.0625"} and set(res["levels"]["blur"]) == {"0.0", "25.0"}
    assert res["levels"]["alpha"]["1.0"]["paper-classical"]["detection"]["n"] == 2
    text = (tmp_path / "report.md").read_text()
    assert "Table 1" in text and "Table 5" in text and "0.0461" in text  # the paper's number beside ours
    assert json.loads((tmp_path / "results.json").read_text())["conf"]["trials"] == 1
    with pytest.raises(ValueError, match="trials"):
        reproduce.main({"trials": 0}, tmp_path, progress=False)


def test_experiments_command_line():
    from markerpose import cli

    args = cli.build_parser().parse_args(["experiments", "--quick", "--trials", "3", "--out", "x"])
    assert args.func is cli.experiments.cmd_experiments and args.quick and args.trials == 3 and args.pairs is None


def test_detection_plot_at_zero_and_full_detection(tmp_path):
    """Regression: a level where nothing was detected made the Wilson error bar negative by a rounding error."""
    from markerpose.experiments.plots import plot_detection
    from markerpose.experiments.reproduce import wilson

    levels = {
        "alpha": {"1.0": {"a": {"detection": wilson(8, 8)}}, "0.039": {"a": {"detection": wilson(0, 8)}}},
        "blur": {"0.0": {"a": {"detection": wilson(8, 8)}}, "25.0": {"a": {"detection": wilson(3, 8)}}},
    }
    assert plot_detection(levels, tmp_path / "d.png").stat().st_size > 0


def test_cli_render_then_estimate_with_the_default_pipeline(tmp_path, capsys):
    import json

    import numpy as np

    from markerpose import cli

    assert cli.main(["render", "--out", str(tmp_path), "--tilt", "25", "--seed", "3"]) == 0
    capsys.readouterr()
    assert cli.main(["estimate", str(tmp_path / "left.png"), str(tmp_path / "right.png")]) == 0
    out = json.loads(capsys.readouterr().out)
    truth = json.loads((tmp_path / "truth.json").read_text())
    T, T_true = np.array(out["T_left_marker"]), np.array(truth["T_left_marker"])
    assert out["found"] and np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.05  # mm
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)  # the rigid fit by default
    assert 0 < out["residual_px"] < 0.1
    # --set: a stage setting over the preset; the paper's pose construction is not orthonormal.
    pair = [str(tmp_path / "left.png"), str(tmp_path / "right.png")]
    assert cli.main(["estimate", *pair, "--set", "solve.pose=paper", "--set", "match.max_fits=5", "--set", "threads=1"]) == 0
    R = np.array(json.loads(capsys.readouterr().out)["T_left_marker"])[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() > 1e-9
    assert cli.main(["estimate", *pair, "--set", "detector=classical", "--set", "solve.bias_correction=false"]) == 0
    assert json.loads(capsys.readouterr().out)["found"]
    # Wrong settings: a one-line error naming them, exit 2 (a Python-style False would be a
    # string, and true).
    for bad, says in (
        (["track.nope=1"], "unknown track setting"),
        (["solve.bias_correction=False"], "solve.bias_correction must be true or false, got 'False'"),
        (["match.max_fits=many"], "match.max_fits must be a whole number >= 1, got 'many'"),
        (["propose.threshold=NaN"], "propose.threshold must be a number in [0, 1], got nan"),
        (["track=1"], "expected track.KEY=VALUE"),
        (["threads.x=1"], "threads takes a value"),
        (["stagex.y=1"], "unknown stage 'stagex'"),
    ):
        assert cli.main(["estimate", *pair, *sum((["--set", b] for b in bad), [])]) == 2
        err = capsys.readouterr().err
        assert says in err and err.count("\n") == 1, err
    with pytest.raises(SystemExit):
        cli.main(["estimate", *pair, "--set", "lost_change"])
    assert "got 'lost_change'" in capsys.readouterr().err
    # User errors: one line on stderr, exit 2; "not found" is exit 1 with {"found": false}.
    capsys.readouterr()
    assert cli.main(["estimate", str(tmp_path / "missing.png"), str(tmp_path / "right.png")]) == 2
    err = capsys.readouterr().err
    assert "cannot read image" in err and "missing.png" in err and err.count("\n") == 1
    (tmp_path / "junk.png").write_bytes(b"not an image")
    assert cli.main(["estimate", str(tmp_path / "junk.png"), str(tmp_path / "right.png")]) == 2
    assert "cannot read image" in capsys.readouterr().err
    import cv2

    cv2.imwrite(str(tmp_path / "gray.png"), np.full((1024, 1280), 90, np.uint8))
    assert cli.main(["estimate", str(tmp_path / "gray.png"), str(tmp_path / "gray.png"), "--preset", "paper-classical"]) == 1
    assert json.loads(capsys.readouterr().out) == {"found": False}


def test_cli_user_errors_are_one_line(tmp_path, capsys):
    from markerpose import __version__, cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0 and __version__ in capsys.readouterr().out
    assert cli.main(["render", "--out", str(tmp_path / "r"), "--repeat", "0"]) == 2
    assert "--repeat must be >= 1" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert cli.main(["render", "--out", str(tmp_path / "file")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert cli.main(["estimate", "a.png", "b.png", "--rig", str(tmp_path / "nope.yaml")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_cli_output_into_a_closed_pipe_is_quiet(tmp_path, monkeypatch, capsys):
    """``markerpose estimate ... | head -3`` with the reader gone: exit 0, no traceback."""
    import os
    import sys

    from markerpose import cli

    assert cli.main(["render", "--out", str(tmp_path), "--seed", "3"]) == 0
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader has gone: writing raises BrokenPipeError
    saved = os.dup(1)
    try:
        os.dup2(write_end, 1)
        monkeypatch.setattr(sys, "stdout", os.fdopen(os.dup(1), "w"))
        rc = cli.main(["estimate", str(tmp_path / "left.png"), str(tmp_path / "right.png"), "--preset", "paper-classical"])
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(write_end)
    assert rc == 0
    assert "Traceback" not in capsys.readouterr().err


def test_sequence_segments_and_summary():
    """The sequence benchmark's trajectory and figures, on hand-made rows (no rendering)."""
    from markerpose.experiments import sequence as sq

    seg = sq.segments(240)
    assert [seg.count(s) for s, _ in sq.SEGMENTS] == [60, 60, 30, 30, 60]
    poses, seg = sq.trajectory(240, 60.0)
    rig = mp.StereoRig.default()
    c0 = np.array([T[:3, 3] for T in poses])
    px = rig.project(c0)  # (2, 240, 2)
    gone = np.array([s == "out of view" for s in seg])
    w, h = rig.left.image_size
    outside = (px[..., 0] < 0) | (px[..., 0] > w) | (px[..., 1] < 0) | (px[..., 1] > h)
    assert outside[:, gone].all() and not outside[:, ~gone].any()
    assert np.allclose(c0[seg.index("static") : seg.index("hand-held")], c0[0])  # held still

    def row(k, segment, visible, t_mm, ms):
        est = {
            "ms": ms,
            "found": t_mm is not None,
            "source": "tracked" if t_mm is not None else None,
            "t_mm": t_mm,
            "r_deg": 0.01 if t_mm is not None else None,
            "t": [0.0, 0.0, 500.0 + (k % 2) * 0.002] if t_mm is not None else None,
            "R": np.eye(3).tolist() if t_mm is not None else None,
        }
        return {"frame": k, "segment": segment, "visible": visible, "blur_px": 0.0, **dict.fromkeys(sq.METHODS, est)}

    rows = [row(k, "static", True, 0.001, 5.0) for k in range(4)] + [row(4, "out of view", False, None, 50.0)]
    rows += [row(5, "dark", True, None, 80.0), row(6, "dark", True, 0.002, 10.0)]
    s = sq.summarize(rows, "track")
    assert s["detected"] == 5 / 6 and s["false_poses"] == 0 and s["frames_to_reacquire"] == 1
    assert s["jitter_mm"] == pytest.approx(0.001) and s["jitter_deg"] == pytest.approx(0.0, abs=1e-6)
    assert s["median_ms"] == 7.5 and s["max_ms"] == 80.0
    assert "frames to re-acquire" in sq.report({"conf": sq.default_conf, "summary": dict.fromkeys(sq.METHODS, s), "frames": rows})


def test_sequence_methods_run_as_paced_streams_in_alternating_passes(monkeypatch):
    """Each method runs the whole sequence in a row, frames handed over on the stream's
    clock, in ``passes`` passes of alternating order (the statistics pool the passes);
    ``preset`` picks track's and estimate's; a bad pass count, preset or setting is a
    clear error."""
    from markerpose import synth
    from markerpose.experiments import sequence as sq

    rig = mp.StereoRig.default()
    frame = synth.render_stereo(rig, synth.look_at_pose([0, 0, 560], 30, 45, 0), seed=1)
    monkeypatch.setattr(sq, "render", lambda c, rig, marker, progress: ((frame, "static", 0.0) for _ in range(c["frames"])))
    order = []  # which tracker each estimate() call was made on
    real = mp.MarkerPose.estimate

    def logged(self, left, right):
        order.append(id(self))
        return real(self, left, right)

    waits = []  # the stream's clock asks for these pauses (not slept here)
    monkeypatch.setattr(mp.MarkerPose, "estimate", logged)
    monkeypatch.setattr(sq.time, "sleep", waits.append)
    res = sq.main({"frames": 40, "passes": 2, "fps": 20.0, "preset": "default-no-second-look"}, out_dir=None, progress=False)
    assert "the `default-no-second-look` configuration's `track()`" in sq.report(res)
    assert [r["frame"] for r in res["frames"]] == list(range(40))
    assert all(r[m]["found"] and len(r[m]["ms_passes"]) == 2 for r in res["frames"] for m in sq.METHODS)
    assert all(r[m]["ms"] == pytest.approx(np.mean(r[m]["ms_passes"])) for r in res["frames"] for m in sq.METHODS)
    pooled = [v for r in res["frames"][1:] for v in r["track"]["ms_passes"]]
    assert res["summary"]["track"]["max_ms"] == max(pooled) and res["summary"]["track"]["median_ms"] == np.median(pooled)
    # After the three warm-up calls: estimate's 40 frames then paper's, then paper's and estimate's.
    runs = [len(list(g)) for _, g in itertools.groupby(order[3:])]
    assert runs == [40, 80, 40], runs
    # On the 20 frames/s clock the faster methods wait for their frames; back to back, none does.
    assert len(waits) > 40 and all(w > 0 for w in waits)
    waits.clear()
    sq.main({"frames": 40, "passes": 1, "pace": False, "preset": "default-no-second-look"}, out_dir=None, progress=False)
    assert waits == []
    for bad, what in (
        ({"passes": 0}, "passes"),
        ({"preset": "no-such"}, "unknown configuration"),
        ({"block": 10}, "unknown sequence settings"),
    ):
        with pytest.raises(ValueError, match=what):
            sq.main({"frames": 40, **bad}, out_dir=None, progress=False)


def test_jumps_track_each_trial_with_and_without_the_search(tmp_path):
    """Both settings see the same trials; jumps the search finds stage 1 finds too, both
    within 0.05 mm (under 15 px of blur the cold fit may refit the rings under the blur
    model where the tracker's keeps the edge fit: ``refine.blur_long_px``); the marker gone
    gives no pose; the counts add up; bad settings are refused."""
    from markerpose.experiments import jumps

    res = jumps.main({"trials": 6, "seed": 2, "max_jump": 20.0, "max_turn": 3.0}, tmp_path, progress=False)
    rows, s = res["trials"], res["summary"]
    assert len(rows) == 6 and (tmp_path / "results.json").is_file()
    report = (tmp_path / "report.md").read_text()
    assert "| … by the prior / the search / stage 1 |" in report and "| jump, mm | n |" in report
    gone = [r for r in rows if r["empty"]]
    assert len(gone) == 1 and all(r[name]["source"] is None for r in gone for name in jumps.CONFIGS)
    for name in jumps.CONFIGS:
        assert s[name]["wrong_poses"] == s[name]["false_poses"] == 0
        assert s[name]["found"] == s[name]["prior"] + s[name]["search"] + s[name]["stage 1"] <= s[name]["visible"]
        assert sum(b["n"] for b in s[name]["by_jump"].values()) == s[name]["visible"]
    assert s["no search"]["search"] == 0 and s["search"]["search"] >= 3
    by_search = [r for r in rows if r["search"]["how"] == "search"]
    assert all(r["no search"]["how"] == "stage 1" and max(r["search"]["t_mm"], r["no search"]["t_mm"]) < 0.05 for r in by_search)
    for bad, what in (({"trials": 0}, "trials"), ({"block": 1}, "unknown jump settings")):
        with pytest.raises(ValueError, match=what):
            jumps.main(bad, out_dir=None, progress=False)


def test_blur_distance_c0_c1_under_blur_along_it(tmp_path, monkeypatch):
    from markerpose import StereoRig
    from markerpose.experiments import blurdistance as bd
    from markerpose.marker import Marker
    from markerpose.synth import look_at_pose

    rig, marker = StereoRig.default(), Marker()
    # The blur's direction is the image direction of c0 -> c1 (x right, y down): +x for an
    # unrolled marker, turned by the roll (y up in the marker is y down in the image).
    assert all(abs(a) < 1.5 for a in bd.along_c0_c1(rig, marker, look_at_pose([0.0, 0.0, 560.0])))
    assert all(abs(a + 30) < 2 for a in bd.along_c0_c1(rig, marker, look_at_pose([0.0, 0.0, 560.0], roll_deg=30)))
    poses = []
    render = bd.render_stereo
    monkeypatch.setattr(bd, "render_stereo", lambda rig_, T, *a, **k: (poses.append(T), render(rig_, T, *a, **k))[1])
    conf = {"pairs": 2, "lengths": (0.0, 25.0, 25.0), "configs": ("classical",), "path_poses": 3}
    res = bd.main(conf, tmp_path, progress=False)
    rows = res["summary"]["classical"]
    assert [r["length_px"] for r in rows] == [0.0, 25.0] and res["true_mm"] == 25.0  # a repeated length once
    assert len(poses) == 4 + 6 + 6 and np.array_equal(poses[0], poses[1]) and np.array_equal(poses[2], poses[3])  # the same poses at both
    # Found, the distances within a few hundredths of a mm.
    assert all(r["found"] == 1.0 and abs(r["mean_mm"]) < 0.03 and r["max_abs_mm"] >= r["p95_abs_mm"] for r in rows)
    assert all(r["found"] == 1.0 and r["max_abs_mm"] < 0.05 for r in res["summary_c0_c2"]["classical"])
    # The robot path: three poses 10 mm apart along x (c0 -> c1) at 560 mm facing the left
    # camera, blurred along the left view's travel (+x: unrolled) in both views.
    path = bd.path_poses(bd.default_conf | {"path_poses": 3})
    assert np.allclose([T[:3, 3] for T in path], [[-10, 0, 560], [0, 0, 560], [10, 0, 560]])
    assert all(abs(bd.along_travel(rig, T)) < 1.0 for T in path)
    assert abs(bd.along_travel(rig, look_at_pose([0.0, 0.0, 560.0], roll_deg=30)) + 30) < 1.0
    for row in res["path"]["classical"]:
        assert row["c0_c1"]["found"] == 1.0 and row["c0_c1"]["max_abs_mm"] < 0.05 and row["c0_c2"]["max_abs_mm"] < 0.05
        assert row["displacement"]["max_abs_mm"] < 0.05 and 0 < row["same_sign_c0_c1"] <= 1
    # The path again on a 3 mm plate on a dark ground, the trackers given that plate (the
    # classical detector's contours lose a ring to the dark ground under the heaviest blur).
    assert np.array_equal(poses[-1], path[-1]) and len(res["tight"]["classical"]) == 2
    for row in res["tight"]["classical"]:
        assert row["c0_c1"]["found"] >= 0.6 and row["c0_c1"]["max_abs_mm"] < 0.05 and row["c0_c2"]["max_abs_mm"] < 0.05
    report = (tmp_path / "report.md").read_text()
    assert (
        report.startswith("# Distance c0-c1")
        and "robot path" in report
        and "tight plate" in report
        and (tmp_path / "blur-distance.png").stat().st_size > 0
    )
    for bad in (
        {"pairs": 0},
        {"lengths": (-1.0,)},
        {"lengths": ()},
        {"lengths": (0.5,)},
        {"lengths": (float("inf"),)},
        {"lengths": (float("nan"),)},
        {"path_poses": 1},
        {"path_step": 0.0},
        {"path_distance": float("nan")},
    ):
        with pytest.raises(ValueError):
            bd.main(bad, None, progress=False)


def test_tools_scenes_and_the_judge_of_each_pose():
    """The tool scenes: 2 to N tools, every ring inside both images, plates apart but in the
    pairs placed behind; a pose on its own rings is right, on another tool's rings a swap."""
    from markerpose.experiments import tools as te
    from markerpose.tools import tool_set

    rig, tools = mp.StereoRig.default(), tool_set(3)
    for frame, _, _, cond in te.scenes(3, rig, tools, 7, hidden_share=0.5):
        assert 2 <= cond["tools"] == len(frame.truths) <= 3
        assert all(v.in_image.all() for t in frame.truths.values() for v in t.views)
        if not cond["hidden"]:
            assert all(t.fully_visible for t in frame.truths.values())
    a, b = list(frame.truths.values())[:2]

    class Pose:  # what judge reads of an Estimate
        def __init__(self, truth, shift=0.0):
            self.centers = np.stack([v.centers for v in truth.views]) + shift

    assert te.judge(Pose(a), a, {b.marker.name: b}, 3.0) == "right"
    assert te.judge(Pose(b), a, {b.marker.name: b}, 3.0) == "swap"
    assert te.judge(Pose(a, 10.0), a, {b.marker.name: b}, 3.0) == "false"


def test_tools_report_names_the_speed_and_each_stage_of_an_extra_tool():
    """The speed table: the cold ratio, the tracked pairs of 1 / 2 / 3 tools, each extra
    tool's cost and its split by stage (a result without the split, as older JSON, still reports)."""
    from markerpose.experiments import tools as te

    speed = {
        "cold_three_ms": 45.0,
        "cold_one_ms": 30.0,
        "cold_ratio": 1.5,
        "tracked_ms": {"1": 5.0, "2": 8.0, "3": 11.0},
        "per_extra_tool_ms": 3.0,
        "per_extra_tool_stages_ms": {"refine": 2.0, "verify": 0.5, "solve": 0.25},
    }
    res = {"tools": [{"name": "a"}, {"name": "b"}], "least_difference_mm": 9.0, "pairs_by_count": {"2": 1}, "configs": {}, "speed": speed}
    text = te.report(res)
    assert "45.0 / 30.0 = **1.50x**" in text and "5.0 / 8.0 / 11.0" in text and "**3.0**" in text
    assert "| ... of which edge fits / checks / solve, ms | 2.00 / 0.50 / 0.25 |" in text
    del speed["per_extra_tool_stages_ms"]
    assert "of which" not in te.report(res)
