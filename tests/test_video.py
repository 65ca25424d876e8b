"""markerpose track: two image folders in, one CSV row a frame out (markerpose.video)."""

import csv
import json

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose import cli
from markerpose.synth import Imaging, clutter_background, look_at_pose, render_stereo
from markerpose.video import CSV_HEADER


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Eight rendered pairs of a moving marker, then two without it, as PNG folders."""
    rig = mp.StereoRig.default()
    root = tmp_path_factory.mktemp("seq")
    (root / "L").mkdir()
    (root / "R").mkdir()
    truth = []
    rng = np.random.default_rng(2)
    for k in range(10):
        if k < 8:
            T = look_at_pose([-4 + k, 1, 560 - k], 30 + k, 45, 5 + k)
            images = render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=k).images
        else:
            T, img = None, (clutter_background((1280, 1024), rng) * 200).astype(np.uint8)
            images = (img, img)
        truth.append(T)
        for side, img in zip("LR", images):
            cv2.imwrite(str(root / side / f"{k:04d}.png"), img)
    return root, truth


def test_track_writes_one_row_a_frame_against_the_truth(folders, tmp_path, capsys):
    root, truth = folders
    out = tmp_path / "poses.csv"
    assert (
        cli.main(
            [
                "track",
                str(root / "L"),
                str(root / "R"),
                "--out",
                str(out),
                "--jsonl",
                str(tmp_path / "p.jsonl"),
                "--video",
                str(tmp_path / "axes.webm"),
                "--detector",
                "classical",
                "--quiet",
            ]
        )
        == 0
    )
    cap = cv2.VideoCapture(str(tmp_path / "axes.webm"))  # both views side by side, one frame a pair, VP9 (browsers play it)
    assert int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") == b"VP90" and int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 2 * 1280
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    assert len(frames) == len(truth)
    red = [float(((f[20:60, 20:300, 2] > 180) & (f[20:60, 20:300, 1] < 80)).mean()) for f in frames]
    assert all(r > 0.02 for r in red[8:]) and all(r < 0.005 for r in red[:8]), red  # the frames without the marker, marked
    assert "10 frames" in capsys.readouterr().out
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == CSV_HEADER and len(rows) == len(truth)
    for row, T in zip(rows, truth):
        if T is None:
            assert row["valid"] == "0" and row["x_mm"] == ""
            continue
        assert row["valid"] == "1"
        t = np.array([float(row[k]) for k in ("x_mm", "y_mm", "z_mm")])
        assert np.linalg.norm(t - T[:3, 3]) < 0.05  # mm
        M = np.array([float(row[f"T{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)
        np.testing.assert_allclose(M[:3, 3], t)
        q = np.array([float(row[k]) for k in ("qx", "qy", "qz", "qw")])
        assert abs(np.linalg.norm(q) - 1) < 1e-6
    sources = [json.loads(line)["source"] for line in (tmp_path / "p.jsonl").read_text().splitlines()]
    assert sources[2:8] == ["tracked"] * 6 and sources[8:] == [None, None]
    assert not list(tmp_path.glob("*.partial"))
    assert len((tmp_path / "p.jsonl").read_text().splitlines()) == len(truth)
    assert float(rows[3]["timestamp_s"]) == pytest.approx(3 / 60)  # folders: --fps, 60 by default


def test_track_bad_input_is_one_line_and_leaves_no_file(folders, tmp_path, capsys):
    root, _ = folders
    out = tmp_path / "poses.csv"
    cases = [
        ([str(tmp_path / "nope"), str(root / "R")], "no such file, folder or camera index"),
        ([str(root / "L"), str(tmp_path)], "no image files"),
    ]
    short = tmp_path / "short"
    short.mkdir()
    for p in sorted((root / "R").iterdir())[:3]:
        (short / p.name).write_bytes(p.read_bytes())
    cases.append(([str(root / "L"), str(short)], "differ in length: .* has 10 frames, .* 3"))
    small = tmp_path / "small"
    small.mkdir()
    for p in sorted((root / "L").iterdir()):
        cv2.imwrite(str(small / p.name), cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (640, 512)))
    cases.append(([str(small), str(small)], "calibrated for 1280x1024"))
    import re

    for args, message in cases:
        assert cli.main(["track", *args, "--out", str(out), "--quiet", "--detector", "classical"]) == 2
        err = capsys.readouterr().err
        assert re.search(message, err) and err.count("\n") == 1, err
        assert not out.exists() and not list(tmp_path.glob("*.partial"))


def test_a_bad_frame_mid_stream_keeps_the_rows_before_it(folders, tmp_path, capsys):
    """An unreadable image part-way: one line naming it and where it stopped (rc 2), and the
    rows so far under the requested name, not left in a .partial."""
    root, _ = folders
    left, right = tmp_path / "L", tmp_path / "R"
    left.mkdir()
    right.mkdir()
    for p in sorted((root / "L").iterdir())[:4]:
        (left / p.name).write_bytes(p.read_bytes())
    for p in sorted((root / "R").iterdir())[:4]:
        (right / p.name).write_bytes(p.read_bytes())
    (left / sorted(p.name for p in left.iterdir())[2]).write_bytes(b"")  # the third left image: empty
    out = tmp_path / "poses.csv"
    assert cli.main(["track", str(left), str(right), "--out", str(out), "--quiet", "--detector", "classical"]) == 2
    err = capsys.readouterr().err
    assert "the file is empty" in err and "the 2 pairs before it are in" in err and err.count("\n") == 1, err
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 2 and not list(tmp_path.glob("*.partial"))


def test_camera_index_and_port_out_of_range_are_one_line_errors(folders, tmp_path, capsys):
    root, _ = folders
    assert cli.main(["track", "99999999999999999999", "1", "--out", str(tmp_path / "p.csv")]) == 2
    assert "a camera index is a small whole number" in capsys.readouterr().err
    for port in ("70000", "-1"):
        with pytest.raises(SystemExit) as e:
            cli.main(["track", str(root / "L"), str(root / "R"), "--igtl", "--igtl-port", port, "--out", str(tmp_path / "p.csv")])
        assert e.value.code == 2 and "a port is 1 to 65535" in capsys.readouterr().err


def test_outputs_and_frame_rates_are_checked_before_the_run(folders, tmp_path, capsys):
    root, _ = folders
    cases = [
        (["--out", str(tmp_path)], "a folder; give a file name"),
        (["--out", str(tmp_path / "no" / "p.csv")], "does not exist"),
        (["--out", str(tmp_path / "p.csv"), "--jsonl", str(tmp_path)], "--jsonl .*: a folder"),
        (["--out", str(tmp_path / "p.csv"), "--fps", "inf"], "frame rate between"),
        (["--out", str(tmp_path / "p.csv"), "--fps", "1e-320"], "frame rate between"),
    ]
    import re

    for extra, message in cases:
        assert cli.main(["track", str(root / "L"), str(root / "R"), "--quiet", *extra]) == 2
        err = capsys.readouterr().err
        assert re.search(message, err) and err.count("\n") == 1, err
        assert not (tmp_path / "p.csv").exists()


def test_estimate_refuses_an_empty_image_in_one_line(tmp_path, capsys):
    (tmp_path / "e.png").write_bytes(b"")
    assert cli.main(["estimate", str(tmp_path / "e.png"), str(tmp_path / "e.png")]) == 2
    err = capsys.readouterr().err
    assert "the file is empty" in err and err.count("\n") == 1


def test_track_reads_two_lossless_videos(folders, tmp_path):
    """The same frames as FFV1 videos: the same poses as from the PNG folders."""
    root, truth = folders
    for side in "LR":
        w = cv2.VideoWriter(str(tmp_path / f"{side}.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 60, (1280, 1024), isColor=False)
        assert w.isOpened()
        for p in sorted((root / side).iterdir()):
            w.write(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
        w.release()
    a, b = tmp_path / "video.csv", tmp_path / "png.csv"
    assert cli.main(["track", str(tmp_path / "L.avi"), str(tmp_path / "R.avi"), "--out", str(a), "--detector", "classical", "--quiet"]) == 0
    assert cli.main(["track", str(root / "L"), str(root / "R"), "--out", str(b), "--detector", "classical", "--quiet"]) == 0
    va, vb = list(csv.DictReader(a.open())), list(csv.DictReader(b.open()))
    assert len(va) == len(vb) == len(truth)
    assert [r["x_mm"] for r in va] == [r["x_mm"] for r in vb]  # lossless: the very same poses
    assert float(va[1]["timestamp_s"]) == pytest.approx(1 / 60, abs=1e-3)
    # Cut short: the run stops with one line saying where, the rows before it kept.
    for side in "LR":
        data = (tmp_path / f"{side}.avi").read_bytes()
        (tmp_path / f"{side}-cut.avi").write_bytes(data[: len(data) // 2])
    cut = tmp_path / "cut.csv"
    assert cli.main(["track", str(tmp_path / "L-cut.avi"), str(tmp_path / "R-cut.avi"), "--out", str(cut), "--quiet"]) == 2
    rows = list(csv.DictReader(cut.open()))
    assert 0 < len(rows) < len(truth)


def test_a_camera_that_does_not_open(tmp_path, capsys):
    assert cli.main(["track", "97", "98", "--out", str(tmp_path / "p.csv"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "error: cannot open camera 97"


def _free_port() -> int:
    import socket

    with socket.socket() as s:  # a free port on the loopback interface
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _collector(pyigtl, port, name):
    """A pyigtl client on 127.0.0.1 and the (timestamp, matrix, metadata) of every ``name``
    message it receives, collected by a thread until ``done`` is set."""
    import threading

    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    received, done = [], threading.Event()

    def listen():
        while not done.is_set():
            msg = client.wait_for_message(name, timeout=0.05)
            if msg is not None:
                received.append((msg.timestamp, np.array(msg.matrix), dict(msg.metadata)))

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    return client, received, done, thread


def _wait(cond, seconds=5.0):
    import time

    for _ in range(int(seconds / 0.01)):
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def test_openigtlink_every_frame_to_every_client_with_its_status(folders, tmp_path):
    """Two pyigtl clients at once: both receive one TRANSFORM a frame, stamped in seconds
    since the epoch (within 1 s of now, spaced as the frames), the CSV's matrices with
    PLUS's status "OK"; a frame without the marker arrives as "MISSING" with the identity,
    never the last pose. One client leaving mid-stream costs the other nothing and prints one
    line, no traceback."""
    import time

    pyigtl = pytest.importorskip("pyigtl")
    from markerpose.igtl import IGTLSender
    from markerpose.video import open_stereo, track_stream

    root, truth = folders
    port = _free_port()
    notices = []
    sender = IGTLSender(port, "MarkerToTracker", notice=notices.append)
    a = _collector(pyigtl, port, "MarkerToTracker")
    b = _collector(pyigtl, port, "MarkerToTracker")
    try:
        assert _wait(lambda: sender.server.clients == 2)

        def send(k, stamp, est):  # each message read by the clients before the next frame
            sender(k, stamp, est)
            assert _wait(lambda: len(a[1]) == k + 1)
            if k < 5:
                assert _wait(lambda: len(b[1]) == k + 1)
            if k == 4:  # the second client leaves after five frames
                b[2].set()
                b[3].join(timeout=2)
                b[0].stop()
                assert _wait(lambda: sender.server.clients == 1)

        out = tmp_path / "poses.csv"
        start = time.time()
        summary = track_stream(
            mp.MarkerPose(mp.StereoRig.default(), detector="classical"),
            open_stereo(str(root / "L"), str(root / "R"), fps=30),
            out,
            progress=False,
            send=send,
        )
        during = list(notices)
    finally:
        for c in (a, b):
            c[2].set()
            c[3].join(timeout=2)
            c[0].stop()
        sender.close()
    rows = list(csv.DictReader(out.open()))
    received = a[1]
    assert summary["frames"] == len(truth) == len(rows) == len(received) and len(b[1]) == 5
    assert sum(" connected (" in n for n in during) == 2 and sum(" left " in n for n in during) == 1, during
    for row, (stamp, M, meta) in zip(rows, received):
        assert abs(stamp - start) < 1.0 + float(row["timestamp_s"])  # seconds since the epoch, not since the start
        assert stamp == pytest.approx(float(row["timestamp_unix"]), abs=1e-6)
        if row["valid"] == "1":
            expected = np.array([float(row[f"T{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)
            np.testing.assert_allclose(M, expected, atol=1e-4)  # float32 on the wire
            assert meta["TransformStatus"] == "OK" and meta["TransformValid"] == "1" and meta["MarkerposeStatus"] == row["status"]
            assert float(meta["SdMm"]) == pytest.approx(float(row["sd_mm"]), rel=1e-3)
        else:
            np.testing.assert_array_equal(M, np.eye(4))  # not the last pose
            assert meta["TransformStatus"] == "MISSING" and meta["TransformValid"] == "0"
    stamps = np.array([r[0] for r in received])
    np.testing.assert_allclose(np.diff(stamps), 1 / 30, atol=1e-5)  # the frames' own spacing


def test_realtime_replays_a_folder_at_its_frame_rate(folders, tmp_path):
    """--realtime: frame k handed over at k / fps from the start (30 +- 1 frames/s)."""
    from markerpose.video import open_stereo

    root, _ = folders
    stream = open_stereo(str(root / "L"), str(root / "R"), fps=30, realtime=True)
    import time

    times = []
    for _k, _t, _l, _r in stream:
        times.append(time.perf_counter())
    stream.close()
    rate = (len(times) - 1) / (times[-1] - times[0])
    assert 29.0 <= rate <= 31.0, rate
    fast = open_stereo(str(root / "L"), str(root / "R"), fps=1)  # without it: as fast as read
    t0 = time.perf_counter()
    assert sum(1 for _ in fast) == len(times) and time.perf_counter() - t0 < 5


def test_igtl_port_is_its_own_option(folders, tmp_path, capsys):
    """--igtl is a switch: an input after it is an input, not a port; --igtl-port alone is refused."""
    pytest.importorskip("pyigtl")
    root, _ = folders
    out = tmp_path / "p.csv"
    assert (
        cli.main(["track", "--igtl", str(root / "L"), str(root / "R"), "--igtl-port", str(_free_port()), "--out", str(out), "--quiet"]) == 0
    )
    assert "serving TRANSFORM 'MarkerToTracker'" in capsys.readouterr().err
    assert cli.main(["track", str(root / "L"), str(root / "R"), "--igtl-port", "18944", "--out", str(out), "--quiet"]) == 2
    assert "--igtl-port needs --igtl" in capsys.readouterr().err


def test_rerun_recording_of_the_tracking(folders, tmp_path):
    """--rerun-save: a recording that rerun reads back, with both cameras, the marker's pose
    on every frame it was found (the CSV's translation), and its pose cleared on the frames
    without it (no stale axes)."""
    chunk = pytest.importorskip("rerun.chunk")
    root, truth = folders
    rrd, out = tmp_path / "view.rrd", tmp_path / "p.csv"
    args = ["track", str(root / "L"), str(root / "R"), "--out", str(out), "--rerun-save", str(rrd), "--rerun-images", "4", "--quiet"]
    assert cli.main([*args, "--detector", "classical"]) == 0
    store = chunk.RrdReader(rrd).stream().collect()
    paths = set(store.schema().entity_paths())
    assert {
        "/world/left",
        "/world/right",
        "/world/left/image",
        "/world/tools/marker",
        "/world/trails/marker",
        "/plots/marker/sd_mm",
    } <= paths
    poses, cleared = {}, []
    for c in store.stream():
        if str(c.entity_path) != "/world/tools/marker":
            continue
        batch = c.to_record_batch()
        frames = batch.column("frame").to_pylist()
        if "Transform3D:translation" in batch.schema.names:
            for k, t in zip(frames, batch.column("Transform3D:translation").to_pylist()):
                poses[k] = np.array(t[0])
        if "Clear:is_recursive" in batch.schema.names:
            cleared += frames
    rows = list(csv.DictReader(out.open()))
    assert sorted(poses) == [int(r["frame"]) for r in rows if r["valid"] == "1"] and sorted(cleared) == [8, 9]
    for r in rows[:8]:
        np.testing.assert_allclose(poses[int(r["frame"])], [float(r[k]) for k in ("x_mm", "y_mm", "z_mm")], atol=1e-3)


def test_sigterm_stops_track_like_ctrl_c(folders, tmp_path):
    """kill -TERM: every row so far under the requested name, the summary printed, rc 130."""
    import signal
    import subprocess
    import sys
    import time

    root, _ = folders
    big = tmp_path / "L"
    big.mkdir()
    bigr = tmp_path / "R"
    bigr.mkdir()
    files = {side: sorted((root / side).iterdir()) for side in "LR"}
    for k in range(2000):  # long enough to be stopped part-way (links: no copies)
        for side, folder in (("L", big), ("R", bigr)):
            (folder / f"{k:05d}.png").symlink_to(files[side][k % len(files[side])])
    out, partial = tmp_path / "p.csv", tmp_path / "p.csv.partial"
    cmd = [sys.executable, "-m", "markerpose.cli", "track", str(big), str(bigr), "--out", str(out), "--quiet", "--detector", "classical"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and p.poll() is None and not (partial.exists() and partial.read_text().count("\n") > 3):
        time.sleep(0.1)
    p.send_signal(signal.SIGTERM)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 130, (p.returncode, stdout, stderr)
    assert stdout.startswith("stopped: ") and "Traceback" not in stderr, (stdout, stderr)
    rows = list(csv.DictReader(out.open()))
    assert 0 < len(rows) < 2000 and not list(tmp_path.glob("*.partial"))


def test_two_cameras_are_grabbed_as_a_pair(monkeypatch):
    """Two live cameras: both grabbed, then both decoded; each frame stamped at its grab, the
    right view's time kept for track(times=...), the grab offsets for the summary."""
    from markerpose import video

    calls = []

    class Cap:
        def __init__(self, name):
            self.name, self.n = name, 0

        def grab(self):
            calls.append(("grab", self.name))
            self.n += 1
            return self.n <= 3

        def retrieve(self):
            calls.append(("retrieve", self.name))
            return True, np.full((8, 8), self.n, np.uint8)

    class Camera:
        def __init__(self, name):
            self.cap, self.name, self.live, self.count, self.fps = Cap(name), name, True, None, None

        def close(self):
            pass

    monkeypatch.setattr(video, "_source", lambda spec: Camera(spec))
    stream = video.open_stereo("0", "1")
    assert stream.cameras
    seen = []
    for _k, t, a, b in stream:
        seen.append((t, stream.right_t, int(a[0, 0]), int(b[0, 0])))
        times = video._capture_times(stream, t, None)
        assert times == (t, stream.right_t) and stream.right_t >= t
        assert video._capture_times(stream, t, 0.01) == (t, stream.right_t + 0.01)
    assert [s[2:] for s in seen] == [(1, 1), (2, 2), (3, 3)]
    assert calls[:4] == [("grab", "0"), ("grab", "1"), ("retrieve", "0"), ("retrieve", "1")]
    assert len(stream.grab_offsets) == 3 and all(0 <= d < 0.1 for d in stream.grab_offsets)


def test_ctrl_c_while_starting_is_an_interruption(folders, tmp_path):
    """SIGINT while the command line starts (its imports, the compiled loops, the networks):
    'interrupted' and exit 130, never a traceback. On a fast machine the last delay can land
    in the tracking already: a run stopped there says so on stdout, with 130 too."""
    import signal
    import subprocess
    import sys
    import time

    root, _ = folders
    cmd = [sys.executable, "-m", "markerpose.cli", "track", str(root / "L"), str(root / "R"), "--out", str(tmp_path / "p.csv"), "--quiet"]
    for delay in (0.2, 0.5, 1.0):
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
        assert "Traceback" not in err, (delay, err)
        assert p.returncode in (0, 130), (delay, p.returncode, err)  # 0: it had finished
        assert p.returncode == 0 or "interrupted" in err or out.startswith("stopped: ")


def test_a_ctrl_c_while_a_library_loads_is_held_then_raised():
    """numpy's C import turns a KeyboardInterrupt into an ImportError ('import numpy failed'):
    inside held_interrupt the Ctrl-C waits for the block's end, then interrupts."""
    import os
    import signal

    from markerpose.signals import held_interrupt

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own (a pyigtl client in this process sets its)
    try:
        done = []
        with pytest.raises(KeyboardInterrupt):
            with held_interrupt():
                os.kill(os.getpid(), signal.SIGINT)
                done.append("the block ran to its end")
        assert done and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with held_interrupt():  # no Ctrl-C: nothing raised
            done.append("again")
        assert len(done) == 2
    finally:
        signal.signal(signal.SIGINT, before)


def test_openigtlink_misbehaving_clients_cost_one_line_each():
    """A client that sends garbage, one that announces a huge body and leaves, one that
    connects and closes at once: each a notice, no traceback, and a good client still
    receives the next frame."""
    import socket
    import struct
    import time

    pyigtl = pytest.importorskip("pyigtl")
    from markerpose.igtl import IGTLSender

    port = _free_port()
    notices = []
    sender = IGTLSender(port, "MarkerToTracker", notice=notices.append)
    try:
        for payload in (b"\x00garbage" * 100, struct.pack(">H12s20sIIQQ", 1, b"IMAGE", b"x", 0, 0, 2**62, 0), b""):
            with socket.create_connection(("127.0.0.1", port)) as s:
                if payload:
                    s.sendall(payload)
                time.sleep(0.05)
        assert _wait(lambda: sender.server.served == 3 and sender.server.clients == 0)
        good = _collector(pyigtl, port, "MarkerToTracker")
        try:
            assert _wait(lambda: sender.server.clients == 1)
            assert sender(0, time.time(), None)
            assert _wait(lambda: len(good[1]) == 1)
        finally:
            good[2].set()
            good[3].join(timeout=2)
            good[0].stop()
    finally:
        sender.close()
    assert sum(" left " in n for n in notices) >= 3 and all(n.startswith("OpenIGTLink: client") for n in notices)
