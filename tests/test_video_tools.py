"""markerpose track --tools: several tools through two image folders, one CSV row a frame and tool (markerpose.video)."""

import csv
import json
import re
import socket
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import markerpose as mp
from markerpose import cli
from markerpose.synth import Imaging, look_at_pose, render_tools
from markerpose.tools import tool_set
from markerpose.video import TOOLS_CSV_HEADER

FRAMES = 5  # the last one without tool1, the reference


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    """Two tools moving a little over four rendered pairs, then a pair with tool2 alone;
    the tool files and the PNG folders, and each frame's true poses by name."""
    rig = mp.StereoRig.default()
    root = tmp_path_factory.mktemp("tools")
    for side in "LR":
        (root / side).mkdir()
    tools = tool_set(2)
    files = [str(t.save(root / f"{t.name}.yaml")) for t in tools]
    truth = []
    for k in range(FRAMES):
        poses = {
            "tool1": look_at_pose(np.array([-90.0 + k, 40, 600 - k]), 20 + k, 30, 10),
            "tool2": look_at_pose(np.array([10.0, -60 + k, 650]), 25, 100 + k, -20),
        }
        if k == FRAMES - 1:
            del poses["tool1"]
        scene = [(t, poses[t.name]) for t in tools if t.name in poses]
        images = render_tools(rig, scene, imaging=Imaging(alpha=0.8), seed=k).images
        for side, img in zip("LR", images):
            cv2.imwrite(str(root / side / f"{k:04d}.png"), img)
        truth.append(poses)
    return root, files, truth


def _track(seq, *extra) -> int:
    root, files, _ = seq
    return cli.main(["track", str(root / "L"), str(root / "R"), "--tools", *files, "--detector", "classical", "--quiet", *extra])


