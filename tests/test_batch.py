"""markerpose batch: many recordings tracked as track tracks one, on a local Ray (markerpose.batch, .engine)."""

import csv
import os
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import markerpose as mp
from markerpose import cli
from markerpose.batch import Job, find_recordings, run_batch
from markerpose.cli.batch import TrackerFactory
from markerpose.engine import Failed, run_tasks
from markerpose.synth import Imaging, look_at_pose, render_stereo


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Ten rendered pairs of a moving marker."""
    root = tmp_path_factory.mktemp("frames")
    rig = mp.StereoRig.default()
    for side in ("left", "right"):
        (root / side).mkdir()
    for k in range(10):
        T = look_at_pose([-4 + k, 1, 560 - k], 30 + k, 45, 5 + k)
        for side, img in zip(("left", "right"), render_stereo(rig, T, imaging=Imaging(alpha=0.8), seed=k).images):
            cv2.imwrite(str(root / side / f"{k:04d}.png"), img)
    return root


def _recording(frames, folder: Path, order) -> Path:
    """A recording folder whose frames are the rendered pairs in ``order`` (links, not copies)."""
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
        for j, k in enumerate(order):
            os.symlink(frames / side / f"{k:04d}.png", folder / side / f"{j:04d}.png")
    return folder


def _rows(path, drop=("timestamp_unix",)):
    """A track CSV's rows without the wall-clock column, which differs between any two runs."""
    with open(path) as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()


def test_recordings_are_found_in_folders_and_list_files(frames, tmp_path):
    a = _recording(frames, tmp_path / "set" / "a", range(3))
    b = tmp_path / "set" / "b"
    b.mkdir()
    for side in ("L", "R"):
        (b / f"{side}.mp4").write_bytes(b"")  # videos named L / R
    (b / "rig.yaml").write_text("")
    (b / "us").mkdir()
    (tmp_path / "set" / "notes").mkdir()  # not a recording: passed over inside a folder of recordings
    found = find_recordings([tmp_path / "set"])
    assert [r.name for r in found] == ["a", "b"]
    assert found[0].left == str(a / "left") and found[0].rig is None and found[0].us is None
    assert found[1].left.endswith("L.mp4") and found[1].rig.endswith("rig.yaml") and found[1].us.endswith("us")
    listing = tmp_path / "list.txt"
    listing.write_text("# two recordings\nset/a\nset/a/left set/a/right  # by their frames\n")
    with pytest.raises(ValueError, match="two recordings are named a"):
        find_recordings([listing])
    listing.write_text("set/a\n")
    assert find_recordings([listing])[0].left == str(tmp_path / "set" / "a" / "left")
    listing.write_text("set/a x y z w\n")
    with pytest.raises(ValueError, match="line 1"):
        find_recordings([listing])
    with pytest.raises(ValueError, match="no recording here"):
        find_recordings([tmp_path / "set" / "notes"])
    with pytest.raises(ValueError, match="no such file"):
        find_recordings([tmp_path / "missing"])


def test_the_engine_runs_tasks_in_order_and_reports_failures_without_ray():
    seen = []
    out = run_tasks(_square, [1, 2, -1, 3], use_ray=False, on_result=lambda i, r: seen.append(i), on_progress=seen.append)
    assert out[:2] == [1, 4] and out[3] == 9 and isinstance(out[2], Failed) and "negative" in out[2].reason
    assert [s for s in seen if isinstance(s, int)]


def _square(x, report):
    if x < 0:
        raise ValueError("negative")
    report(1)
    return x * x


