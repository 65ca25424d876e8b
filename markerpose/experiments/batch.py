"""``markerpose eval batch``: many recordings, tracked three ways, timed in one run.

``recordings`` rendered recordings of ``frames`` pairs each (one rendered hand-held path,
each recording starting at another frame of it, so no two are the same), tracked as a user
would track them, each as its own command: ``markerpose track`` once per recording, one after
the other (a shell loop); ``markerpose batch --serial`` (one process, no Ray);
``markerpose batch`` on a local Ray with ``workers`` workers (where Ray is installed). The
wall time of each, start-up included, gives recordings per minute; every recording's CSV
is compared with track's (all columns but the wall-clock ``timestamp_unix``).

    markerpose eval batch [--recordings 8] [--frames 120] [--workers 2] [--out DIR]
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..engine import ray_installed
from ..formats import write_report
from ..synth import Imaging, clutter_background, look_at_pose, render_stereo

default_conf = {"recordings": 8, "frames": 120, "workers": 2, "seed": 5200}


def _render(folder: Path, n: int, seed: int, progress: bool) -> None:
    """``n`` pairs of a marker moved by hand around 560 mm (PNG folders left/ and right/)."""
    rig, rng = StereoRig.default(), np.random.default_rng(seed)
    bgs = tuple(clutter_background(cam.image_size, rng) for cam in rig.cameras)
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True, exist_ok=True)
    for k in tqdm(range(n), desc="render", unit="pair", disable=not progress):
        t = k / 30
        T = look_at_pose(
            [-5 + 25 * np.sin(2 * np.pi * 0.3 * t), 10 * np.sin(2 * np.pi * 0.4 * t + 1), 560 + 30 * np.sin(2 * np.pi * 0.2 * t)],
            30 + 8 * np.sin(2 * np.pi * 0.25 * t),
            45 + 20 * np.sin(2 * np.pi * 0.15 * t),
            5,
        )
        pair = render_stereo(rig, T, imaging=Imaging(alpha=0.8, motion_blur=2.0), background=bgs, seed=int(rng.integers(1 << 31)))
        for side, img in zip(("left", "right"), pair.images):
            cv2.imwrite(str(folder / side / f"{k:05d}.png"), img)


def _recordings(frames: Path, root: Path, count: int, n: int) -> list[Path]:
    """``count`` recordings of ``n`` pairs each: the rendered path from a different start,
    wrapping round (links to the rendered files)."""
    out = []
    for i in range(count):
        rec = root / f"rec{i:02d}"
        for side in ("left", "right"):
            (rec / side).mkdir(parents=True, exist_ok=True)
            for j in range(n):
                os.symlink(frames / side / f"{(j + i * n // count) % n:05d}.png", rec / side / f"{j:05d}.png")
        out.append(rec)
    return out


def _rows(path: Path) -> list[dict]:
    with open(path) as f:
        return [{k: v for k, v in row.items() if k != "timestamp_unix"} for row in csv.DictReader(f)]


def _timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "markerpose.cli", *cmd], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    c = {**default_conf, **(conf or {})}
    work = Path(out or "markerpose-batch") / "work"
    if work.exists():
        import shutil

        shutil.rmtree(work)
    _render(work / "frames", int(c["frames"]), int(c["seed"]), progress)
    recs = _recordings(work / "frames", work / "recordings", int(c["recordings"]), int(c["frames"]))
    runs = {}
    # A shell loop of track commands, each starting its own process.
    t = 0.0
    (work / "track").mkdir()
    for rec in tqdm(recs, desc="track, one after the other", disable=not progress):
        t += _timed(["track", str(rec / "left"), str(rec / "right"), "--out", str(work / "track" / f"{rec.name}.csv"), "--quiet"])
    runs["track, one recording after the other"] = {"seconds": t, "dir": None}
    if progress:
        print("batch --serial ...", file=sys.stderr)
    runs["batch --serial (one process)"] = {
        "seconds": _timed(["batch", str(work / "recordings"), "--out", str(work / "serial"), "--serial", "--quiet"]),
        "dir": "serial",
    }
    if ray_installed():
        if progress:
            print(f"batch on a local Ray of {c['workers']} workers ...", file=sys.stderr)
        runs[f"batch on a local Ray, {c['workers']} workers"] = {
            "seconds": _timed(["batch", str(work / "recordings"), "--out", str(work / "ray"), "--workers", str(c["workers"]), "--quiet"]),
            "dir": "ray",
        }
    base = runs["track, one recording after the other"]["seconds"]
    for r in runs.values():
        r["recordings_per_min"] = 60 * len(recs) / r["seconds"]
        r["speed_up"] = base / r["seconds"]
        if r["dir"] is not None:
            r["csvs_as_track"] = all(
                _rows(work / r["dir"] / rec.name / "poses.csv") == _rows(work / "track" / f"{rec.name}.csv") for rec in recs
            )
    res = {"conf": c, "cpus": os.cpu_count(), "ray": ray_installed(), "runs": runs}
    if out is not None:
        write_report(out, res, report(res))
    return res


def report(res: dict) -> str:
    c = res["conf"]
    lines = [
        "# Many recordings: track one after the other, batch, batch on Ray",
        "",
        f"{c['recordings']} rendered recordings of {c['frames']} pairs each (PNG folders, 1280 × 1024), {res['cpus']} CPU cores; "
        "each way run as its own command and timed from start to end (start-up included).",
        "",
        "| how | wall time (s) | recordings per minute | speed-up over track | CSVs as track's |",
        "|---|---|---|---|---|",
    ]
    for name, r in res["runs"].items():
        same = "-" if r["dir"] is None else ("identical" if r["csvs_as_track"] else "DIFFERENT")
        lines.append(f"| {name} | {r['seconds']:.1f} | {r['recordings_per_min']:.1f} | {r['speed_up']:.2f}× | {same} |")
    if not res["ray"]:
        lines += ["", "Ray is not installed here: no Ray row (pip install 'markerpose[ray]')."]
    lines.append("")
    return "\n".join(lines)


__all__ = ["default_conf", "main", "report"]
