"""Many recordings, each tracked as ``markerpose track`` tracks one (``markerpose batch``).

A recording is a folder holding the two cameras' frames, ``left`` and ``right`` (image
folders, or videos named ``left.mp4``, ``right.avi``, …; ``L`` and ``R`` also do),
optionally its own rig (``rig.yaml`` or ``rig.xml``) and an ultrasound sweep (``us/``, with
its ``timestamps.csv``). A list file names recordings one a line: a recording folder, or
``LEFT RIGHT [RIG]`` (paths relative to the list file; ``#`` starts a comment).

Each recording's outputs go into its folder, or into ``OUT/<name>``: ``poses.csv``
(``poses.jsonl``), ``reconstruction/`` where it has a sweep and a probe calibration is
given, and last ``batch.json``, the record that the recording is done, with its summary.
A recording with a ``batch.json`` is skipped by the next run; one killed midway has
none, and its CSV, written under a ``.partial`` name until complete, is redone.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from . import __version__
from .engine import Failed, ray_installed, run_tasks

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")
SIDES = (("left", "L"), ("right", "R"))
RIG_NAMES = ("rig.yaml", "rig.yml", "rig.xml")
DONE = "batch.json"
SUMMARY_COLUMNS = ("recording", "status", "frames", "found", "tracked", "frames_per_s", "seconds", "outputs", "reason")


@dataclass(frozen=True)
class Recording:
    """One recording: its name (unique in a run), both cameras' frames, its rig (None: the
    run's), its ultrasound sweep (None: none) and the folder its outputs go to by default."""

    name: str
    left: str
    right: str
    rig: str | None = None
    us: str | None = None
    folder: str = "."


def _side(folder: Path, names: tuple[str, str]) -> Path | None:
    for name in names:
        if (folder / name).is_dir():
            return folder / name
        for suffix in VIDEO_SUFFIXES:
            if (folder / (name + suffix)).is_file():
                return folder / (name + suffix)
    return None


def recording_at(folder) -> Recording | None:
    """The recording in ``folder``, or None where it has no left and right frames."""
    folder = Path(folder)
    left, right = (_side(folder, names) for names in SIDES)
    if left is None or right is None:
        return None
    rig = next((str(folder / n) for n in RIG_NAMES if (folder / n).is_file()), None)
    us = str(folder / "us") if (folder / "us").is_dir() else None
    return Recording(folder.resolve().name, str(left), str(right), rig, us, str(folder))


def _from_list(path: Path) -> list[Recording]:
    found = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        where = [p if Path(p).is_absolute() else str(path.parent / p) for p in fields]
        if len(fields) == 1:
            rec = recording_at(where[0])
            if rec is None:
                raise ValueError(f"{path}, line {n}: {fields[0]} is not a recording (no left and right frames in it)")
        elif len(fields) in (2, 3):
            for p in where[:2]:
                if not Path(p).exists():
                    raise ValueError(f"{path}, line {n}: {p} does not exist")
            folder = Path(where[0]).parent
            rec = Recording(folder.resolve().name, where[0], where[1], where[2] if len(where) == 3 else None, None, str(folder))
        else:
            raise ValueError(f"{path}, line {n}: give a recording folder or LEFT RIGHT [RIG], got {len(fields)} fields")
        found.append(rec)
    return found


def find_recordings(sources) -> list[Recording]:
    """The recordings named by ``sources``: recording folders, folders of recording folders,
    list files. ``ValueError`` for a source that holds none, or two recordings of one name."""
    found: list[Recording] = []
    for source in sources:
        p = Path(source)
        if p.is_file():
            found += _from_list(p)
        elif p.is_dir():
            rec = recording_at(p)
            inside = [] if rec else [r for r in (recording_at(d) for d in sorted(p.iterdir()) if d.is_dir()) if r is not None]
            if rec is None and not inside:
                raise ValueError(f"{p}: no recording here (a recording is a folder with left and right frames: left/, right/ or videos)")
            found += [rec] if rec else inside
        else:
            raise ValueError(f"{p}: no such file or folder")
    seen: dict[str, Recording] = {}
    for rec in found:
        if rec.name in seen:
            raise ValueError(f"two recordings are named {rec.name}: {seen[rec.name].folder} and {rec.folder}; rename one")
        seen[rec.name] = rec
    return found


@dataclass(frozen=True)
class Job:
    """One recording's task: where its outputs go and how to track it (picklable)."""

    recording: Recording
    out: str
    make_tracker: object  # rig path or None -> MarkerPose, as the command line builds it
    fps: float = 60.0
    right_delay: float | None = None
    tools: bool = False
    reference: str | None = None
    jsonl: bool = False
    probe: str | None = None  # probe calibration: reconstruct the recordings with a sweep
    time_offset_s: float = 0.0


def done_record(out) -> dict | None:
    """The ``batch.json`` of a finished recording, or None."""
    path = Path(out) / DONE
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") == "done" else None


