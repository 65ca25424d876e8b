"""``markerpose eval sync``: cameras that are not synchronised, rendered.

A hand-held-like path of the paper's marker around 560 mm (up to ~100 mm/s and ~20°/s),
filmed at ``fps`` with the right view exposed ``delay`` ms after the left (0, 8, 16, 33 ms:
from a trigger cable to a whole frame at 30 frames/s). Each view is rendered at its own
time, with the motion blur of its own exposure (``exposure_ms``). The same frames are
tracked three ways: as today (the views taken as simultaneous), with the true capture
times (``track(left, right, times=...)``), and with the delay that ``markerpose sync``
estimates (from a run with its looser limits, :data:`markerpose.sync.LOOSE`). Errors are against the marker's pose at the left
view's time, over the frames after the first three (the compensation needs a previous pose).

    markerpose eval sync [--frames 90] [--out DIR]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_report
from ..geometry import nearest_rotation, rotation_angle
from ..marker import Marker
from ..pipeline import MarkerPose
from ..sync import LOOSE, estimate_delay
from ..synth import Imaging, clutter_background, look_at_pose
from ..synth.render import render_view

default_conf = {"frames": 90, "fps": 30.0, "delays_ms": [0.0, 8.0, 16.0, 33.0], "exposure_ms": 4.0, "seed": 4900}
SKIP = 3  # frames left out at the start: the compensation needs a previous pose


def pose(t: float) -> np.ndarray:
    """T_left_marker at time ``t`` (s): the hand-held path."""
    c = np.array(
        [
            -5 + 25 * np.sin(2 * np.pi * 0.5 * t),
            12 * np.sin(2 * np.pi * 0.7 * t + 1.0),
            560 + 15 * np.sin(2 * np.pi * 0.4 * t + 0.5),
        ]
    )
    return look_at_pose(
        c, 30 + 5 * np.sin(2 * np.pi * 0.3 * t), 45 + 10 * np.sin(2 * np.pi * 0.2 * t), 10 + 8 * np.sin(2 * np.pi * 0.5 * t)
    )


def _blur(cam, T_of, t: float, exposure: float, marker: Marker) -> tuple[float, float]:
    """(length px, angle °) of the image motion of the marker's centre over the exposure at ``t``."""
    X = marker.points3d.mean(0)
    a = cam.project((T_of(t)[:3, :3] @ X + T_of(t)[:3, 3])[None])[0]
    b = cam.project((T_of(t + exposure)[:3, :3] @ X + T_of(t + exposure)[:3, 3])[None])[0]
    d = b - a
    return float(np.hypot(*d)), float(np.degrees(np.arctan2(d[1], d[0])))


def render(rig: StereoRig, marker: Marker, conf: dict, delay: float, rng, progress: bool, backgrounds) -> list:
    """The frames (left, right images) with the right view at ``t + delay``."""
    frames = []
    exposure = conf["exposure_ms"] / 1000
    for k in tqdm(range(int(conf["frames"])), desc=f"render {1000 * delay:g} ms", unit="pair", disable=not progress):
        t = k / conf["fps"]
        images = []
        for view, (cam, tt, bg) in enumerate(zip(rig.cameras, (t, t + delay), backgrounds)):

            def T_of(s, view=view):
                return pose(s) if view == 0 else rig.T_right_left @ pose(s)

            L, ang = _blur(cam, T_of, tt, exposure, marker)
            img, _ = render_view(cam, T_of(tt), marker, Imaging(alpha=0.8, motion_blur=L, motion_angle=ang), bg, rng)
            images.append(img)
        frames.append((t, images))
    return frames


def _errors(tracker: MarkerPose, frames: list, times_of) -> tuple[np.ndarray, np.ndarray, list]:
    """Translation (mm) and rotation (°) errors per frame (NaN where not found) and the
    estimates, tracking with ``times_of(t)`` (None: as simultaneous)."""
    tracker.reset()
    te, re, ests = [], [], []
    for t, (left, right) in frames:
        est = tracker.track(left, right, times=times_of(t))
        ests.append(est)
        if est is None:
            te.append(np.nan)
            re.append(np.nan)
            continue
        T = pose(t)
        te.append(float(np.linalg.norm(est.T[:3, 3] - T[:3, 3])))
        re.append(float(np.degrees(rotation_angle(nearest_rotation(est.T[:3, :3]), T[:3, :3]))))
    return np.array(te), np.array(re), ests


