"""A live 3D view of the tracking in rerun (``markerpose track ... --rerun``; the rerun extra).

What it shows, on the timelines ``frame`` and ``time`` (the stream's seconds):

- ``world``: the left camera's frame, mm. The two cameras (``world/left``,
  ``world/right``: their pinhole models, placed by the rig's extrinsics), each with its
  image and the detected ring centres drawn on it (``.../image/rings``).
- ``world/tools/<name>``: each tool's pose (its axes), and ``world/trails/<name>``: the
  path of its origin over the last ``trail`` frames. A frame without the tool clears its
  pose (no stale axes) and logs why on ``log``.
- ``plots/<name>/sd_mm`` and ``plots/<name>/residual_px``: how far to trust each pose, over time.

``--rerun`` opens the viewer (rerun's own, spawned), ``--rerun-save FILE.rrd`` writes a
recording that ``rerun FILE.rrd`` opens later. Images are logged every ``image_every``-th
frame, as two 1280 x 1024 images a frame weigh more than the rest together.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np


def _rerun():
    try:
        import rerun as rr
    except ImportError as exc:
        raise ValueError('--rerun needs rerun-sdk: pip install -e ".[rerun]"') from exc
    return rr


class RerunSink:
    """A sink of :func:`markerpose.video.track_stream` / ``track_tools_stream``
    (``sink(k, t, left, right, est)``) that logs the scene to rerun (see the module's docstring).

    Args:
        rig: the stereo rig (the cameras drawn).
        save: write the recording to this .rrd file instead of opening the viewer.
        image_every: log the images every this many frames (0: never).
        trail: frames of each tool's path kept.
        name: the tool's name when ``est`` is one Estimate (one marker).
    """

    def __init__(self, rig, save: str | Path | None = None, image_every: int = 1, trail: int = 120, name: str = "marker"):
        rr = self.rr = _rerun()
        if save is not None and Path(save).suffix != ".rrd":
            raise ValueError(f"--rerun-save {save}: a rerun recording is a .rrd file")
        self.rec = rr.RecordingStream("markerpose")
        if save is not None:
            self.rec.save(str(save))
        else:
            self.rec.spawn()
        self.rig, self.image_every, self.name = rig, int(image_every), name
        self.trails: dict[str, deque] = {}
        self.trail = int(trail)
        self._log_rig()

    def _log_rig(self) -> None:
        rr, rec = self.rr, self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)  # the cameras' own convention
        T_left_right = np.linalg.inv(self.rig.T_right_left)
        for side, cam, T in (("left", self.rig.left, np.eye(4)), ("right", self.rig.right, T_left_right)):
            rec.log(f"world/{side}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            rec.log(f"world/{side}/image", rr.Pinhole(image_from_camera=cam.K, resolution=list(cam.image_size)), static=True)

    def __call__(self, k: int, t: float, left, right, est) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(k))
        rec.set_time("time", duration=float(t))
        found = est if isinstance(est, dict) else ({} if est is None else {self.name: est})
        if self.image_every and k % self.image_every == 0:
            for side, img in (("left", left), ("right", right)):
                rec.log(f"world/{side}/image", rr.Image(img))
        for side in (0, 1):
            pts = [e.centers[side] for e in found.values()]
            rec.log(f"world/{('left', 'right')[side]}/image/rings", rr.Points2D(np.concatenate(pts) if pts else np.zeros((0, 2)), radii=4))
        names = set(self.trails) | set(found)
        for name in sorted(names):
            trail = self.trails.setdefault(name, deque(maxlen=self.trail))
            e = found.get(name)
            if e is None:
                rec.log(f"world/tools/{name}", rr.Clear(recursive=True))
                rec.log("log", rr.TextLog(f"{name}: not found", level=rr.TextLogLevel.WARN))
                continue
            T = e.T
            rec.log(f"world/tools/{name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), rr.TransformAxes3D(30.0))
            trail.append(T[:3, 3].copy())
            rec.log(f"world/trails/{name}", rr.LineStrips3D([np.array(trail)]))
            sd = e.sd_mm
            if np.isfinite(sd):
                rec.log(f"plots/{name}/sd_mm", rr.Scalars(sd))
            rec.log(f"plots/{name}/residual_px", rr.Scalars(float(e.residual_px)))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


__all__ = ["RerunSink"]
