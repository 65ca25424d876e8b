"""The rig check on rendered sequences: a stable rig in several conditions (false alarms),
and a right camera turned or shifted part-way through (how soon it fires, and how wrong
the poses were meanwhile).

    markerpose eval rigcheck [--stable 200] [--before 10] [--after 30] [--out DIR]
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..camera import Camera, StereoRig
from ..formats import write_report
from ..marker import Marker
from ..pipeline import MarkerPose
from ..rigcheck import statistics
from ..synth import Imaging, look_at_pose, render_stereo

CONDITIONS = {
    "standard": {"alpha": (0.25, 1.0), "blur": (0.0, 9.0)},
    "dark (alpha 0.0625)": {"alpha": (0.0625, 0.0625), "blur": (0.0, 9.0)},
    "blur 15 px": {"alpha": (0.25, 1.0), "blur": (15.0, 15.0)},
}
CHANGES = [("turn", deg, axis) for deg in (0.02, 0.05, 0.1, 0.5) for axis in ("x", "y", "z")] + [("shift", px, "x") for px in (1.0, 3.0)]
default_conf = {"stable": 200, "before": 10, "after": 30, "seed": 3800}


def changed(rig: StereoRig, kind: str, size: float, axis: str) -> StereoRig:
    """The rig with its right camera turned by ``size`` degrees about its own ``axis``, or
    its image shifted by ``size`` px along ``axis`` (a principal point moved: refocused)."""
    if kind == "turn":
        v = {"x": (1.0, 0, 0), "y": (0, 1.0, 0), "z": (0, 0, 1.0)}[axis]
        Rd = cv2.Rodrigues(np.radians(size) * np.array(v))[0]
        return dataclasses.replace(rig, R=Rd @ rig.R, t=Rd @ rig.t)
    K = rig.right.K.copy()
    K[0 if axis == "x" else 1, 2] += size
    return dataclasses.replace(rig, right=Camera(K, rig.right.dist, rig.right.image_size))


def _pose(k: int, phase: float) -> np.ndarray:
    """A hand-held path around 560 mm: drifting, tilting and turning."""
    c = np.array([60 * np.sin(k / 23 + phase), 40 * np.cos(k / 31 + phase), 560 + 80 * np.sin(k / 41 + phase)])
    return look_at_pose(c, 25 + 15 * np.sin(k / 17 + phase), 40 * np.sin(k / 29) + 60, 3 * k + 30 * phase)


def _frame(rig, k, phase, spec, rng):
    alpha, blur = rng.uniform(*spec["alpha"]), rng.uniform(*spec["blur"])
    T = _pose(k, phase)
    return T, render_stereo(rig, T, Marker(), Imaging(alpha=alpha, motion_blur=blur, motion_angle=rng.uniform(0, 180)), seed=rng)


def stable(rig: StereoRig, n: int, spec: dict, rng, progress: bool, desc: str) -> dict:
    tracker = MarkerPose(rig)
    found, z, peak = 0, [], 0.0
    for k in tqdm(range(n), desc=desc, unit="pair", disable=not progress):
        _, f = _frame(rig, k, 0.0, spec, rng)
        est = tracker.track(*f.images)
        found += est is not None
        zz = None if est is None else statistics(rig, est, Marker().points3d, tracker.rig_check.conf)
        if zz is not None:
            z.append(zz)
        peak = max(peak, float(tracker.rig_check.sums.max()))
    z = np.array(z).reshape(-1, 2)
    return {
        "frames": n,
        "found": found,
        "fired": tracker.rig_check.fired is not None,
        "fired_at": tracker.rig_check.fired_at,
        "z_epipolar_mean_sd": [float(z[:, 0].mean()), float(z[:, 0].std())] if len(z) else None,
        "z_scale_mean_sd": [float(z[:, 1].mean()), float(z[:, 1].std())] if len(z) else None,
        "cusum_peak": peak,
    }


def bump(rig: StereoRig, change: tuple, before: int, after: int, rng) -> dict:
    """``before`` pairs with the rig as calibrated, then ``after`` with the right camera
    changed, all tracked with the calibrated rig: the pair the check fired at (counted from
    the change; None: not within ``after``) and the median pose error after the change."""
    tracker, moved = MarkerPose(rig), changed(rig, *change)
    errs, fired, refused = [], None, 0
    for k in range(before + after):
        T, f = _frame(rig if k < before else moved, k, 1.0, CONDITIONS["standard"], rng)
        est = tracker.track(*f.images)
        if est is None:
            refused += k >= before
            continue
        if k >= before:
            errs.append(float(np.linalg.norm(est.T[:3, 3] - T[:3, 3])))
            if fired is None and est.rig_warning is not None:
                fired = k - before
                break
        elif est.rig_warning is not None:
            return {"change": list(change), "fired_before": True, "fired_after": None, "error_mm": None, "no_pose": refused}
    return {
        "change": list(change),
        "fired_before": False,
        "fired_after": fired,
        "error_mm": float(np.median(errs)) if errs else None,
        "no_pose": refused,  # pairs after the change without a pose (the verification refused them)
    }


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    c = {**default_conf, **(conf or {})}
    rig = StereoRig.default()
    rng = np.random.default_rng(c["seed"])
    res = {"conf": c, "stable": {}, "changes": []}
    for name, spec in CONDITIONS.items():
        res["stable"][name] = stable(rig, int(c["stable"]), spec, rng, progress, name)
    for ch in tqdm(CHANGES, desc="changes", unit="run", disable=not progress):
        res["changes"].append(bump(rig, ch, int(c["before"]), int(c["after"]), rng))
    if out is not None:
        write_report(out, res, report(res))
    return res


def report(res: dict) -> str:
    c = res["conf"]
    lines = [
        "| stable rig: condition | pairs | tracked | rig check fired | z epipolar: mean, sd | z scale: mean, sd | CUSUM peak (fires at h) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in res["stable"].items():
        fired = "at pose " + str(r["fired_at"]) if r["fired"] else "no"
        ze, zs = r["z_epipolar_mean_sd"] or [np.nan] * 2, r["z_scale_mean_sd"] or [np.nan] * 2
        lines.append(
            f"| {name} | {r['frames']} | {r['found']} | {fired} | {ze[0]:+.2f}, {ze[1]:.2f} | {zs[0]:+.2f}, {zs[1]:.2f} | {r['cusum_peak']:.1f} |"
        )
    lines += [
        "",
        f"Right camera changed after {c['before']} pairs (standard conditions), then {c['after']} pairs tracked with the calibrated rig:",
        "",
        "| change | fired, pairs after the change | pairs without a pose meanwhile | pose error meanwhile, median (mm) |",
        "|---|---|---|---|",
    ]
    for r in res["changes"]:
        kind, size, axis = r["change"]
        what = f"turned {size:g}° about {axis}" if kind == "turn" else f"image shifted {size:g} px along {axis}"
        if r["fired_before"]:
            fired = "before the change (false alarm)"
        elif r["fired_after"] is None:
            fired = "never: no pose was given" if r["error_mm"] is None else "not within the run"
        else:
            fired = str(r["fired_after"])
        err = "-" if r["error_mm"] is None else f"{r['error_mm']:.3f}"
        lines.append(f"| {what} | {fired} | {r['no_pose']} | {err} |")
    return "\n".join(lines)


__all__ = ["CHANGES", "CONDITIONS", "bump", "changed", "main", "report", "stable"]
