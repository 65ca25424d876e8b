"""Stereo streams in, poses out: two image folders, two video files or two cameras.

:func:`open_stereo` pairs the frames of two sources; :func:`track_stream` runs
:meth:`markerpose.MarkerPose.track` over them and writes one CSV row a frame (the
pose ``T_left_marker`` as a translation, a quaternion (x, y, z, w), a rotation vector
and the 16 matrix entries; empty pose fields when the marker is not found). The CSV is
written to ``NAME.partial`` and renamed when the stream ends or is stopped with Ctrl-C,
so a file under the final name always holds every frame that was read.

With several tools (:meth:`markerpose.MarkerPose.track_all`), :func:`track_tools_stream`
writes the CSV in long form, one row a frame and tool (:data:`TOOLS_CSV_HEADER`): each
tool's pose in the left camera's frame, or, given a reference tool, every other tool's
pose in the reference's frame (T_reference_tool) as seen in the same pair.
"""

from __future__ import annotations

import contextlib
import csv
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
CSV_HEADER = (
    ["frame", "timestamp_s", "timestamp_unix", "valid", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw", "rx", "ry", "rz"]
    + [f"T{i}{j}" for i in range(4) for j in range(4)]
    + ["residual_px", "sd_mm", "sd_deg", "status"]
)
# Long form, one row a frame and tool: which tool, and the frame its pose is in ("camera":
# T_left_tool, as CSV_HEADER's; else the reference tool's name: T_reference_tool).
TOOLS_CSV_HEADER = CSV_HEADER[:3] + ["tool", "relative_to"] + CSV_HEADER[3:]
# Where a tool has a tip (a pointer's, ``Marker.tip``): its position in the pose's frame and
# its RMS 3D standard deviation, after the columns above.
TIP_COLUMNS = ["tip_x_mm", "tip_y_mm", "tip_z_mm", "tip_sd_mm"]
CAMERA = "camera"
REFERENCE_NOT_SEEN = "reference not seen"


class _Folder:
    def __init__(self, path: Path):
        self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise ValueError(f"{path}: no image files ({', '.join(IMAGE_SUFFIXES)})")
        self.name, self.count, self.fps = str(path), len(self.files), None

    def frames(self) -> Iterator[tuple[float | None, np.ndarray]]:
        from .images import read_image

        for p in self.files:
            yield None, read_image(p)

    def close(self):
        pass


class _Capture:
    def __init__(self, source: str | int):
        # OpenCV prints a warning per backend it tries; our own error names the source.
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        self.name = f"camera {source}" if isinstance(source, int) else str(source)
        if isinstance(source, int) and not 0 <= source < 2**31:
            raise ValueError(f"cannot open {self.name}: a camera index is a small whole number (0, 1, ...)")
        try:
            self.cap = cv2.VideoCapture(source)
        except (cv2.error, OverflowError, TypeError) as exc:
            raise ValueError(f"cannot open {self.name}: {exc}") from None
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not self.cap.isOpened():
            raise ValueError(f"cannot open {self.name}")
        n = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.count = n if n > 0 and not isinstance(source, int) else None
        fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and fps > 0 else None
        self.live = isinstance(source, int)

    def frames(self) -> Iterator[tuple[float | None, np.ndarray]]:
        t0 = time.perf_counter()
        n = 0
        while True:
            ok, img = self.cap.read()
            if not ok:
                # A file that ends well before the length its header gives is truncated or
                # damaged: said, not taken as the end (a header's count may be off by a frame).
                if self.count is not None and n < self.count - max(1.0, 0.02 * self.count):
                    raise ValueError(f"{self.name}: no frame can be read after frame {n} of {self.count} (truncated or damaged)")
                return
            n += 1
            if self.live:
                yield time.perf_counter() - t0, img
            else:
                ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
                yield (ms / 1000.0 if ms > 0 else None), img

    def close(self):
        self.cap.release()


def _source(spec: str):
    """An image folder, a video file or a camera index (a whole number)."""
    if str(spec).isdigit():
        return _Capture(int(spec))
    path = Path(spec)
    if path.is_dir():
        return _Folder(path)
    if path.is_file():
        return _Capture(str(path))
    raise ValueError(f"{spec}: no such file, folder or camera index")


class StereoStream:
    """Two sources read in step: ``for k, timestamp_s, left, right in stream``.

    ``count`` is the number of pairs when known (folders, video files), else None.
    ``start_unix`` is the wall-clock time (seconds since the epoch) of ``timestamp_s`` 0,
    set when the iteration starts: :meth:`unix` gives each frame's. Two cameras are
    grabbed as a pair (both ``grab()``, then both ``retrieve()``), each frame stamped at
    its grab; ``grab_offsets`` keeps each pair's right-minus-left grab time (s). USB
    cameras are not synchronised: the offset is a lower bound on how far apart the two
    exposures are. With ``realtime``, folders and videos are replayed at their frame
    rate (frame k handed over at its timestamp from the start), not as fast as read.
    """

    def __init__(self, left: str, right: str, fps: float | None = None, realtime: bool = False):
        self.left = _source(left)
        try:
            self.right = _source(right)
        except ValueError:
            self.left.close()
            raise
        if self.left.count is not None and self.right.count is not None and self.left.count != self.right.count:
            self.close()
            raise ValueError(
                f"the two sources differ in length: {self.left.name} has {self.left.count} frames, {self.right.name} {self.right.count}"
            )
        self.count = self.left.count if self.left.count is not None else self.right.count
        # Timestamps: a video's own, a camera's clock, else frame / fps (image folders).
        self.fps = self.left.fps or self.right.fps or fps
        self.live = getattr(self.left, "live", False)
        self.realtime = bool(realtime) and not self.live
        self.start_unix: float | None = None
        self.grab_offsets: list[float] = []
        self.right_t: float | None = None  # the last pair's right view's time on the stream's clock (its grab, for cameras)
        self.cameras = self.live and getattr(self.right, "live", False)  # two cameras, grabbed as a pair

    def unix(self, t: float) -> float | None:
        """The wall-clock time (seconds since the epoch) of stream time ``t``."""
        return None if self.start_unix is None else self.start_unix + t

    def __iter__(self):
        t0, self.start_unix = time.perf_counter(), time.time()
        pair = self.cameras
        frames = self._grabbed(t0) if pair else zip(self.left.frames(), self.right.frames())
        paced = None  # the replay's clock starts with its first frame, once read
        for k, ((tl, a), (tr, b)) in enumerate(frames):
            t = tl if tl is not None else (k / self.fps if self.fps else float(k))
            self.right_t = tr if pair else t
            if self.realtime:
                paced = time.perf_counter() - t if paced is None else paced
                wait = paced + t - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            yield k, t, a, b

    def _grabbed(self, t0: float):
        """Frames of two cameras, grabbed together then decoded, stamped at their grabs."""
        while True:
            ok_l = self.left.cap.grab()
            tl = time.perf_counter()
            ok_r = self.right.cap.grab()
            tr = time.perf_counter()
            if not (ok_l and ok_r):
                return
            (ok_l, a), (ok_r, b) = self.left.cap.retrieve(), self.right.cap.retrieve()
            if not (ok_l and ok_r):
                return
            self.grab_offsets.append(tr - tl)
            yield (tl - t0, a), (tr - t0, b)

    def close(self):
        self.left.close()
        self.right.close()


def open_stereo(left: str, right: str, fps: float | None = 60.0, realtime: bool = False) -> StereoStream:
    """The frames of two sources (folders of images sorted by name, video files, or camera
    indices), paired in order; ``ValueError`` naming the source that cannot be read.
    ``fps`` times image folders, which carry no timestamps of their own; ``realtime``
    replays folders and videos at their frame rate (:class:`StereoStream`)."""
    if fps is not None and not MIN_FPS <= fps <= MAX_FPS:
        raise ValueError(f"fps must be a frame rate between {MIN_FPS:g} and {MAX_FPS:g} frames/s, got {fps}")
    return StereoStream(left, right, fps, realtime)


MIN_FPS, MAX_FPS = 1e-3, 1e6  # frame rates that give finite, distinct timestamps


def check_output(path, what: str = "--out") -> Path:
    """``path`` if a file can be written there (its folder exists and is writable, it is not
    a folder itself), else a ValueError naming it: checked before a run, not after it."""
    import os

    path = Path(path)
    if path.is_dir() or not path.name:
        raise ValueError(f"{what} {path}: a folder; give a file name")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"{what} {path}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ValueError(f"{what} {path}: not writable here")
    return path


def read_track_csv(path, tool: str | None = None) -> tuple[np.ndarray, list, str]:
    """Times (s), poses (4 x 4, or None where not found) and the frame they are in
    (:data:`CAMERA` or a reference tool's name) of a ``markerpose track`` CSV: one
    marker's (:data:`CSV_HEADER`), or with several tools (:data:`TOOLS_CSV_HEADER`) the
    rows of ``tool`` (which may be left out when the file has one tool)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    need = ["timestamp_s", "valid"] + [f"T{i}{j}" for i in range(4) for j in range(4)]
    if not rows or any(k not in rows[0] for k in need):
        raise ValueError(f"{path}: not a markerpose track CSV (needs the columns timestamp_s, valid, T00 … T33)")
    frame = CAMERA
    if "tool" in rows[0]:
        names = list(dict.fromkeys(r["tool"] for r in rows))
        if tool is None and len(names) > 1:
            raise ValueError(f"{path}: poses of several tools ({', '.join(names)}): name one (--tool)")
        tool = names[0] if tool is None else tool
        rows = [r for r in rows if r["tool"] == tool]
        if not rows:
            raise ValueError(f"{path}: no rows of tool {tool!r} (tools: {', '.join(names)})")
        frame = rows[0].get("relative_to") or CAMERA
    elif tool is not None:
        raise ValueError(f"{path}: one marker's poses, no tool column; leave out the tool ({tool!r})")
    times, poses = [], []
    for k, r in enumerate(rows):
        try:
            times.append(float(r["timestamp_s"]))
            if r["valid"] not in ("1", "True", "true"):
                poses.append(None)
                continue
            T = np.array([float(r[f"T{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: row {k + 2} is not a complete pose row") from None
        from .geometry import POSE_ROTATION_TOL

        R = T[:3, :3]
        if not (np.all(np.isfinite(T)) and np.abs(R.T @ R - np.eye(3)).max() <= POSE_ROTATION_TOL and np.linalg.det(R) > 0):
            raise ValueError(f"{path}: row {k + 2}: T00 … T33 is not a rigid transform (its rotation part is not a rotation)")
        poses.append(T)
    return np.array(times), poses, frame


def _pose_cells(T, residual_px, cov=None, status: str = "") -> list:
    """``valid`` and the pose fields of :data:`CSV_HEADER` for the pose ``T`` (4, 4, mm)
    with covariance ``cov`` (6, 6; its standard deviations, empty without one) and
    ``status`` (:meth:`~markerpose.results.Estimate.status`), or valid 0 and empty fields
    when ``T`` is None."""
    if T is None:
        return [0] + [""] * (len(CSV_HEADER) - 4)
    from scipy.spatial.transform import Rotation

    from .geometry import nearest_rotation

    T = np.asarray(T)
    R = Rotation.from_matrix(nearest_rotation(T[:3, :3]))
    from .uncertainty import sd_deg, sd_mm

    vals = [*T[:3, 3], *R.as_quat(), *R.as_rotvec(), *T.ravel(), residual_px]
    sds = ["", ""] if cov is None else [f"{sd_mm(cov, T):.6g}", f"{sd_deg(cov):.6g}"]
    return [1, *(f"{v:.9g}" for v in vals), *sds, status]


def _tip_cells(T, cov, tip) -> list:
    """:data:`TIP_COLUMNS` of a tool with ``tip`` (marker frame, mm) at pose ``T`` (empty
    without a pose)."""
    if T is None or tip is None:
        return [""] * len(TIP_COLUMNS)
    from .uncertainty import sd_mm

    p = T[:3, :3] @ np.asarray(tip, np.float64) + T[:3, 3]
    sd = sd_mm(cov, T, tip)
    return [*(f"{v:.9g}" for v in p), "" if not np.isfinite(sd) else f"{sd:.6g}"]


def pose_row(k: int, t: float, est, tip=None, unix: float | None = None) -> list:
    """One CSV row (see :data:`CSV_HEADER`) for frame ``k`` at ``t`` seconds (``unix``: the
    same instant in seconds since the epoch, or None); with ``tip`` (the marker's, mm),
    :data:`TIP_COLUMNS` after it."""
    if tip is not None:
        return pose_row(k, t, est, unix=unix) + _tip_cells(None if est is None else est.T, None if est is None else est.cov, tip)
    if est is None:
        return [*_times(k, t, unix), *_pose_cells(None, None)]
    return [*_times(k, t, unix), *_pose_cells(est.T, est.residual_px, est.cov, _status(est))]


def _times(k: int, t: float, unix: float | None) -> list:
    return [k, f"{t:.6f}", "" if unix is None else f"{unix:.6f}"]


class ToolReport(NamedTuple):
    """What a frame reports of one tool.

    Attributes:
        name: the tool's name.
        relative_to: the frame ``T`` is in: :data:`CAMERA` (T_left_tool) or the reference
            tool's name (T_reference_tool).
        T: (4, 4) the pose reported, mm, or None (the tool, or its reference, not found).
        est: the tool's own :class:`~markerpose.results.Estimate` (left camera), or None.
        why: None when ``T`` is reported, else why not: the tracker's reason, or
            :data:`REFERENCE_NOT_SEEN`.
        cov: (6, 6) the covariance of ``T`` (:attr:`~markerpose.results.Estimate.cov`;
            relative to the reference, :func:`~markerpose.results.relative_covariances`), or None.
    """

    name: str
    relative_to: str
    T: np.ndarray | None
    est: object
    why: str | None
    cov: np.ndarray | None = None

    @property
    def valid(self) -> bool:
        return self.T is not None


def tool_reports(found: dict, names, reference: str | None = None, whys: dict | None = None) -> list[ToolReport]:
    """One :class:`ToolReport` per tool of ``names``, in that order, from ``found``
    (``{name: Estimate}`` of :meth:`markerpose.MarkerPose.track_all`; ``whys`` its
    tracker's ``whys``). With ``reference``, every other tool is reported relative to it
    (:func:`markerpose.results.relative_poses`), and not at all when the reference is not
    in ``found``; the reference itself in the camera's frame."""
    from .results import relative_covariances, relative_poses

    whys = whys or {}
    relative = relative_poses(found, reference) if reference is not None else {}
    covs = relative_covariances(found, reference) if reference is not None else {}
    out = []
    for name in names:
        est = found.get(name)
        missing = None if est is not None else whys.get(name, "not found")
        if reference is None or name == reference:
            out.append(ToolReport(name, CAMERA, None if est is None else est.T, est, missing, None if est is None else est.cov))
        else:
            T = relative.get(name)
            out.append(ToolReport(name, reference, T, est, missing or (None if T is not None else REFERENCE_NOT_SEEN), covs.get(name)))
    return out


def tools_row(k: int, t: float, report: ToolReport, tips: dict | None = None, unix: float | None = None) -> list:
    """One CSV row (see :data:`TOOLS_CSV_HEADER`) of one tool in frame ``k`` at ``t``
    seconds (``unix``: since the epoch, or None); the residual is the tool's own, also for a pose relative to the reference.
    With ``tips`` (``{name: tip or None}``, when any tool has one), :data:`TIP_COLUMNS`
    after it (in the pose's frame)."""
    residual = report.est.residual_px if report.valid else None
    row = [
        *_times(k, t, unix),
        report.name,
        report.relative_to,
        *_pose_cells(report.T, residual, report.cov if report.valid else None, _status(report.est) if report.valid else ""),
    ]
    if tips is not None:
        row += _tip_cells(report.T, report.cov, tips.get(report.name))
    return row


def _annotated(images, est, rig) -> np.ndarray:
    """Both views side by side with the axes drawn: of the estimate ``est``
    (:func:`~markerpose.viz.annotate_pair`), or of each tool of ``{name: Estimate}``
    (:func:`~markerpose.viz.annotate_tools`)."""
    from .viz import annotate_pair, annotate_tools

    return annotate_tools(images, est, rig) if isinstance(est, dict) else annotate_pair(images, est, rig)


# Video codecs by file suffix, best first: what browsers play where this OpenCV has it.
VIDEO_CODECS = {".webm": ("VP90", "VP80"), ".mp4": ("avc1", "mp4v"), ".avi": ("MJPG",), ".mkv": ("VP90", "MJPG")}
BROWSER_CODECS = ("VP90", "VP80", "avc1")


def _lost_mark(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` with ``text`` in red at its top left: a frame without a pose, marked."""
    cv2.putText(frame, text, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.4, (0, 0, 0), 6, cv2.LINE_AA)
    cv2.putText(frame, text, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.4, (0, 0, 255), 3, cv2.LINE_AA)
    return frame


class VideoSink:
    """Both views side by side with the marker's axes drawn, into a video file; with
    several tools (``est`` a ``{name: Estimate}``), each tool's axes and name. A frame
    without a pose (a tool missing) is marked in red. The codec follows the suffix:
    ``.webm`` VP9 (browsers play it), ``.mp4`` H.264 where this OpenCV has an encoder for it,
    else MPEG-4 Part 2 (players, not browsers: said once, ``notice``), ``.avi`` MJPEG.
    ``tools``: the tools' names, to mark the ones missing from a frame."""

    def __init__(self, path: str | Path, rig, fps: float, notice=None, tools=()):
        self.path, self.rig, self.fps, self.writer, self.tools = Path(path), rig, fps, None, list(tools)
        suffix = self.path.suffix.lower()
        if suffix not in VIDEO_CODECS:
            raise ValueError(f"--video {self.path}: a .webm (VP9, plays in browsers), .mp4 or .avi file")
        self.codec: str | None = None
        self.notice = notice

    def _open(self, w: int, h: int) -> None:
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # each codec tried is not a warning
        try:
            for codec in VIDEO_CODECS[self.path.suffix.lower()]:
                self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*codec), float(self.fps), (w, h))
                if self.writer.isOpened():
                    self.codec = codec
                    break
        finally:
            cv2.utils.logging.setLogLevel(level)
        if self.codec is None:
            raise ValueError(
                f"cannot write the video {self.path}: this OpenCV has none of {', '.join(VIDEO_CODECS[self.path.suffix.lower()])}"
            )
        if self.codec not in BROWSER_CODECS and self.path.suffix.lower() == ".mp4" and self.notice is not None:
            self.notice(
                f"{self.path}: MPEG-4 Part 2 (this OpenCV has no H.264 encoder); video players show it, browsers do not: use a .webm for VP9"
            )

    def __call__(self, k, t, left, right, est):
        frame = _annotated((left, right), est, self.rig)
        if est is None or (isinstance(est, dict) and not est):
            frame = _lost_mark(frame, "not found")
        elif isinstance(est, dict) and self.tools:
            missing = [n for n in self.tools if n not in est]
            if missing:
                frame = _lost_mark(frame, "not found: " + ", ".join(missing))
        if self.writer is None:
            h, w = frame.shape[:2]
            self._open(w, h)
        self.writer.write(frame)

    def close(self):
        if self.writer is not None:
            self.writer.release()


class ShowSink:
    """A live window with both views and the axes (OpenCV with GUI support and a display;
    several tools as :class:`VideoSink` draws them); q or Esc stops the stream like Ctrl-C."""

    def __init__(self, rig, name: str = "markerpose"):
        self.rig, self.name = rig, name
        try:
            cv2.namedWindow(name, cv2.WINDOW_NORMAL)
        except cv2.error as exc:
            raise ValueError("--show needs OpenCV with GUI support (opencv-python, not -headless) and a display") from exc

    def __call__(self, k, t, left, right, est):
        cv2.imshow(self.name, _annotated((left, right), est, self.rig))
        if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
            raise KeyboardInterrupt

    def close(self):
        cv2.destroyWindow(self.name)


def _json_row(k: int, t: float, est, unix: float | None = None) -> str:
    """Frame ``k``'s line of the JSON-lines output (time ``t``, since the epoch ``unix``,
    estimate ``est`` or None)."""
    return (
        json.dumps(
            {
                "frame": k,
                "timestamp_s": t,
                "timestamp_unix": unix,
                "valid": est is not None,
                "T_left_marker": None if est is None else est.T.tolist(),
                "residual_px": None if est is None else est.residual_px,
                "sd_mm": None if est is None else _finite(est.sd_mm),
                "sd_deg": None if est is None else _finite(est.sd_deg),
                "status": None if est is None else est.status(),
                "source": None if est is None else est.source,
            }
        )
        + "\n"
    )


def _status(est) -> str:
    """The pose's status (:meth:`~markerpose.results.Estimate.status`), "" for an object
    without one."""
    return est.status() if hasattr(est, "status") else ""


def _sd(cov, T) -> float:
    from .uncertainty import sd_mm

    return sd_mm(cov, T)


def _finite(x) -> float | None:
    """``x`` as a float, or None when there is none or it is not finite (strict JSON has no NaN)."""
    return None if x is None or not np.isfinite(x) else float(x)


def _json_tools_row(k: int, t: float, reports: list[ToolReport], unix: float | None = None) -> str:
    """Frame ``k``'s line of the JSON-lines output with several tools (time ``t``, since the epoch ``unix``)."""
    tools = {
        r.name: {
            "valid": r.valid,
            "relative_to": r.relative_to,
            "T": r.T.tolist() if r.valid else None,
            "residual_px": _finite(r.est.residual_px) if r.valid else None,
            "sd_mm": _finite(_sd(r.cov, r.T)) if r.valid else None,
            "status": r.est.status() if r.valid else None,
            "source": r.est.source if r.valid else None,
            "why": r.why,
        }
        for r in reports
    }
    return json.dumps({"frame": k, "timestamp_s": t, "timestamp_unix": unix, "tools": tools}, allow_nan=False) + "\n"


def _discard(f, partial: Path, fj, partial_jsonl: Path | None) -> None:
    """Close and delete the partial outputs (the CSV ``f`` at ``partial`` and, where there
    is one, the JSON lines ``fj`` at ``partial_jsonl``)."""
    f.close()
    partial.unlink(missing_ok=True)
    if partial_jsonl:
        fj.close()
        partial_jsonl.unlink(missing_ok=True)


class _Out:
    """A stream's open outputs, for the step of :func:`_run`: CSV rows (flushed each
    frame) and, where asked for, JSON lines."""

    def __init__(self, f, fj):
        self._f, self._w, self._fj = f, csv.writer(f), fj

    def rows(self, rows) -> None:
        for row in rows:
            self._w.writerow(row)
        self._f.flush()

    def line(self, text: str) -> None:
        if self._fj is not None:
            self._fj.write(text)


def _run(tracker, stream: StereoStream, out_csv: str | Path, jsonl, header: list, step, progress: bool) -> dict:
    """The loop of :func:`track_stream` and :func:`track_tools_stream`: ``step(k, t,
    left, right, out)`` handles each pair (``out``: :class:`_Out`) and returns the
    progress bar's counts. The CSV (``header`` first) and JSON lines are written to
    ``.partial`` files and renamed when the stream ends, Ctrl-C stops it or a later pair
    fails (the error then says where it stopped); deleted when the first pair fails.
    Returns frames, frames per second, stopped and csv."""
    out_csv = check_output(out_csv)
    if jsonl is not None:
        check_output(jsonl, "--jsonl")
    partial = out_csv.with_name(out_csv.name + ".partial")
    partial_jsonl = None if jsonl is None else Path(jsonl).with_name(Path(jsonl).name + ".partial")
    tracker.reset()
    n = 0
    stopped, failed = False, None
    t0 = time.perf_counter()
    bar = tqdm(total=stream.count, desc="track", unit="pair", disable=not progress)
    with open(partial, "w", newline="") as f, open(partial_jsonl, "w") if partial_jsonl else contextlib.nullcontext() as fj:
        out = _Out(f, fj)
        out.rows([header])
        try:
            for k, t, left, right in stream:
                counts = step(k, t, left, right, out)
                n += 1
                bar.update()
                bar.set_postfix(fps=f"{n / (time.perf_counter() - t0):.1f}", **counts)
        except KeyboardInterrupt:
            stopped = True
        except BaseException as exc:
            if n == 0:  # nothing tracked (e.g. images that do not match the rig): no file
                _discard(f, partial, fj, partial_jsonl)
                raise
            failed = exc  # the rows so far land under the requested names, then the error
        finally:
            bar.close()
            stream.close()
    partial.replace(out_csv)
    if partial_jsonl:
        partial_jsonl.replace(jsonl)
    if failed is not None:
        if isinstance(failed, ValueError):
            raise ValueError(f"{failed} (stopped there: the {n} pair{'s' if n != 1 else ''} before it are in {out_csv})") from failed
        raise failed
    seconds = time.perf_counter() - t0
    offsets = getattr(stream, "grab_offsets", None)
    return {
        "frames": n,
        "fps": n / seconds if seconds > 0 else 0.0,
        "stopped": stopped,
        "csv": str(out_csv),
        "grab_offset_ms": 1000 * float(np.median(offsets)) if offsets else None,  # two cameras: right minus left grab
    }


def _capture_times(stream: StereoStream, t: float, right_delay: float | None) -> tuple | None:
    """The pair's capture times for ``track(..., times=)``: the left view's ``t`` and the
    right view's (its grab, for two cameras) plus ``right_delay`` s; None for recordings
    without a delay."""
    if right_delay is None and not stream.cameras:
        return None
    return (t, (stream.right_t if stream.right_t is not None else t) + (right_delay or 0.0))


def track_stream(
    tracker,
    stream: StereoStream,
    out_csv: str | Path,
    jsonl: str | Path | None = None,
    progress: bool = True,
    send=None,
    sinks: tuple = (),
    right_delay: float | None = None,
) -> dict:
    """Track every pair of ``stream``; one CSV row a frame into ``out_csv`` (and, with
    ``jsonl``, one JSON object a frame; with ``send``, ``send(k, timestamp_unix, est)`` after each,
    e.g. a :class:`markerpose.igtl.IGTLSender`; each of ``sinks`` gets ``(k, t, left, right, est)``, e.g.
    a :class:`VideoSink` or :class:`ShowSink`). ``right_delay``: the right view's exposure after
    the left's, s (``markerpose sync`` measures it): each pose is then the marker's at the left
    view's time (:meth:`~markerpose.MarkerPose.track`'s ``times``). Returns the summary: frames,
    found share, tracked share, frames per second, longest run of frames without a pose."""
    c = {"n": 0, "found": 0, "tracked": 0, "gap": 0, "longest": 0}
    tip = tracker.marker.tip

    def step(k, t, left, right, out):
        est = tracker.track(left, right, times=_capture_times(stream, t, right_delay))
        unix = stream.unix(t)
        out.rows([pose_row(k, t, est, tip, unix)])
        if send is not None:
            send(k, unix, est)
        for sink in sinks:
            sink(k, t, left, right, est)
        out.line(_json_row(k, t, est, unix))
        c["n"] += 1
        c["found"] += est is not None
        c["tracked"] += est is not None and est.source == "tracked"
        c["gap"] = 0 if est is not None else c["gap"] + 1
        c["longest"] = max(c["longest"], c["gap"])
        return {"found": f"{c['found']}/{c['n']}"}

    run = _run(tracker, stream, out_csv, jsonl, CSV_HEADER + (TIP_COLUMNS if tip is not None else []), step, progress)
    n, found = run["frames"], c["found"]
    return {
        "frames": n,
        "found": found / n if n else 0.0,
        "tracked": c["tracked"] / found if found else 0.0,
        "fps": run["fps"],
        "longest_gap": c["longest"],
        "stopped": run["stopped"],
        "csv": run["csv"],
        "grab_offset_ms": run["grab_offset_ms"],
    }


def track_tools_stream(
    tracker,
    stream: StereoStream,
    out_csv: str | Path,
    jsonl: str | Path | None = None,
    progress: bool = True,
    reference: str | None = None,
    send=None,
    sinks: tuple = (),
    right_delay: float | None = None,
) -> dict:
    """Track every tool of ``tracker`` (a MarkerPose of several tools, ``markers=``)
    through ``stream`` with :meth:`~markerpose.MarkerPose.track_all`: one CSV row a frame
    and tool, in the order of ``tracker.tools`` (:data:`TOOLS_CSV_HEADER`, see
    :func:`tool_reports` for ``reference``); with ``jsonl``, one JSON object a frame
    (``{"frame", "timestamp_s", "tools": {name: {"valid", "relative_to", "T",
    "residual_px", "source", "why"}}}``); with ``send``, ``send(k, timestamp_unix, reports)`` after
    each (e.g. a :class:`markerpose.igtl.IGTLToolsSender`); each of ``sinks`` gets ``(k, t, left, right,
    found)``, ``found`` the ``{name: Estimate}`` in the camera's frame; ``right_delay`` as
    :func:`track_stream`'s. Outputs are written as :func:`track_stream` writes them.

    Returns:
        frames, frames per second, stopped, csv, reference, and ``tools``: per tool its
        found share, the tracked share of those found, the longest run of frames without
        it, and ``reported``: the share of frames with its pose written (for a tool
        relative to the reference: found together with the reference).
    """
    names = list(tracker.tools)
    if reference is not None and reference not in names:
        stream.close()
        raise ValueError(f"reference {reference!r} is none of the tools: {', '.join(names)}")
    c = {name: {"found": 0, "tracked": 0, "reported": 0, "gap": 0, "longest": 0} for name in names}
    tips = {name: p.marker.tip for name, p in tracker.tools.items()}
    tips = tips if any(v is not None for v in tips.values()) else None

    def step(k, t, left, right, out):
        found = tracker.track_all(left, right, times=_capture_times(stream, t, right_delay))
        reports = tool_reports(found, names, reference, tracker.whys)
        unix = stream.unix(t)
        out.rows([tools_row(k, t, r, tips, unix) for r in reports])
        if send is not None:
            send(k, unix, reports)
        for sink in sinks:
            sink(k, t, left, right, found)
        out.line(_json_tools_row(k, t, reports, unix))
        for r in reports:
            s = c[r.name]
            s["found"] += r.est is not None
            s["tracked"] += r.est is not None and r.est.source == "tracked"
            s["reported"] += r.valid
            s["gap"] = 0 if r.est is not None else s["gap"] + 1
            s["longest"] = max(s["longest"], s["gap"])
        return {"found": ",".join(str(c[n]["found"]) for n in names) + f"/{k + 1}"}

    run = _run(tracker, stream, out_csv, jsonl, TOOLS_CSV_HEADER + (TIP_COLUMNS if tips is not None else []), step, progress)
    n = run["frames"]
    tools = {
        name: {
            "found": s["found"] / n if n else 0.0,
            "tracked": s["tracked"] / s["found"] if s["found"] else 0.0,
            "reported": s["reported"] / n if n else 0.0,
            "longest_gap": s["longest"],
        }
        for name, s in c.items()
    }
    return {"frames": n, "tools": tools, "reference": reference, **run}


__all__ = [
    "CAMERA",
    "CSV_HEADER",
    "TIP_COLUMNS",
    "check_output",
    "read_track_csv",
    "REFERENCE_NOT_SEEN",
    "ShowSink",
    "StereoStream",
    "TOOLS_CSV_HEADER",
    "ToolReport",
    "VideoSink",
    "open_stereo",
    "pose_row",
    "tool_reports",
    "tools_row",
    "track_stream",
    "track_tools_stream",
]
