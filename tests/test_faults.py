"""Bad inputs, every class: refused with one line, never a traceback (markerpose.experiments.faults;
property-based where the input space is open)."""

import math
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from markerpose import presets
from markerpose.experiments import faults
from markerpose.images import read_image
from markerpose.ultrasound.recording import read_frames
from markerpose.video import MAX_FPS, MIN_FPS, open_stereo, read_track_csv

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.mark.parametrize(
    "name, n",
    [
        ("rig files", 12),
        ("settings", 8),
        ("image arrays", 12),
        ("poses CSVs", 7),
        ("command-line numbers", 10),
        ("other commands' files", 8),
    ],
)
def test_campaign_classes_have_no_fault(name, n, tmp_path, monkeypatch):
    """A seeded slice of the campaign (the full one: markerpose eval faults): every bad input
    refused with one line, every good one given a result."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng([7, list(faults.CLASSES).index(name)])
    seen = []
    for what, bad, run in faults.CLASSES[name](n, rng, tmp_path):
        outcome, detail = run()
        seen.append(outcome)
        assert outcome == ("refused" if bad else "ok"), (what, outcome, detail)
    assert "refused" in seen


def test_the_judges_tell_faults_apart():
    assert faults.api(lambda: int("x"), bad=True)[0] == "refused"  # ValueError: a refusal
    assert faults.api(lambda: [][1], bad=True)[0] == "traceback"  # IndexError: a fault
    assert faults.api(lambda: None, bad=True)[0] == "accepted"
    assert faults.api(lambda: None, bad=False)[0] == "ok"
    assert faults.cli(["estimate", "no-such.png", "nor-this.png"], bad=True)[0] == "refused"
    assert faults.cli(["peers", "--pairs", "0"], bad=True)[0] == "refused"


def test_a_class_whose_process_dies_names_the_case_it_died_in(tmp_path):
    """Each class runs in its own process, logging each case before and after it: a crash
    (or a hang) is the case started and not finished; the cases before it keep their outcome."""
    import json

    log = tmp_path / "class.jsonl"
    lines = [
        {"k": 0, "case": "a", "bad": True, "start": True},
        {"k": 0, "case": "a", "bad": True, "outcome": "refused", "detail": "x"},
        {"k": 1, "case": "nested 40000 deep", "bad": True, "start": True},
    ]
    log.write_text("\n".join(json.dumps(r) for r in lines) + "\n")
    got = faults.read_log(log, "the process ended with -11", "crash")
    assert [(r["case"], r["outcome"]) for r in got] == [("a", "refused"), ("nested 40000 deep", "crash")]
    assert [r["outcome"] for r in faults.read_log(log, None)] == ["refused"]  # ended normally: nothing in flight
    assert "crash" in faults.report({"conf": {"seed": 0}, "classes": {"rig files": got}, "totals": faults._totals({"rig files": got})})


stages = [
    (s, k, v) for s, c in presets.default_conf.items() if isinstance(c, dict) for k, v in c.items() if not isinstance(v, (dict, list))
]


@FAST
@given(
    setting=st.sampled_from(stages),
    value=st.one_of(st.floats(allow_nan=True), st.integers(-(10**6), 10**6), st.text(max_size=5), st.none()),
)
def test_any_stage_setting_is_checked_or_kept(setting, value):
    """Every stage setting: a value is refused with one line naming it, or kept as given and
    within its rule (a NaN is never kept for a number)."""
    stage, key, default = setting
    try:
        conf = presets.resolve("default", **{stage: {key: value}})
    except ValueError as exc:
        assert f"{stage}.{key}" in str(exc) and "\n" not in str(exc)
        return
    kept = conf[stage][key]
    assert kept == value or (isinstance(value, int) and kept == float(value))
    if isinstance(kept, float):
        assert not math.isnan(kept)


@FAST
@given(data=st.binary(max_size=3000))
def test_any_bytes_as_an_image_file_are_read_or_refused(data, tmp_path):
    path = tmp_path / "img.png"
    path.write_bytes(data)
    try:
        img = read_image(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    assert isinstance(img, np.ndarray) and img.size > 0


_cells = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(str), st.text(string.printable, max_size=4), st.just(""))


@FAST
@given(rows=st.lists(st.lists(_cells, min_size=0, max_size=20), max_size=5), cut=st.integers(0, 400))
def test_any_poses_csv_is_read_or_refused(rows, cut, tmp_path):
    """A poses CSV with cells of any kind, cut anywhere: its poses (each a rigid transform)
    or one line naming the file."""
    header = "frame,timestamp_s,valid," + ",".join(f"T{i}{j}" for i in range(4) for j in range(4))
    text = (header + "\n" + "\n".join(",".join(["0", "0.0", "1", *r]) for r in rows))[: len(header) + 1 + cut]
    path = tmp_path / "poses.csv"
    path.write_text(text)
    try:
        times, poses, _ = read_track_csv(path)
    except ValueError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
        return
    assert len(times) == len(poses)
    for T in poses:
        if T is not None:
            R = T[:3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0


@FAST
@given(rows=st.lists(st.tuples(st.text(string.ascii_letters + ".", max_size=6), _cells), max_size=6))
def test_any_ultrasound_timestamps_are_read_or_refused(rows, tmp_path_factory):
    folder = tmp_path_factory.mktemp("us")
    (folder / "timestamps.csv").write_text("file,timestamp_s\n" + "\n".join(f"{f},{t}" for f, t in rows))
    try:
        files, times = read_frames(folder)
    except ValueError as exc:
        assert "\n" not in str(exc)
        return
    assert len(files) == len(times) and np.all(np.isfinite(times)) and np.all(np.diff(times) > 0)


@FAST
@given(fps=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e-300, 1e-300)))
def test_any_frame_rate_is_used_or_refused(fps, tmp_path):
    try:
        open_stereo(str(tmp_path), str(tmp_path), fps)
    except ValueError as exc:
        refused_for_fps = "fps" in str(exc)
        assert refused_for_fps == (not MIN_FPS <= fps <= MAX_FPS), (fps, str(exc))
        return
    raise AssertionError("an empty folder was accepted")
