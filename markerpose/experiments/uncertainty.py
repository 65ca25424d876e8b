"""Is ``Estimate.cov`` calibrated? Held-out rendered pairs per condition: the share of
poses whose true error's Mahalanobis distance under the covariance is inside the
chi-square 95 % bound (6-D pose: 12.59; translation alone: 7.81), which a calibrated
covariance puts near 95 %; and the centres' scatter beyond their fits' covariances on
pairs of their own (what :data:`markerpose.uncertainty.MODEL_PX` stands for).

    markerpose eval uncertainty [--pairs 60] [--out DIR]
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..blurfit import MODEL_PX_PER_BLUR_PX
from ..camera import StereoRig
from ..formats import write_report
from ..marker import Marker
from ..pipeline import MarkerPose
from ..uncertainty import MODEL_PX
from .endtoend import random_pairs

CHI2_95 = {6: 12.59, 3: 7.81, 2: 5.99}

CONDITIONS = {
    "standard": {"seed": 3501, "alpha": (0.25, 1.0), "blur": (0.0, 9.0)},
    "dark (alpha 0.0625)": {"seed": 3502, "alpha": 0.0625, "blur": (0.0, 9.0)},
    "blur 15 px": {"seed": 3503, "alpha": (0.25, 1.0), "blur": 15.0},
    "far (0.8-1.2 m)": {"seed": 3504, "alpha": (0.25, 1.0), "blur": (0.0, 9.0), "distance": (800.0, 1200.0)},
}

default_conf = {"pairs": 60, "preset": "default", "model_pairs": 60}


def pose_error(T_true: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """(6,) the error in ``Estimate.cov``'s terms: translation true - estimated (mm) and
    the rotation vector of ``R_true @ R_est.T`` (rad), both in the left-camera frame."""
    w = cv2.Rodrigues(T_true[:3, :3] @ T_est[:3, :3].T)[0].ravel()
    return np.r_[T_true[:3, 3] - T_est[:3, 3], w]


def mahalanobis2(x: np.ndarray, cov: np.ndarray) -> float:
    return float(x @ np.linalg.solve(cov, x))


def condition(tracker: MarkerPose, spec: dict, n: int, rig: StereoRig, marker: Marker, progress: bool = False, desc: str = "") -> dict:
    """The calibration figures of ``n`` pairs drawn from ``spec``."""
    d6, d3, d2, sd, err = [], [], [], [], []
    found = no_cov = 0
    for frame, _ in tqdm(random_pairs(spec, n, rig, marker), total=n, desc=desc, unit="pair", disable=not progress):
        est = tracker.estimate(*frame.images)
        if est is None:
            continue
        found += 1
        if est.cov is None:
            no_cov += 1
            continue
        x = pose_error(frame.T_left_marker, est.T)
        d6.append(mahalanobis2(x, est.cov))
        d3.append(mahalanobis2(x[:3], est.cov[:3, :3]))
        sd.append(est.sd_mm)
        err.append(float(np.linalg.norm(x[:3])))
        for v in range(2):
            e = est.detections[v].centers - frame.views[v].outer_centers
            for k in range(3):
                C = est.detections[v].center_cov[k] + MODEL_PX**2 * np.eye(2)
                d2.append(mahalanobis2(e[k], C))
    share = lambda d, k: float(np.mean(np.array(d) < CHI2_95[k])) if d else float("nan")  # noqa: E731
    return {
        "pairs": n,
        "found": found,
        "without_cov": no_cov,
        "inside_95_6d": share(d6, 6),
        "inside_95_3d": share(d3, 3),
        "inside_95_centres_2d": share(d2, 2),
        "median_d2_6d": float(np.median(d6)) if d6 else float("nan"),
        "median_sd_mm": float(np.median(sd)) if sd else float("nan"),
        "rms_error_mm": float(np.sqrt(np.mean(np.square(err)))) if err else float("nan"),
        "rms_predicted_mm": float(np.sqrt(np.mean(np.square(sd)))) if sd else float("nan"),
    }


def model_error(tracker: MarkerPose, n: int, rig: StereoRig, marker: Marker) -> dict:
    """What :data:`~markerpose.uncertainty.MODEL_PX` stands for: the ring centres' scatter
    beyond what their own fits' covariances explain, per axis, px, on pairs of the standard
    conditions drawn with a seed of their own (not the held-out pairs above)."""
    e, var = [], []
    for frame, _ in random_pairs({"seed": 3510, "alpha": (0.25, 1.0), "blur": (0.0, 9.0)}, n, rig, marker):
        est = tracker.estimate(*frame.images)
        if est is None:
            continue
        for v in range(2):
            e.append(est.detections[v].centers - frame.views[v].outer_centers)
            var.append(np.trace(est.detections[v].center_cov, axis1=1, axis2=2) / 2)
    if not e:
        return {
            "centres": 0,
            "rms_per_axis_px": float("nan"),
            "fits_per_axis_px": float("nan"),
            "excess_px": float("nan"),
            "model_px": MODEL_PX,
        }
    e, var = np.concatenate(e), np.concatenate(var)
    ms, fit = float(np.mean(e**2)), float(np.mean(var))
    # The blurred-ring fit's centres (views it ran on), on 15 px-blurred pairs of their own seed:
    # their scatter beyond what the fit's own s^2 H^-1 says (without its MODEL_PX).
    be, bvar, blur = [], [], []
    for frame, _ in random_pairs({"seed": 3511, "alpha": (0.25, 1.0), "blur": 15.0}, n, rig, marker):
        est = tracker.estimate(*frame.images)
        for det, view in zip(est.detections if est is not None else (), frame.views):
            if det.blur_px > 0 and det.center_cov is not None:
                be.append(det.centers - view.outer_centers)
                bvar.append(np.trace(det.center_cov, axis1=1, axis2=2) / 2 - (MODEL_PX_PER_BLUR_PX * det.blur_px) ** 2)
                blur.append(det.blur_px)
    bms = float(np.mean(np.concatenate(be) ** 2)) if be else float("nan")
    bfit = float(np.mean(np.concatenate(bvar))) if bvar else float("nan")
    return {
        "centres": len(e),
        "rms_per_axis_px": float(np.sqrt(ms)),
        "fits_per_axis_px": float(np.sqrt(fit)),
        "excess_px": float(np.sqrt(max(ms - fit, 0.0))),
        "model_px": MODEL_PX,
        "blur_centres": 3 * len(be),
        "blur_rms_per_axis_px": float(np.sqrt(bms)),
        "blur_fit_per_axis_px": float(np.sqrt(bfit)),
        "blur_excess_px": float(np.sqrt(max(bms - bfit, 0.0))) if bvar else float("nan"),
        "blur_length_px": float(np.median(blur)) if blur else float("nan"),
        "blur_model_px_per_px": MODEL_PX_PER_BLUR_PX,
    }


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    c = {**default_conf, **(conf or {})}
    rig, marker = StereoRig.default(), Marker()
    tracker = MarkerPose(rig, marker, preset=c["preset"])
    res = {"conf": c, "conditions": {}}
    for name, spec in CONDITIONS.items():
        res["conditions"][name] = condition(tracker, spec, int(c["pairs"]), rig, marker, progress, name)
    if c["model_pairs"]:
        res["model_error"] = model_error(tracker, int(c["model_pairs"]), rig, marker)
    if out is not None:
        write_report(out, res, report(res))
    return res


def report(res: dict) -> str:
    lines = [
        "| condition | pairs | found | inside χ² 95 %: pose (6-D) | translation (3-D) | centres (2-D) | "
        "RMS error / RMS predicted sd (mm) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in res["conditions"].items():
        lines.append(
            f"| {name} | {r['pairs']} | {r['found']} | {100 * r['inside_95_6d']:.1f} % | {100 * r['inside_95_3d']:.1f} % | "
            f"{100 * r['inside_95_centres_2d']:.1f} % | {r['rms_error_mm']:.4f} / {r['rms_predicted_mm']:.4f} |"
        )
    m = res.get("model_error")
    if m:
        lines += [
            "",
            f"Ring centres of {m['centres']} views of the standard conditions (a seed of their own): RMS error "
            f"{m['rms_per_axis_px']:.4f} px per axis, their fits' covariances explain {m['fits_per_axis_px']:.4f} px, the excess is "
            f"{m['excess_px']:.4f} px; the covariance adds MODEL_PX = {m['model_px']:g} px.",
        ]
        if m.get("blur_centres"):
            lines.append(
                f"The blurred-ring fit's {m['blur_centres']} centres on 15 px-blurred pairs (a seed of their own): RMS error "
                f"{m['blur_rms_per_axis_px']:.4f} px per axis, the fit's own s² H⁻¹ explains {m['blur_fit_per_axis_px']:.4f} px, "
                f"the excess is {m['blur_excess_px']:.4f} px at a median blur of {m['blur_length_px']:.1f} px; the covariance adds "
                f"blurfit.MODEL_PX_PER_BLUR_PX = {m['blur_model_px_per_px']:g} px per px of blur."
            )
    return "\n".join(lines)


__all__ = ["CONDITIONS", "condition", "main", "mahalanobis2", "model_error", "pose_error", "report"]