def _matrix(row) -> np.ndarray:
    return np.array([float(row[f"T{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)


def _strict(line: str) -> dict:
    """The JSON object of a line, refusing NaN and Infinity (not JSON)."""

    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    return json.loads(line, parse_constant=refuse)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_each_tool_in_the_camera_frame(seq, tmp_path, capsys):
    _, _, truth = seq
    out, jsonl, video = tmp_path / "poses.csv", tmp_path / "p.jsonl", tmp_path / "axes.mp4"
    assert _track(seq, "--out", str(out), "--jsonl", str(jsonl), "--video", str(video)) == 0
    summary = capsys.readouterr().out
    assert f"{FRAMES} frames" in summary and "tool1 found in 80.0 %" in summary and "tool2 found in 100.0 %" in summary
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == TOOLS_CSV_HEADER and len(rows) == FRAMES * 2
    assert [r["tool"] for r in rows] == ["tool1", "tool2"] * FRAMES and {r["relative_to"] for r in rows} == {"camera"}
    for row in rows:
        T = truth[int(row["frame"])].get(row["tool"])
        if T is None:
            assert row["valid"] == "0" and row["x_mm"] == "" and row["T00"] == ""
            continue
        assert row["valid"] == "1"
        t = np.array([float(row[k]) for k in ("x_mm", "y_mm", "z_mm")])
        assert np.linalg.norm(t - T[:3, 3]) < 1.0  # mm
        np.testing.assert_allclose(_matrix(row)[:3, 3], t)
    lines = [_strict(line) for line in jsonl.read_text().splitlines()]
    assert [d["frame"] for d in lines] == list(range(FRAMES)) and list(lines[0]["tools"]) == ["tool1", "tool2"]
    first, last = lines[0]["tools"]["tool2"], lines[-1]["tools"]["tool1"]
    assert first["valid"] and first["why"] is None and first["relative_to"] == "camera" and np.shape(first["T"]) == (4, 4)
    assert not last["valid"] and last["T"] is None and last["residual_px"] is None and isinstance(last["why"], str) and last["why"]
    cap = cv2.VideoCapture(str(video))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == FRAMES and int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 2 * 1280
    assert not list(tmp_path.glob("*.partial"))


def test_relative_to_the_reference_tool(seq, tmp_path, capsys):
    _, _, truth = seq
    out, jsonl, camera = tmp_path / "rel.csv", tmp_path / "rel.jsonl", tmp_path / "camera.csv"
    with socket.socket() as s:  # a free port on the loopback interface; no client connects
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    igtl = ["--igtl", "--igtl-port", str(port)] if _has_pyigtl() else []
    assert _track(seq, "--out", str(out), "--jsonl", str(jsonl), "--reference", "tool1", *igtl) == 0
    captured = capsys.readouterr()
    assert "tool2 found in 100.0 %, 80.0 % relative to tool1" in captured.out
    if igtl:
        assert "'Tool1ToTracker', 'Tool2ToReference'" in captured.err
    assert _track(seq, "--out", str(camera)) == 0
    rows, plain = list(csv.DictReader(out.open())), list(csv.DictReader(camera.open()))
    assert list(rows[0]) == TOOLS_CSV_HEADER and len(rows) == FRAMES * 2
    for row, own in zip(rows, plain):
        poses = truth[int(row["frame"])]
        if row["tool"] == "tool1":  # the reference itself: in the camera's frame, as without --reference
            assert row["relative_to"] == "camera" and _without_clock(row) == _without_clock(own)
            continue
        assert row["relative_to"] == "tool1"
        if "tool1" not in poses:  # tool2 found, the reference not: no pose, never one in the camera frame
            assert own["valid"] == "1" and row["valid"] == "0" and row["x_mm"] == "" and row["residual_px"] == ""
            continue
        expected = np.linalg.inv(poses["tool1"]) @ poses["tool2"]
        M = _matrix(row)
        assert row["valid"] == "1" and np.linalg.norm(M[:3, 3] - expected[:3, 3]) < 1.0  # mm
        assert _angle_deg(M[:3, :3].T @ expected[:3, :3]) < 0.5
        assert row["residual_px"] == own["residual_px"]  # the tool's own
    last = _strict(jsonl.read_text().splitlines()[-1])["tools"]
    assert last["tool2"]["why"] == "reference not seen" and not last["tool2"]["valid"] and last["tool2"]["relative_to"] == "tool1"
    assert last["tool1"]["relative_to"] == "camera" and last["tool1"]["why"]


def _without_clock(row: dict) -> dict:
    """A CSV row without its wall-clock time (which differs from run to run)."""
    return {k: v for k, v in row.items() if k != "timestamp_unix"}


def _has_pyigtl() -> bool:
    try:
        import pyigtl  # noqa: F401
    except ImportError:
        return False
    return True


def test_openigtlink_client_receives_each_tool(seq, tmp_path):
    """A pyigtl client receives Tool1ToTracker and Tool2ToReference on every frame: the
    CSV's matrices with status OK where a pose is reported, the identity with MISSING for
    the frame without the reference (never the last pose)."""
    import threading
    import time

    pyigtl = pytest.importorskip("pyigtl")
    from markerpose.igtl import IGTLToolsSender
    from markerpose.video import open_stereo, track_tools_stream

    root, files, truth = seq
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    sender = IGTLToolsSender(port, ["tool1", "tool2"], reference="tool1", notice=lambda line: None)
    assert sender.devices == {"tool1": "Tool1ToTracker", "tool2": "Tool2ToReference"}
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    received, done = [], threading.Event()

    def listen():
        while not done.is_set():
            for msg in client.get_latest_messages():
                received.append((msg.device_name, msg.timestamp, np.array(msg.matrix), dict(msg.metadata)))
            time.sleep(0.005)

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    try:
        for _ in range(500):  # the client connects within a few seconds at most
            if sender.server.is_connected():
                break
            time.sleep(0.01)
        assert sender.server.is_connected()

        def send(k, stamp, reports):  # each frame's messages read before the next frame
            sender(k, stamp, reports)
            for _ in range(400):
                if len(received) == sender.sent:
                    break
                time.sleep(0.005)

        out = tmp_path / "poses.csv"
        tracker = mp.MarkerPose(mp.StereoRig.default(), markers=files, detector="classical")
        summary = track_tools_stream(
            tracker, open_stereo(str(root / "L"), str(root / "R")), out, progress=False, reference="tool1", send=send
        )
    finally:
        done.set()
        listener.join(timeout=2)
        client.stop()
        sender.close()
    rows = list(csv.DictReader(out.open()))
    assert summary["frames"] == FRAMES and summary["tools"]["tool2"]["reported"] == pytest.approx(0.8)
    assert len(rows) == len(received) == 2 * FRAMES
    for row, (device, stamp, M, meta) in zip(rows, received):
        assert device == {"tool1": "Tool1ToTracker", "tool2": "Tool2ToReference"}[row["tool"]]
        assert stamp == pytest.approx(float(row["timestamp_unix"]), abs=1e-6)
        if row["valid"] == "1":
            np.testing.assert_allclose(M, _matrix(row), atol=1e-4)  # float32 on the wire
            assert meta["TransformStatus"] == "OK"
        else:
            np.testing.assert_array_equal(M, np.eye(4))
            assert meta["TransformStatus"] == "MISSING" and meta["TransformValid"] == "0"
    assert sum(m[3]["TransformStatus"] == "MISSING" for m in received) == sum(r["valid"] == "0" for r in rows) > 0


def test_annotate_tools_draws_each_tool_and_keeps_the_images():
    from markerpose.viz import annotate_tools

    rig = mp.StereoRig.default()
    tool = tool_set(1)[0]
    T = look_at_pose(np.array([0.0, 0, 600]))
    images = [np.full((1024, 1280), 128, np.uint8)] * 2
    plain = annotate_tools(images, {}, rig)
    assert plain.shape == (1024, 2560, 3) and np.all(plain == 128)
    drawn = annotate_tools(images, {tool.name: mp.Estimate(T, tool.points3d, np.zeros((2, 3, 2)))}, rig)
    for view in (drawn[:, :1280], drawn[:, 1280:]):  # axes and the name on both views
        assert np.count_nonzero(np.any(view != 128, axis=2)) > 500
    assert np.all(images[0] == 128)


def _one_line_error(capsys, pattern: str) -> None:
    err = capsys.readouterr().err
    assert re.search(pattern, err) and err.count("\n") == 1, err


def test_bad_tools_options_are_one_line_errors_and_leave_no_file(seq, tmp_path, capsys):
    root, files, _ = seq
    out = tmp_path / "poses.csv"
    assert _track(seq, "--out", str(out), "--reference", "tool9") == 2
    _one_line_error(capsys, r"--reference tool9: no such tool; the tools are tool1, tool2")
    assert _track(seq, "--out", str(out), "--c1", "30") == 2
    _one_line_error(capsys, r"--c1 with --tools: the tool files define the geometry")
    assert _track(seq, "--out", str(out), "--c1", "25") == 0  # the default is no option given
    out.unlink()
    bad = tmp_path / "bad.yaml"
    fields = yaml.safe_load(Path(files[1]).read_text())
    del fields["rings"]
    bad.write_text(yaml.safe_dump(fields))
    assert cli.main(["track", str(root / "L"), str(root / "R"), "--tools", files[0], str(bad), "--out", str(out), "--quiet"]) == 2
    _one_line_error(capsys, re.escape(str(bad)) + r": missing \['rings'\] key")
    assert cli.main(["track", str(root / "L"), str(root / "R"), "--reference", "tool1", "--out", str(out), "--quiet"]) == 2
    _one_line_error(capsys, r"--reference needs --tools")
    assert not out.exists() and not list(tmp_path.glob("*.partial"))