def track_recording(job: Job, report=lambda n: None) -> dict:
    """Track one recording as ``markerpose track`` would, reconstruct its sweep where asked,
    then write ``batch.json``. Returns its summary row (:data:`SUMMARY_COLUMNS`)."""
    from .video import open_stereo, track_stream, track_tools_stream

    rec, out = job.recording, Path(job.out)
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    tracker = job.make_tracker(rec.rig)
    stream = open_stereo(rec.left, rec.right, job.fps)
    csv_path, jsonl = out / "poses.csv", (out / "poses.jsonl" if job.jsonl else None)
    sinks = (lambda *frame: report(1),)  # each frame tracked counts into the run's progress
    if job.tools:
        s = track_tools_stream(
            tracker, stream, csv_path, jsonl, progress=False, reference=job.reference, sinks=sinks, right_delay=job.right_delay
        )
        found = tracked = None
    else:
        s = track_stream(tracker, stream, csv_path, jsonl, progress=False, sinks=sinks, right_delay=job.right_delay)
        found, tracked = s["found"], s["tracked"]
    if s["stopped"]:
        raise RuntimeError("stopped before its last frame")
    outputs = [csv_path.name] + ([jsonl.name] if jsonl else [])
    if job.probe is not None and rec.us is not None:
        from .ultrasound.recording import reconstruct_recording

        reconstruct_recording(csv_path, rec.us, job.probe, out / "reconstruction", time_offset_s=job.time_offset_s, progress=False)
        outputs.append("reconstruction/")
    row = {
        "recording": rec.name,
        "status": "done",
        "frames": s["frames"],
        "found": found,
        "tracked": tracked,
        "frames_per_s": s["fps"],
        "seconds": time.perf_counter() - t0,
        "outputs": " ".join(outputs),
        "reason": "",
    }
    record = {**row, "version": __version__, "recording_paths": asdict(rec)}
    if job.tools:
        record["tools"] = s["tools"]
    partial = out / (DONE + ".partial")
    partial.write_text(json.dumps(record, indent=1))
    partial.replace(out / DONE)
    return row


def run_batch(
    jobs: list[Job],
    *,
    force: bool = False,
    use_ray: bool | None = None,
    address: str | None = None,
    workers: int | None = None,
    max_retries: int = 3,
    progress: bool = True,
) -> list[dict]:
    """Every job's recording tracked (:func:`track_recording`), on Ray where it is installed;
    those already done skipped unless ``force``. Returns one summary row per job, in order:
    ``status`` done, skipped (done by an earlier run) or failed (with its reason)."""
    if use_ray is None:  # on Ray whenever it is there, even for one recording: a dead worker is retried
        use_ray = address is not None or ray_installed()
    rows: list[dict | None] = [None] * len(jobs)
    todo = []
    for i, job in enumerate(jobs):
        record = None if force else done_record(job.out)
        if record is not None:
            rows[i] = {k: record.get(k) for k in SUMMARY_COLUMNS} | {"status": "skipped", "reason": "done by an earlier run"}
        else:
            todo.append(i)
    bars = _bars(progress, len(todo))

    def arrived(k, result):
        i = todo[k]
        rows[i] = result if not isinstance(result, Failed) else _failed(jobs[i], result.reason)
        if bars:
            bars[0].update()
            bars[0].set_postfix(failed=sum(r is not None and r["status"] == "failed" for r in rows))

    def frames(total):
        if bars:
            bars[1].update(total - bars[1].n)

    try:
        run_tasks(
            track_recording,
            [jobs[i] for i in todo],
            use_ray=use_ray,
            address=address,
            workers=workers,
            max_retries=max_retries,
            on_result=arrived,
            on_progress=frames,
        )
    finally:
        for bar in bars:
            bar.close()
    return rows


def _bars(progress: bool, n: int) -> list:
    if not progress or n == 0:
        return []
    from tqdm import tqdm

    return [tqdm(total=n, desc="recordings", unit="rec", position=0), tqdm(desc="frames", unit="pair", position=1)]


def _failed(job: Job, reason: str) -> dict:
    return dict.fromkeys(SUMMARY_COLUMNS) | {"recording": job.recording.name, "status": "failed", "reason": reason}


def write_summary(rows: list[dict], out_dir) -> tuple[Path, Path]:
    """The run's table as ``summary.csv`` and ``summary.md`` in ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out_dir / "summary.csv", out_dir / "summary.md"
    with open(csv_path.with_name(csv_path.name + ".partial"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
        w.writeheader()
        w.writerows({k: _cell(r.get(k)) for k in SUMMARY_COLUMNS} for r in rows)
    os.replace(csv_path.with_name(csv_path.name + ".partial"), csv_path)
    t = totals(rows)
    lines = [
        f"# markerpose batch ({__version__})",
        "",
        f"{t['recordings']} recordings: {t['done']} tracked now, {t['skipped']} done before, {t['failed']} failed; "
        f"{t['frames']} frames tracked now, the marker found in {_pct(t['found'])} of them.",
        "",
        "| " + " | ".join(SUMMARY_COLUMNS) + " |",
        "|" + "---|" * len(SUMMARY_COLUMNS),
    ]
    shown = [{**r, "found": _pct(r.get("found")), "tracked": _pct(r.get("tracked"))} for r in rows]
    lines += ["| " + " | ".join(_cell(r.get(k)).replace("|", "/") for k in SUMMARY_COLUMNS) + " |" for r in shown]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


def totals(rows: list[dict]) -> dict:
    """Recordings by status, the frames tracked in this run and the share with the marker."""
    now = [r for r in rows if r["status"] == "done"]
    frames = sum(r["frames"] for r in now)
    with_share = [r for r in now if r["found"] is not None]
    n = sum(r["frames"] for r in with_share)
    return {
        "recordings": len(rows),
        "done": len(now),
        "skipped": sum(r["status"] == "skipped" for r in rows),
        "failed": sum(r["status"] == "failed" for r in rows),
        "frames": frames,
        "found": sum(r["found"] * r["frames"] for r in with_share) / n if n else None,
    }


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


__all__ = ["Job", "Recording", "done_record", "find_recordings", "recording_at", "run_batch", "totals", "track_recording", "write_summary"]
