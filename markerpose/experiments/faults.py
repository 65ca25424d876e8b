"""``markerpose eval faults``: a seeded fault campaign against the API and the command line.

Every case feeds one input that a hostile or careless user could give (a mutated rig file,
a stage setting, an image array, an image file, a folder or video to track, a poses CSV, a
number on the command line) and says what the answer must be: a **refusal** (a
``ValueError``-family error with a one-line message from the API, exit 2 with one line and
no traceback from the command line) for a bad input, a **result** for a good one. Each
class runs in its own process, so that a crash (a segfault in a library) costs one class
and names the case it happened in; a class that runs past ``timeout_s`` is a hang.

Outcomes: ``refused`` and ``ok`` are right where they were expected; ``accepted`` (a bad
input given a result), ``traceback`` (any other exception, or a traceback on stderr),
``crash``, ``hang`` and ``wrong refusal`` (a good input refused) are faults.

    markerpose eval faults [--cases 40] [--seed 0] [--out DIR]
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ..formats import write_report

default_conf = {"cases": 45, "seed": 0, "timeout_s": 900.0}
REFUSALS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError)


# --- how one case is judged -------------------------------------------------------------------
def api(fn: Callable, bad: bool) -> tuple[str, str]:
    """(outcome, detail) of an API call on a bad (refusal expected) or good input."""
    try:
        fn()
    except REFUSALS as exc:
        line = str(exc)
        if "\n" in line.strip() or not line.strip():
            return "traceback", f"{type(exc).__name__} without a one-line message: {line[:120]!r}"
        return ("refused" if bad else "wrong refusal"), line[:160]
    except Exception as exc:  # the fault the campaign looks for
        return "traceback", f"{type(exc).__name__}: {str(exc)[:160]}"
    return ("accepted" if bad else "ok"), ""


def cli(argv: list[str], bad: bool, ok_codes=(0, 1)) -> tuple[str, str]:
    """(outcome, detail) of ``markerpose ARGV`` run in this process (stdout and stderr caught)."""
    from .. import cli as command_line

    err, out = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            rc = command_line.main(argv)
    except SystemExit as exc:  # argparse: a bad option value
        rc = exc.code if isinstance(exc.code, int) else 2
    except Exception as exc:
        return "traceback", f"{type(exc).__name__}: {str(exc)[:160]}"
    text = err.getvalue()
    if "Traceback" in text:
        return "traceback", text.strip().splitlines()[-1][:160]
    if rc == 2:
        lines = [ln for ln in text.strip().splitlines() if ln.strip()]
        detail = lines[-1][:160] if lines else ""
        return ("refused" if bad else "wrong refusal"), detail
    if rc in ok_codes:
        return ("accepted" if bad else "ok"), f"exit {rc}"
    return "traceback", f"exit {rc}: {text.strip()[-160:]}"


# --- the classes ------------------------------------------------------------------------------
def _rig_text(tmp: Path) -> str:
    from ..camera import StereoRig

    path = StereoRig.default().save(tmp / "good.yaml")
    return path.read_text()


def rig_files(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """Mutated rig files through ``StereoRig.load`` (and one in ten through ``estimate --rig``)."""
    import cv2

    from ..camera import StereoRig

    good = _rig_text(tmp)
    lines = good.splitlines()
    blank = np.zeros((1024, 1280), np.uint8)
    images = [str(tmp / "blank-left.png"), str(tmp / "blank-right.png")]
    for p in images:
        cv2.imwrite(p, blank)

    def mutate(k: int) -> tuple[str, str, bool]:
        kind = k % 12
        if kind == 0:
            return "unchanged", good, False
        if kind == 1:
            cut = int(rng.integers(10, len(good) - 10))
            return f"cut at byte {cut}", good[:cut], True
        if kind == 2:
            key = rng.choice(["K1", "dist1", "K2", "dist2", "R", "t"])
            out, skip = [], False
            for ln in lines:
                if ln.startswith(f"{key}:"):
                    skip = True
                    continue
                if skip and ln.startswith(" "):
                    continue
                skip = False
                out.append(ln)
            return f"without {key}", "\n".join(out) + "\n", True
        if kind == 3:
            v = rng.choice([".nan", ".inf", "-.inf", "1e309", "abc"])
            return f"a value {v}", good.replace("data: [ ", f"data: [ {v}, ", 1), True
        if kind == 4:
            depth = int(rng.integers(33, 60000))
            return f"nested {depth} deep", "%YAML:1.0\n---\nK1: " + "[" * depth + "]" * depth + "\n", True
        if kind == 5:
            return "random bytes", rng.integers(0, 256, int(rng.integers(1, 4000)), dtype=np.uint8).tobytes().decode("latin-1"), True
        if kind == 6:
            return "empty", "", True
        if kind == 7:
            return "1.5 MB of comments", good + ("# pad\n" * 260000), True
        if kind == 8:
            s = float(rng.choice([0.5, 2.0, -1.0]))
            return (
                f"R scaled by {s:g}",
                good.replace(
                    "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ ",
                    f"R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {s}, ",
                ),
                True,
            )
        if kind == 9:
            return (
                "3 x 2 translation",
                good.replace("t: !!opencv-matrix\n   rows: 3\n   cols: 1", "t: !!opencv-matrix\n   rows: 3\n   cols: 2"),
                True,
            )
        if kind == 10:
            w = int(rng.choice([0, 8, -640, 63]))
            return f"image_size {w} x 1024", good.replace("data: [ 1280, 1024 ]", f"data: [ {w}, 1024 ]"), True
        return "a focal length of -2500", good.replace("data: [ ", "data: [ -", 1), True

    for k in range(n):
        what, text, bad = mutate(k)
        if bad and text == good:  # the campaign's own check: a mutation that did not apply
            raise RuntimeError(f"the rig mutation {what!r} left the file as it was")
        path = tmp / f"rig{k}.yaml"
        path.write_bytes(text.encode("latin-1", "replace") if isinstance(text, str) else text)
        if k % 10 == 9 or k % 12 == 10:  # a tiny image size is a rig; the tracker is what refuses it
            yield f"estimate --rig, {what}", bad, lambda p=path, b=bad: cli(["estimate", *images, "--rig", str(p)], b)
        else:
            yield what, bad, lambda p=path, b=bad: api(lambda: StereoRig.load(p), b)


def settings(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """Stage settings with values of the wrong type or out of any range, and the presets'
    own values: refused when made, or a tracker that runs a pair."""
    from ..camera import StereoRig
    from ..pipeline import MarkerPose
    from ..presets import default_conf as conf
    from ..synth import look_at_pose, render_stereo

    rig = StereoRig.default()
    pair = render_stereo(rig, look_at_pose([0, 0, 560], 20, 30, 0), seed=1).images
    keys = [(stage, key, v) for stage, c in conf.items() if isinstance(c, dict) for key, v in c.items() if not isinstance(v, (dict, list))]
    for k in range(n):
        stage, key, value = keys[int(rng.integers(len(keys)))]
        if k % 4 == 0:
            new, bad = value, False
        elif isinstance(value, bool):
            new, bad = rng.choice(["yes", "1", 2]).item(), True
        elif isinstance(value, (int, float)):
            new, bad = [float("nan"), "x", [1, 2], {"a": 1}, None][k % 5], True
        else:
            new, bad = 12345, True

        def run(stage=stage, key=key, new=new):
            MarkerPose(rig, **{stage: {key: new}}).estimate(*pair)

        yield f"{stage}.{key}={new!r}", bad, lambda run=run, b=bad: api(run, b)


def arrays(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """``estimate`` on image arrays of the wrong shape, type or size, and on right ones."""
    from ..camera import StereoRig
    from ..pipeline import MarkerPose

    rig = StereoRig.default()
    tracker = MarkerPose(rig, preset="classical")
    W, H = rig.left.image_size
    makers = [
        ("good uint8", False, lambda: rng.integers(0, 256, (H, W), dtype=np.uint8)),
        ("good BGR", False, lambda: rng.integers(0, 256, (H, W, 3), dtype=np.uint8)),
        ("empty", True, lambda: np.zeros((0, 0), np.uint8)),
        ("wrong size", True, lambda: np.zeros((int(rng.integers(1, H)), int(rng.integers(1, W))), np.uint8)),
        ("1-D", True, lambda: np.zeros(W * H, np.uint8)),
        ("4-D", True, lambda: np.zeros((1, H, W, 1), np.uint8)),
        ("complex", True, lambda: np.zeros((H, W), np.complex64)),
        ("object", True, lambda: np.full((H, W), None, object)),
        ("NaN float", True, lambda: np.full((H, W), np.nan, np.float32)),
        ("None", True, lambda: None),
        ("a list", True, lambda: [[0] * 4] * 4),
        ("5 channels", True, lambda: np.zeros((H, W, 5), np.uint8)),
    ]
    for k in range(n):
        what, bad, make = makers[k % len(makers)]
        good = rng.integers(0, 256, (H, W), dtype=np.uint8)
        left, right = (make(), good) if k % 2 else (good, make())
        yield what, bad, lambda a=left, b=right, bad=bad: api(lambda: tracker.estimate(a, b), bad)


def image_files(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """``markerpose estimate`` on image files that are not images, or not the rig's."""
    import cv2

    from ..camera import StereoRig
    from ..synth import look_at_pose, render_stereo

    rig = StereoRig.default()
    pair = render_stereo(rig, look_at_pose([0, 0, 560], 20, 30, 0), seed=2).images
    good = [tmp / "left.png", tmp / "right.png"]
    for p, img in zip(good, pair):
        cv2.imwrite(str(p), img)
    png = good[0].read_bytes()
    for k in range(n):
        kind = k % 8
        path = tmp / f"img{k}.png"
        if kind == 0:
            what, bad, path = "a rendered pair", False, good[0]
        elif kind == 1:
            what, bad = "0 bytes", True
            path.write_bytes(b"")
        elif kind == 2:
            cut = int(rng.integers(8, len(png) // 2))
            what, bad = f"a PNG cut at byte {cut}", True
            path.write_bytes(png[:cut])
        elif kind == 3:
            what, bad = "random bytes", True
            path.write_bytes(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
        elif kind == 4:
            what, bad = "text", True
            path.write_text("not an image\n")
        elif kind == 5:
            what, bad = "a folder", True
            path = tmp / f"dir{k}.png"
            path.mkdir()
        elif kind == 6:
            what, bad = "missing", True
        else:
            what, bad = "64 x 48, not the rig's size", True
            cv2.imwrite(str(path), np.zeros((48, 64), np.uint8))
        args = [str(path), str(good[1])] if k % 2 else [str(good[0]), str(path)]
        if path == good[0]:
            args = [str(good[0]), str(good[1])]
        yield what, bad, lambda a=args, b=bad: cli(["estimate", *a], b)


def tracking(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """``markerpose track`` on folders and videos that are empty, uneven, corrupt or
    truncated, and on good ones: the CSV must hold every row before a bad frame."""
    import cv2

    from ..camera import StereoRig
    from ..synth import look_at_pose, render_stereo

    rig = StereoRig.default()
    frames = [render_stereo(rig, look_at_pose([k, 0, 560], 20, 30, 0), seed=k).images for k in range(4)]
    for k in range(n):
        kind = k % 8
        d = tmp / f"rec{k}"
        (d / "L").mkdir(parents=True)
        (d / "R").mkdir()
        count = len(frames)
        for j, (a, b) in enumerate(frames):
            cv2.imwrite(str(d / "L" / f"{j:03d}.png"), a)
            cv2.imwrite(str(d / "R" / f"{j:03d}.png"), b)
        left, right, extra, bad = str(d / "L"), str(d / "R"), [], True
        if kind == 0:
            what, bad = "four good pairs", False
        elif kind == 1:
            what = "an empty folder"
            for p in (d / "R").iterdir():
                p.unlink()
        elif kind == 2:
            what = "a frame more on the left"
            cv2.imwrite(str(d / "L" / "999.png"), frames[0][0])
        elif kind == 3:
            j = int(rng.integers(1, count))
            what = f"pair {j} a 0-byte file"
            (d / "L" / f"{j:03d}.png").write_bytes(b"")
        elif kind == 4:
            what = "a video of random bytes"
            (d / "v.mp4").write_bytes(rng.integers(0, 256, 20000, dtype=np.uint8).tobytes())
            left = right = str(d / "v.mp4")
        elif kind == 5:
            fps = rng.choice(["nan", "inf", "-1", "0", "1e-320", "1e9", "abc"]).item()
            what, extra = f"--fps {fps}", ["--fps", fps]
        elif kind == 6:
            what, left = "camera index 99999999999999999999", "99999999999999999999"
        else:
            what, extra = "--out in a missing folder", ["--out", str(d / "missing" / "p.csv")]
        out = ["--out", str(d / "poses.csv")] if "--out" not in extra else []
        argv = ("track", left, right, *out, *extra, "--quiet")

        def run(argv=argv, bad=bad, d=d, kind=kind):
            outcome, detail = cli(list(argv), bad)
            if kind == 3 and outcome == "refused":  # the rows before the bad pair must be kept, under the name asked for
                rows = (d / "poses.csv").read_text().splitlines() if (d / "poses.csv").is_file() else []
                if len(rows) < 2 or any(p.name.endswith(".partial") for p in d.iterdir()):
                    return "accepted", f"rows lost: {len(rows)} lines in poses.csv"
            return outcome, detail

        yield what, bad, run


def _pivoting_csv() -> tuple[str, list[list[str]]]:
    """A track CSV's header and rows of 60 poses of a tool pivoting about its tip."""
    from ..pivot import pivoting_poses
    from ..video import CSV_HEADER

    T = pivoting_poses((12.5, -110.0, -4.0), (10.0, 100.0, 560.0), 60, 25.0, np.random.default_rng(5))
    rows = [[str(k), f"{k / 30:.6f}", "", "1"] + [""] * 10 + [f"{v:.9g}" for v in Ti.ravel()] + ["", "", "", ""] for k, Ti in enumerate(T)]
    return ",".join(CSV_HEADER), rows


def poses_csvs(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """``markerpose pivot`` on poses CSVs cut, emptied, non-numeric or non-rigid, and good."""
    header, rows = _pivoting_csv()
    good = header + "\n" + "\n".join(",".join(r) for r in rows) + "\n"
    for k in range(n):
        kind = k % 7
        path = tmp / f"poses{k}.csv"
        bad = True
        if kind == 0:
            what, text, bad = "60 poses pivoting", good, False
        elif kind == 1:
            cut = int(rng.integers(len(header) + 5, len(good) - 5))
            what, text = f"cut at byte {cut}", good[:cut]
        elif kind == 2:
            what, text = "header only", header + "\n"
        elif kind == 3:
            what, text = "empty", ""
        elif kind == 4:
            j = int(rng.integers(len(rows)))
            bad_rows = [list(r) for r in rows]
            bad_rows[j][14 + int(rng.integers(16))] = rng.choice(["x", "nan", "inf", ""]).item()
            what, text = f"row {j + 2} with a bad number", header + "\n" + "\n".join(",".join(r) for r in bad_rows) + "\n"
        elif kind == 5:
            j = int(rng.integers(len(rows)))
            bad_rows = [list(r) for r in rows]
            bad_rows[j][14] = f"{float(bad_rows[j][14]) * 1.5:.9g}"
            what, text = f"row {j + 2} not a rotation", header + "\n" + "\n".join(",".join(r) for r in bad_rows) + "\n"
        else:
            what, text = "random bytes", rng.integers(0, 256, 3000, dtype=np.uint8).tobytes().decode("latin-1")
        path.write_text(text, encoding="latin-1")
        yield what, bad, lambda p=path, b=bad, k=k: cli(["pivot", str(p), "--out", str(tmp / f"tip{k}.yaml")], b)


def numbers(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """Numbers on the command line out of range or not numbers: refused before any work."""
    bad = [
        ("track", "--igtl-port", ["-1", "70000", "abc", "1.5"]),
        ("track", "--right-delay", ["nan", "5000", "x"]),
        ("ultrasound calibrate", "--spacing", ["1e300,1e300", "0,1", "a,b", "-1,1", "1"]),
        ("calibrate", "--every", ["0", "-3", "x"]),
        ("peers", "--pairs", ["0", "-1", "x"]),
        ("eval sync", "--frames", ["0", "x"]),
    ]
    base = {
        "track": ["track", "L", "R", "--igtl"],
        "ultrasound calibrate": ["ultrasound", "calibrate", "--poses", "p.csv", "--images", "us"],
        "calibrate": ["calibrate", "L", "R", "--grid", "4x11", "--spacing", "15"],
        "peers": ["peers"],
        "eval sync": ["eval", "sync"],
    }
    cases = [(cmd, opt, v) for cmd, opt, vals in bad for v in vals]
    for _ in range(n):
        cmd, opt, v = cases[int(rng.integers(len(cases)))]
        argv = [*base[cmd], opt, v]

        def run(argv=argv, opt=opt):
            outcome, detail = cli(argv, True)
            if outcome == "refused" and opt not in detail:  # refused, but for another reason: the number went through
                return "accepted", f"refused without naming {opt}: {detail}"
            return outcome, detail

        yield f"{cmd} {opt} {v}", True, run


def command_files(n: int, rng: np.random.Generator, tmp: Path) -> Iterator[tuple[str, bool, Callable]]:
    """The other commands' file inputs, malformed: ``handeye``'s robot CSV, ``ultrasound
    calibrate``'s timestamps, ``ultrasound reconstruct``'s probe calibration, ``track
    --tools``' tool files, ``batch``'s list file, ``sync``'s and ``calibrate``'s folders."""
    import cv2
    import yaml

    from ..marker import Marker

    rows = [f"{k / 10:.3f}," + ",".join(f"{v:g}" for v in np.eye(4).ravel()) for k in range(6)]
    robot_good = "timestamp_s," + ",".join(f"T{i}{j}" for i in range(4) for j in range(4)) + "\n" + "\n".join(rows) + "\n"
    header, pose_rows = _pivoting_csv()
    good_poses = tmp / "poses-good.csv"
    good_poses.write_text(header + "\n" + "\n".join(",".join(r) for r in pose_rows) + "\n")
    us = tmp / "us"
    us.mkdir()
    for k in range(3):
        cv2.imwrite(str(us / f"{k:03d}.png"), np.zeros((64, 64), np.uint8))
    frames = tmp / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "000.png"), np.zeros((1024, 1280), np.uint8))
    empty = tmp / "empty"
    empty.mkdir()
    Marker().save(tmp / "marker.yaml")
    tool_text = (tmp / "marker.yaml").read_text()
    probe_good = "%YAML:1.0\n---\nT_marker_image: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n   data: [ 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1. ]\nspacing: [ 0.1, 0.1 ]\n"

    def case(k: int) -> tuple[str, list]:
        kind = k % 8
        f = tmp / f"in{k}"
        if kind == 0:
            cut = int(rng.integers(20, len(robot_good) - 5))
            f.with_suffix(".csv").write_text(robot_good[:cut] + ",x")
            return f"handeye: a robot CSV cut at byte {cut}", [
                "handeye",
                "--robot",
                str(f.with_suffix(".csv")),
                "--poses",
                str(good_poses),
                "--setup",
                "eye-to-hand",
                "--out",
                str(tmp / f"h{k}.yaml"),
            ]
        if kind == 1:
            bad = rng.choice(["a row of one field", "times going back", "a NaN time"]).item()
            text = {
                "a row of one field": "file,timestamp_s\n000.png\n",
                "times going back": "file,timestamp_s\n000.png,1.0\n001.png,0.5\n002.png,0.7\n",
                "a NaN time": "file,timestamp_s\n000.png,nan\n001.png,1\n002.png,2\n",
            }[bad]
            d = tmp / f"us{k}"
            d.mkdir()
            for p in us.iterdir():
                (d / p.name).write_bytes(p.read_bytes())
            (d / "timestamps.csv").write_text(text)
            return f"ultrasound calibrate: timestamps with {bad}", [
                "ultrasound",
                "calibrate",
                "--poses",
                str(good_poses),
                "--images",
                str(d),
                "--spacing",
                "0.1,0.1",
                "--out",
                str(tmp / f"p{k}.yaml"),
            ]
        if kind == 2:
            bad = rng.choice(["spacing", "T_marker_image", "all"]).item()
            text = {
                "spacing": probe_good.replace("spacing: [ 0.1, 0.1 ]", "spacing: [ 0.1 ]"),
                "T_marker_image": probe_good.replace("rows: 4", "rows: 2").replace("cols: 4", "cols: 8"),
                "all": "garbage: [\n",
            }[bad]
            f.with_suffix(".yaml").write_text(text)
            return f"ultrasound reconstruct: a probe file with a bad {bad}", [
                "ultrasound",
                "reconstruct",
                "--poses",
                str(good_poses),
                "--images",
                str(us),
                "--calibration",
                str(f.with_suffix(".yaml")),
                "--out",
                str(tmp / f"r{k}"),
                "--fps",
                "10",
                "--quiet",
            ]
        if kind == 3:
            bad = rng.choice(["without rings", "rings of 2 points", "a word for a diameter", "not YAML"]).item()
            text = {
                "without rings": yaml.safe_dump({k: v for k, v in yaml.safe_load(tool_text).items() if k != "rings"}),
                "rings of 2 points": "name: t\nrings: [[0, 0], [25, 0]]\nouter_diameter: 20\ninner_diameter: 8\nplate_margin: 10\n",
                "a word for a diameter": re.sub(r"outer_diameter: .*", "outer_diameter: big", tool_text),
                "not YAML": "{[}: :\n",
            }[bad]
            f.with_suffix(".yaml").write_text(text)
            return f"track --tools: a tool file {bad}", [
                "track",
                str(frames),
                str(frames),
                "--tools",
                str(f.with_suffix(".yaml")),
                str(tmp / "marker.yaml"),
                "--out",
                str(tmp / f"t{k}.csv"),
                "--quiet",
            ]
        if kind == 4:
            f.with_suffix(".txt").write_text(rng.choice(["a b c d e\n", "missing-folder\n", "x y\n"]).item())
            return "batch: a list file with a bad line", [
                "batch",
                str(f.with_suffix(".txt")),
                "--serial",
                "--quiet",
                "--out",
                str(tmp / f"b{k}"),
            ]
        if kind == 5:
            return "sync: an empty folder", ["sync", str(empty), str(frames)]
        if kind == 6:
            return "calibrate: a folder without the grid", [
                "calibrate",
                str(frames),
                str(frames),
                "--grid",
                "4x11",
                "--spacing",
                "15",
                "--out",
                str(tmp / f"c{k}.yaml"),
            ]
        return "track --tools: the same tool twice", [
            "track",
            str(frames),
            str(frames),
            "--tools",
            str(tmp / "marker.yaml"),
            str(tmp / "marker.yaml"),
            "--out",
            str(tmp / f"t{k}.csv"),
            "--quiet",
        ]

    for k in range(n):
        what, argv = case(k)
        yield what, True, lambda a=argv: cli(a, True)


CLASSES = {
    "rig files": rig_files,
    "settings": settings,
    "image arrays": arrays,
    "image files": image_files,
    "tracking inputs": tracking,
    "poses CSVs": poses_csvs,
    "command-line numbers": numbers,
    "other commands' files": command_files,
}
FAULTS = ("accepted", "traceback", "crash", "hang", "wrong refusal")


# --- one class in its own process ---------------------------------------------------------------
def run_class(name: str, n: int, seed: int, log: Path) -> None:
    """Every case of class ``name``: a line 'start' before each, its outcome after (so a
    crash names its case)."""
    rng = np.random.default_rng([seed, list(CLASSES).index(name)])
    with tempfile.TemporaryDirectory() as tmp, open(log, "a") as f:
        os.chdir(tmp)  # outputs a case writes by default stay in the temporary folder
        for k, (what, bad, fn) in enumerate(CLASSES[name](n, rng, Path(tmp))):
            f.write(json.dumps({"k": k, "case": what, "bad": bad, "start": True}) + "\n")
            f.flush()
            t0 = time.perf_counter()
            outcome, detail = fn()
            f.write(
                json.dumps({"k": k, "case": what, "bad": bad, "outcome": outcome, "detail": detail, "s": time.perf_counter() - t0}) + "\n"
            )
            f.flush()


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    c = {**default_conf, **(conf or {})}
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in CLASSES:
            log = Path(tmp) / f"{name.replace(' ', '_')}.jsonl"
            if progress:
                print(f"faults: {name} ({c['cases']} cases) ...", file=sys.stderr)
            cmd = [sys.executable, "-m", "markerpose.experiments.faults", name, str(int(c["cases"])), str(int(c["seed"])), str(log)]
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=c["timeout_s"])
                ended = None if proc.returncode == 0 else f"the process ended with {proc.returncode}: {proc.stderr.strip()[-200:]}"
                stuck = "crash"
            except subprocess.TimeoutExpired:
                ended, stuck = f"no answer within {c['timeout_s']:g} s", "hang"
            results[name] = read_log(log, ended, stuck)
    res = {"conf": c, "classes": results, "totals": _totals(results)}
    if out is not None:
        write_report(out, res, report(res))
    return res


def read_log(log: Path, ended: str | None, stuck: str = "crash") -> list[dict]:
    """A class's cases from its log: each case's outcome; where the process ``ended``
    abnormally, the case it had started and not finished is ``stuck`` (crash or hang)."""
    cases: dict = {}
    for line in log.read_text().splitlines() if log.is_file() else []:
        rec = json.loads(line)
        cases[rec["k"]] = rec
    for rec in cases.values():
        if rec.get("start") and ended is not None:
            rec.update(outcome=stuck, detail=ended)
    return [cases[k] for k in sorted(cases) if "outcome" in cases[k]]


def _totals(results: dict) -> dict:
    every = [r for rs in results.values() for r in rs]
    out = {"cases": len(every)}
    for o in ("refused", "ok", *FAULTS):
        out[o] = sum(r["outcome"] == o for r in every)
    return out


def report(res: dict) -> str:
    t = res["totals"]
    lines = [
        "# Fault campaign: bad inputs against the API and the command line",
        "",
        f"{t['cases']} seeded cases (seed {res['conf']['seed']}), each class in its own process. A bad input must be "
        "refused (a one-line error; exit 2 from the command line, no traceback), a good one must give a result.",
        "",
        "| class | cases | bad inputs refused | good inputs with a result | accepted (bad, no error) | tracebacks | crashes | hangs | good refused |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, rs in res["classes"].items():
        n = {o: sum(r["outcome"] == o for r in rs) for o in ("refused", "ok", *FAULTS)}
        bad = sum(r["bad"] for r in rs)
        lines.append(
            f"| {name} | {len(rs)} | {n['refused']} of {bad} | {n['ok']} of {len(rs) - bad} | {n['accepted']} | {n['traceback']} | "
            f"{n['crash']} | {n['hang']} | {n['wrong refusal']} |"
        )
    lines.append(
        f"| all | {t['cases']} | {t['refused']} | {t['ok']} | {t['accepted']} | {t['traceback']} | {t['crash']} | {t['hang']} | {t['wrong refusal']} |"
    )
    faults = [(name, r) for name, rs in res["classes"].items() for r in rs if r["outcome"] in FAULTS]
    lines += ["", f"**Faults: {len(faults)}.**", ""]
    for name, r in faults:
        lines.append(f"- {name}, {r['case']}: {r['outcome']} ({r['detail']})")
    examples = {}
    for name, rs in res["classes"].items():
        for r in rs:
            if r["outcome"] == "refused" and name not in examples:
                examples[name] = r
    lines += ["", "One refusal per class, as the user reads it:", ""]
    lines += [f"- {name}, {r['case']}: `{r['detail']}`" for name, r in examples.items()]
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    run_class(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4]))


__all__ = ["CLASSES", "api", "cli", "default_conf", "main", "read_log", "report", "run_class"]
