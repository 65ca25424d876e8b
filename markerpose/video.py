"""Stereo streams in, poses out: two image folders, two video files or two cameras.

:func:`open_stereo` pairs the frames of two sources; :func:`track_stream` runs
:meth:`markerpose.MarkerPose.track` over them and writes one CSV row a frame (the
pose ``T_left_marker`` as a translation, a quaternion (x, y, z, w), a rotation vector
and the 16 matrix entries; empty pose fields when the marker is not found). The CSV is
written to ``NAME.partial`` and renamed when the stream ends or is stopped with Ctrl-C,
so a file under the final name always holds every frame that was read.
"""

from __future__ import annotations

import contextlib
import csv
import json
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
CSV_HEADER = (
    ["frame", "timestamp_s", "valid", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw", "rx", "ry", "rz"]
    + [f"T{i}{j}" for i in range(4) for j in range(4)]
    + ["residual_px"]
)


class _Folder:
    def __init__(self, path: Path):
        self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise ValueError(f"{path}: no image files ({', '.join(IMAGE_SUFFIXES)})")
        self.name, self.count, self.fps = str(path), len(self.files), None

    def frames(self) -> Iterator[tuple[float | None, np.ndarray]]:
        for p in self.files:
            img = cv2.imdecode(np.fromfile(p, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"cannot read image {p}")
            yield None, img

    def close(self):
        pass


class _Capture:
    def __init__(self, source: str | int):
        # OpenCV prints a warning per backend it tries; our own error names the source.
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            self.cap = cv2.VideoCapture(source)
        finally:
            cv2.utils.logging.setLogLevel(level)
        self.name = f"camera {source}" if isinstance(source, int) else str(source)
        if not self.cap.isOpened():
            raise ValueError(f"cannot open {self.name}")
        n = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.count = n if n > 0 and not isinstance(source, int) else None
        fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and fps > 0 else None
        self.live = isinstance(source, int)

    def frames(self) -> Iterator[tuple[float | None, np.ndarray]]:
        t0 = time.perf_counter()
        while True:
            ok, img = self.cap.read()
            if not ok:
                return
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
    """

    def __init__(self, left: str, right: str, fps: float | None = None):
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

    def __iter__(self):
        for k, ((tl, a), (_, b)) in enumerate(zip(self.left.frames(), self.right.frames())):
            t = tl if tl is not None else (k / self.fps if self.fps else float(k))
            yield k, t, a, b

    def close(self):
        self.left.close()
        self.right.close()


def open_stereo(left: str, right: str, fps: float | None = 60.0) -> StereoStream:
    """The frames of two sources (folders of images sorted by name, video files, or camera
    indices), paired in order; ``ValueError`` naming the source that cannot be read.
    ``fps`` times image folders, which carry no timestamps of their own."""
    if fps is not None and not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    return StereoStream(left, right, fps)


def pose_row(k: int, t: float, est) -> list:
    """One CSV row (see :data:`CSV_HEADER`) for frame ``k`` at ``t`` seconds."""
    if est is None:
        return [k, f"{t:.6f}", 0] + [""] * (len(CSV_HEADER) - 3)
    from scipy.spatial.transform import Rotation

    from .geometry import nearest_rotation

    R = Rotation.from_matrix(nearest_rotation(est.R))
    vals = [*est.t, *R.as_quat(), *R.as_rotvec(), *est.T.ravel(), est.residual_px]
    return [k, f"{t:.6f}", 1, *(f"{v:.9g}" for v in vals)]


class IGTLSender:
    """An OpenIGTLink server (``pyigtl``, the igtl extra) that sends each found pose as a
    TRANSFORM message named ``name`` (millimetres, T_left_marker, the frame's timestamp),
    so 3D Slicer's OpenIGTLinkIF module shows it live. Frames without a pose send
    nothing, and nothing is queued while no client is connected: a client that connects
    later gets the next pose, never a stale one.

    Args:
        port: TCP port (OpenIGTLink's default is 18944).
        name: the device name (e.g. "MarkerToTracker").
        local_only: listen on 127.0.0.1 only (False: the machine's network interface).
    """

    def __init__(self, port: int = 18944, name: str = "MarkerToTracker", local_only: bool = True):
        try:
            import pyigtl
        except ImportError as exc:
            raise ValueError('--igtl needs pyigtl: pip install -e ".[igtl]"') from exc
        self._pyigtl, self.name = pyigtl, name
        try:
            self.server = pyigtl.OpenIGTLinkServer(port=int(port), local_server=local_only)
        except OSError as exc:
            raise ValueError(f"cannot serve OpenIGTLink on port {port}: {exc.strerror or exc}") from exc
        self.sent = 0

    def __call__(self, k: int, t: float, est, wait: bool = False) -> bool:
        if est is None or not self.server.is_connected():
            return False
        msg = self._pyigtl.TransformMessage(np.asarray(est.T, np.float64), timestamp=float(t), device_name=self.name)
        self.server.send_message(msg, wait=wait)
        self.sent += 1
        return True

    def close(self):
        self.server.stop()


class VideoSink:
    """Both views side by side with the marker's axes drawn, into a video file (mp4v)."""

    def __init__(self, path: str | Path, rig, fps: float):
        self.path, self.rig, self.fps, self.writer = Path(path), rig, fps, None

    def __call__(self, k, t, left, right, est):
        from .viz import annotate_pair

        frame = annotate_pair((left, right), est, self.rig)
        if self.writer is None:
            h, w = frame.shape[:2]
            self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), float(self.fps), (w, h))
            if not self.writer.isOpened():
                raise ValueError(f"cannot write the video {self.path}")
        self.writer.write(frame)

    def close(self):
        if self.writer is not None:
            self.writer.release()


class ShowSink:
    """A live window with both views and the axes (OpenCV with GUI support and a display);
    q or Esc stops the stream like Ctrl-C."""

    def __init__(self, rig, name: str = "markerpose"):
        self.rig, self.name = rig, name
        try:
            cv2.namedWindow(name, cv2.WINDOW_NORMAL)
        except cv2.error as exc:
            raise ValueError("--show needs OpenCV with GUI support (opencv-python, not -headless) and a display") from exc

    def __call__(self, k, t, left, right, est):
        from .viz import annotate_pair

        cv2.imshow(self.name, annotate_pair((left, right), est, self.rig))
        if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
            raise KeyboardInterrupt

    def close(self):
        cv2.destroyWindow(self.name)


def _json_row(k: int, t: float, est) -> str:
    """Frame ``k``'s line of the JSON-lines output (time ``t``, estimate ``est`` or None)."""
    return (
        json.dumps(
            {
                "frame": k,
                "timestamp_s": t,
                "valid": est is not None,
                "T_left_marker": None if est is None else est.T.tolist(),
                "residual_px": None if est is None else est.residual_px,
                "source": None if est is None else est.source,
            }
        )
        + "\n"
    )


def _discard(f, partial: Path, fj, partial_jsonl: Path | None) -> None:
    """Close and delete the partial outputs (the CSV ``f`` at ``partial`` and, where there
    is one, the JSON lines ``fj`` at ``partial_jsonl``)."""
    f.close()
    partial.unlink(missing_ok=True)
    if partial_jsonl:
        fj.close()
        partial_jsonl.unlink(missing_ok=True)


def track_stream(
    tracker, stream: StereoStream, out_csv: str | Path, jsonl: str | Path | None = None, progress: bool = True, send=None, sinks: tuple = ()
) -> dict:
    """Track every pair of ``stream``; one CSV row a frame into ``out_csv`` (and, with
    ``jsonl``, one JSON object a frame; with ``send``, ``send(k, t, est)`` after each,
    e.g. an :class:`IGTLSender`; each of ``sinks`` gets ``(k, t, left, right, est)``, e.g.
    a :class:`VideoSink` or :class:`ShowSink`). Returns the summary: frames, found share, tracked
    share, frames per second, longest run of frames without a pose."""
    out_csv = Path(out_csv)
    partial = out_csv.with_name(out_csv.name + ".partial")
    partial_jsonl = None if jsonl is None else Path(jsonl).with_name(Path(jsonl).name + ".partial")
    tracker.reset()
    n = found = tracked = gap = longest = 0
    stopped = False
    t0 = time.perf_counter()
    bar = tqdm(total=stream.count, desc="track", unit="pair", disable=not progress)
    with open(partial, "w", newline="") as f, open(partial_jsonl, "w") if partial_jsonl else contextlib.nullcontext() as fj:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        try:
            for k, t, left, right in stream:
                est = tracker.track(left, right)
                w.writerow(pose_row(k, t, est))
                f.flush()
                if send is not None:
                    send(k, t, est)
                for sink in sinks:
                    sink(k, t, left, right, est)
                if partial_jsonl:
                    fj.write(_json_row(k, t, est))
                n += 1
                found += est is not None
                tracked += est is not None and est.source == "tracked"
                gap = 0 if est is not None else gap + 1
                longest = max(longest, gap)
                bar.update()
                bar.set_postfix(fps=f"{n / (time.perf_counter() - t0):.1f}", found=f"{found}/{n}")
        except KeyboardInterrupt:
            stopped = True
        except BaseException:
            if n == 0:  # nothing tracked (e.g. images that do not match the rig): no file
                _discard(f, partial, fj, partial_jsonl)
            raise
        finally:
            bar.close()
            stream.close()
    partial.replace(out_csv)
    if partial_jsonl:
        partial_jsonl.replace(jsonl)
    seconds = time.perf_counter() - t0
    return {
        "frames": n,
        "found": found / n if n else 0.0,
        "tracked": tracked / found if found else 0.0,
        "fps": n / seconds if seconds > 0 else 0.0,
        "longest_gap": longest,
        "stopped": stopped,
        "csv": str(out_csv),
    }


__all__ = ["CSV_HEADER", "IGTLSender", "ShowSink", "StereoStream", "VideoSink", "open_stereo", "pose_row", "track_stream"]