def test_batch_on_local_ray_matches_track_fails_alone_resumes_and_survives_a_killed_worker(frames, tmp_path, local_ray, capsys):
    """Four recordings and one with a corrupt video on a local Ray of 2 CPUs: each CSV is
    track's; the corrupt one fails with its reason; a second run skips the finished ones; a
    worker killed midway through a long recording is replaced and that recording completes."""
    root = tmp_path / "recordings"
    for i in range(4):
        _recording(frames, root / f"rec{i}", range(i, 10))
    bad = root / "broken"
    bad.mkdir()
    for side in ("left", "right"):
        (bad / f"{side}.mp4").write_bytes(b"\x00not a video" * 100)
    out = tmp_path / "out"
    rc = cli.main(["batch", str(root), "--out", str(out), "--quiet"])
    assert rc == 2  # one recording failed
    err = capsys.readouterr().err
    assert "failed: broken:" in err and "cannot" in err.lower()
    for i in range(4):
        track_csv = tmp_path / f"track{i}.csv"
        assert cli.main(["track", str(root / f"rec{i}" / "left"), str(root / f"rec{i}" / "right"), "--out", str(track_csv), "--quiet"]) == 0
        assert _rows(out / f"rec{i}" / "poses.csv") == _rows(track_csv)
        assert (out / f"rec{i}" / "batch.json").is_file()
    assert not (out / "broken" / "batch.json").exists()
    with open(out / "summary.csv") as f:
        summary = {r["recording"]: r for r in csv.DictReader(f)}
    assert [summary[f"rec{i}"]["status"] for i in range(4)] == ["done"] * 4 and summary["broken"]["status"] == "failed"
    assert "| rec0 | done | 10 |" in (out / "summary.md").read_text()
    capsys.readouterr()

    before = {i: (out / f"rec{i}" / "poses.csv").stat().st_mtime_ns for i in range(4)}
    assert cli.main(["batch", str(root), "--out", str(out), "--quiet"]) == 2
    assert "0 tracked (0 frames), 4 done before, 1 failed" in capsys.readouterr().out
    assert all((out / f"rec{i}" / "poses.csv").stat().st_mtime_ns == before[i] for i in range(4))

    long = _recording(frames, tmp_path / "long" / "long", list(range(10)) * 16)  # 160 pairs
    killed = []
    watcher = threading.Thread(target=_kill_the_writer, args=(tmp_path / "out2" / "long" / "poses.csv.partial", killed), daemon=True)
    watcher.start()
    factory = TrackerFactory(cli.build_parser().parse_args(["batch", str(long)]), threads=1)
    rows = run_batch([Job(find_recordings([long])[0], str(tmp_path / "out2" / "long"), factory)], max_retries=2, progress=False)
    watcher.join(timeout=5)
    assert killed, "the worker was not killed midway: the test did not test a retry"
    assert rows[0]["status"] == "done" and rows[0]["frames"] == 160
    assert len(_rows(tmp_path / "out2" / "long" / "poses.csv")) == 160


def _kill_the_writer(partial: Path, killed: list, timeout: float = 120.0) -> None:
    """SIGKILL the process that has ``partial`` open, once, as soon as it has one."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if partial.exists():
            for pid in os.listdir("/proc"):
                if not pid.isdigit() or int(pid) == os.getpid():  # a worker's, never this test's own
                    continue
                try:
                    fds = os.listdir(f"/proc/{pid}/fd")
                    if any(os.readlink(f"/proc/{pid}/fd/{fd}") == str(partial) for fd in fds):
                        os.kill(int(pid), signal.SIGKILL)
                        killed.append(int(pid))
                        return
                except OSError:
                    continue
        time.sleep(0.01)


def test_batch_without_ray_gives_the_same_rows(frames, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the summary: in the current folder without --out
    root = tmp_path / "recordings"
    _recording(frames, root / "one", range(6))
    assert cli.main(["batch", str(root), "--serial", "--quiet", "--jsonl"]) == 0  # outputs beside the recording
    track_csv = tmp_path / "track.csv"
    assert cli.main(["track", str(root / "one" / "left"), str(root / "one" / "right"), "--out", str(track_csv), "--quiet"]) == 0
    assert _rows(root / "one" / "poses.csv") == _rows(track_csv)
    assert (root / "one" / "poses.jsonl").is_file() and np.isclose(
        float(next(r for r in _rows(track_csv))["timestamp_s"]), float(next(r for r in _rows(root / "one" / "poses.csv"))["timestamp_s"])
    )
    assert "1 recordings: 1 tracked (6 frames" in capsys.readouterr().out and (tmp_path / "summary.md").is_file()


def test_batch_reconstructs_the_sweep_of_a_recording_that_has_one(tmp_path, capsys):
    """--probe: a recording with an ultrasound sweep (us/) is tracked, then reconstructed into
    reconstruction/, as markerpose ultrasound reconstruct would."""
    from markerpose.experiments.ultrasound.simulate import write_simulated_recording

    rec = tmp_path / "study" / "sweep1"
    write_simulated_recording(rec, n_frames=6, calibration_frames=3, progress=False)
    out = tmp_path / "out"
    assert (
        cli.main(["batch", str(tmp_path / "study"), "--out", str(out), "--probe", str(rec / "probe_true.yaml"), "--serial", "--quiet"]) == 0
    )
    done = out / "sweep1"
    assert (done / "reconstruction" / "sweep.igs.nrrd").is_file() and (done / "reconstruction" / "volume.nrrd").is_file()
    assert "reconstruction/" in (done / "batch.json").read_text()
    assert "1 recordings: 1 tracked" in capsys.readouterr().out