def _stats(te: np.ndarray) -> dict:
    e = te[SKIP:]
    f = e[np.isfinite(e)]
    return {
        "found": int(len(f)),
        "frames": int(len(e)),
        "median_mm": float(np.median(f)) if len(f) else None,
        "p95_mm": float(np.percentile(f, 95)) if len(f) else None,
    }


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    c = {**default_conf, **(conf or {})}
    rig, marker = StereoRig.default(), Marker()
    rng = np.random.default_rng(c["seed"])
    bgs = tuple(clutter_background(cam.image_size, rng) for cam in rig.cameras)
    tracker, loose = MarkerPose(rig), MarkerPose(rig, **LOOSE)
    speeds = []
    for k in range(1, int(c["frames"])):
        t0, t1 = (k - 1) / c["fps"], k / c["fps"]
        speeds.append(np.linalg.norm(pose(t1)[:3, 3] - pose(t0)[:3, 3]) * c["fps"])
    res = {"conf": c, "speed_mm_s": {"median": float(np.median(speeds)), "max": float(np.max(speeds))}, "delays": []}
    for delay_ms in c["delays_ms"]:
        d = delay_ms / 1000
        frames = render(rig, marker, c, d, rng, progress, bgs)
        raw, raw_r, _ = _errors(tracker, frames, lambda t: None)
        comp, comp_r, _ = _errors(tracker, frames, lambda t, d=d: (t, t + d))
        _, _, ests = _errors(loose, frames, lambda t: None)  # what markerpose sync tracks the recording with
        nan = np.full((3, 2), np.nan)
        lefts = np.array([e.detections[0].centers if e is not None else nan for e in ests])
        rights = np.array([e.detections[1].centers if e is not None else nan for e in ests])
        times = np.array([t for t, _ in frames])
        found = estimate_delay(rig, marker, times, lefts, rights, max_delay=2 / c["fps"])
        est_d = found["delay_s"]
        sync_e, _, _ = _errors(tracker, frames, lambda t, e=est_d: (t, t + e))
        res["delays"].append(
            {
                "delay_ms": delay_ms,
                "uncompensated": _stats(raw),
                "compensated": _stats(comp),
                "with_estimated_delay": _stats(sync_e),
                "rotation_deg_median": {
                    "uncompensated": float(np.nanmedian(raw_r[SKIP:])),
                    "compensated": float(np.nanmedian(comp_r[SKIP:])),
                },
                "estimated_delay_ms": 1000 * est_d,
                "estimated_sd_ms": 1000 * found["sd_s"],
                "estimate": found,
            }
        )
    if out is not None:
        write_report(out, res, report(res))
    return res


def _f(x, nd=4):
    return "–" if x is None else f"{x:.{nd}f}"


def report(res: dict) -> str:
    c = res["conf"]
    lines = [
        "# Unsynchronised cameras: the right view exposed after the left",
        "",
        f"A hand-held path around 560 mm ({c['frames']} frames at {c['fps']:g} frames/s; the marker's origin moving "
        f"{res['speed_mm_s']['median']:.0f} mm/s at the median, {res['speed_mm_s']['max']:.0f} mm/s at most), each view rendered "
        f"at its own time with the blur of a {c['exposure_ms']:g} ms exposure. Translation error of the marker's origin against its "
        f"pose at the left view's time, frames {SKIP + 1}–{c['frames']} (median / p95, mm), tracked as simultaneous (what "
        "`track()` gives without times), with the true capture times (`times=(t, t + delay)`), and with the delay "
        "`markerpose sync` estimated (from a run with its looser limits).",
        "",
        "| right view after the left | as simultaneous | compensated (true delay) | compensated (estimated delay) | "
        "delay estimated by sync (± sd) | pairs found (of frames) |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["delays"]:
        u, k, s = r["uncompensated"], r["compensated"], r["with_estimated_delay"]
        lines.append(
            f"| {r['delay_ms']:g} ms | {_f(u['median_mm'])} / {_f(u['p95_mm'])} | {_f(k['median_mm'])} / {_f(k['p95_mm'])} | "
            f"{_f(s['median_mm'])} / {_f(s['p95_mm'])} | {r['estimated_delay_ms']:.2f} ± {r['estimated_sd_ms']:.2f} ms | "
            f"{u['found']}, {k['found']}, {s['found']} of {u['frames']} |"
        )
    base = res["delays"][0]["uncompensated"]["median_mm"]
    worst = res["delays"][-1]
    lines += [
        "",
        f"With the true delay, the {worst['delay_ms']:g} ms error is "
        f"{worst['compensated']['median_mm'] / base:.2f}× the synchronised one at the median "
        f"({worst['compensated']['p95_mm'] / res['delays'][0]['uncompensated']['p95_mm']:.2f}× at the p95; target ≤ 1.5×); "
        f"uncompensated it is {worst['uncompensated']['median_mm'] / base:.0f}×.",
        "",
    ]
    return "\n".join(lines)


__all__ = ["default_conf", "main", "pose", "report"]
