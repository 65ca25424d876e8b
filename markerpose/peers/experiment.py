"""``markerpose peers``: markerpose and the fiducials people already use, on the same frames.

Every scene is one plate pose, one lighting, one motion blur, one pair of cluttered
backgrounds and one noise seed; each system's target is printed on the same plate
(:mod:`.targets`) and rendered into that scene by the same renderer, then measured by
its own detector (:mod:`.systems`), mono (left view) and stereo.

Scenes:

- **levels**: ``pairs`` random plate poses per darkness α (down to 0.039) and per
  motion-blur length (px, random direction), anywhere in the working volume
  (350–800 mm, tilt 0–60°, any roll), the whole plate in both views;
- **jitter**: ``jitter_poses`` static poses, each rendered ``jitter_repeats`` times
  with fresh sensor noise (same background);
- **marker-free**: ``marker_free`` pairs of clutter with ring distractors.

A pose counts as a detection when the plate centre is within ``tolerance_mm`` and the
rotation within ``tolerance_deg`` of the truth; any other pose is a wrong pose, and a
wrong mono pose whose other IPPE solution is within tolerance is a flip (the planar
ambiguity). Errors are measured at the plate centre, the same point for every system.
"""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import numpy as np

from ..camera import StereoRig
from ..engine import run_tasks
from ..formats import write_json
from ..geometry import nearest_rotation, rotation_angle
from ..synth import Imaging, look_at_pose, render_target_view
from ..synth.background import clutter_background
from . import systems, targets

default_conf = {
    "pairs": 40,  # random scenes per darkness / blur level
    "alphas": (1.0, 0.5, 0.25, 0.125, 0.0625, 0.039),
    "blurs": (5.0, 10.0, 15.0, 20.0, 25.0),  # px
    "jitter_poses": 4,
    "jitter_repeats": 10,
    "marker_free": 40,
    "tolerance_mm": 5.0,
    "tolerance_deg": 5.0,
    "systems": systems.SYSTEMS,
    "tuned": True,  # also every peer's further settings (systems.TUNED), for the best per condition
    "seed": 0,
}
QUICK = {"pairs": 6, "jitter_poses": 2, "jitter_repeats": 5, "marker_free": 8}


# --- scenes ----------------------------------------------------------------------------
def _plate_visible(rig: StereoRig, T: np.ndarray, margin_px: float = 5.0) -> bool:
    x0, y0, x1, y1 = targets.PLATE
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    for cam, Tc in zip(rig.cameras, (T, rig.T_right_left @ T)):
        P = corners @ Tc[:3, :3].T + Tc[:3, 3]
        if np.any(P[:, 2] <= 0):
            return False
        uv = cam.project(P)
        w, h = cam.image_size
        if np.any(uv < margin_px) or np.any(uv[:, 0] > w - 1 - margin_px) or np.any(uv[:, 1] > h - 1 - margin_px):
            return False
    return True


def random_pose(rng: np.random.Generator, rig: StereoRig, distance=(350.0, 800.0), tilt=(0.0, 60.0)) -> tuple[np.ndarray, dict]:
    """A plate pose in the working volume with the whole plate in both views, and its
    conditions (distance of the plate centre, tilt)."""
    while True:
        z = rng.uniform(*distance)
        t = rng.uniform(*tilt)
        T = look_at_pose([0, 0, z], t, rng.uniform(0, 360), rng.uniform(0, 360))
        T[:3, 3] = [rng.uniform(-0.1, 0.1) * z - 0.12 * (z - 560), rng.uniform(-0.15, 0.15) * z, z]
        T[:3, 3] -= T[:3, :3] @ targets.CENTRE  # the plate centre at the sampled point
        if _plate_visible(rig, T):
            return T, {"distance": float(z), "tilt": float(t)}


def scenes(conf: dict, rig: StereoRig) -> list[dict]:
    """Every scene of the experiment, deterministic in ``conf["seed"]``."""
    out = []
    levels = [("alpha", a, a, 0.0) for a in conf["alphas"]] + [("blur", b, 1.0, b) for b in conf["blurs"]]
    for k, (kind, value, alpha, blur) in enumerate(levels):
        rng = np.random.default_rng([conf["seed"], 31, k])
        for i in range(conf["pairs"]):
            T, cond = random_pose(rng, rig)
            out.append(
                {
                    "kind": kind,
                    "level": float(value),
                    "T": T,
                    "alpha": alpha,
                    "blur": blur,
                    "angle": float(rng.uniform(0, 180)),
                    "seed": [conf["seed"], 32, k, i],
                    **cond,
                }
            )
    rng = np.random.default_rng([conf["seed"], 33])
    for p in range(conf["jitter_poses"]):
        T, cond = random_pose(rng, rig, distance=(450.0, 600.0), tilt=(15.0, 40.0))
        for r in range(conf["jitter_repeats"]):
            # The same background (bg_seed) every repeat; fresh sensor noise (seed).
            out.append(
                {
                    "kind": "jitter",
                    "level": float(p),
                    "T": T,
                    "alpha": 1.0,
                    "blur": 0.0,
                    "angle": 0.0,
                    "bg_seed": [conf["seed"], 34, p],
                    "seed": [conf["seed"], 35, p, r],
                    **cond,
                }
            )
    for i in range(conf["marker_free"]):
        out.append({"kind": "free", "level": 0.0, "T": None, "alpha": 1.0, "blur": 0.0, "angle": 0.0, "seed": [conf["seed"], 36, i]})
    return out


# --- one scene, every system -------------------------------------------------------------
_SYSTEMS: dict = {}


def measured(conf: dict) -> tuple:
    """The systems a run measures: ``conf["systems"]`` and, with ``conf["tuned"]``, the
    further settings (:data:`systems.TUNED`) of the peers among them."""
    extra = tuple(n for n in systems.TUNED if conf.get("tuned") and systems.SETTINGS[n][0] in conf["systems"])
    return tuple(conf["systems"]) + extra


def _systems(names, rig) -> dict:
    """The systems of this process, made once."""
    for n in names:
        if n not in _SYSTEMS:
            _SYSTEMS[n] = systems.make(n, rig)
    return {n: _SYSTEMS[n] for n in names}


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(plate-centre position error mm, rotation error deg)."""
    c = targets.CENTRE
    dt = np.linalg.norm((T_est[:3, :3] - T_true[:3, :3]) @ c + T_est[:3, 3] - T_true[:3, 3])
    return float(dt), float(np.rad2deg(rotation_angle(T_est[:3, :3], T_true[:3, :3])))


def _render(rig: StereoRig, scene: dict, target) -> tuple:
    im = Imaging(alpha=scene["alpha"], motion_blur=scene["blur"], motion_angle=scene["angle"])
    bg_rng = np.random.default_rng(scene.get("bg_seed", scene["seed"]))
    if scene["kind"] == "free":
        bgs = [clutter_background(c.image_size, bg_rng, ring_distractors=int(bg_rng.integers(3, 11))) for c in rig.cameras]
        T = np.eye(4)
        T[:3, 3] = [0.0, 3000.0, 1000.0]  # far outside both views
    else:
        bgs = [clutter_background(c.image_size, bg_rng) for c in rig.cameras]
        T = scene["T"]
    noise = np.random.default_rng(scene["seed"] + [1])
    return tuple(render_target_view(cam, Tc, target, im, bg, noise) for cam, Tc, bg in zip(rig.cameras, (T, rig.T_right_left @ T), bgs))


def run_scene(scene: dict, names, rig: StereoRig) -> dict:
    """Render ``scene`` for every system and measure it: {system: {"mono": ..., "stereo": ...}}.
    The settings of one peer see the same images (its target rendered once)."""
    out: dict = {}
    rendered: dict = {}
    for name, s in _systems(names, rig).items():
        key = "all" if scene["kind"] == "free" else systems.SETTINGS.get(name, (name,))[0]  # marker-free: one pair for everyone
        if key not in rendered:
            rendered[key] = _render(rig, scene, s.target)
        out[name] = measure(s, rig, rendered[key], scene)
    return out


def measure(s, rig: StereoRig, images, scene: dict) -> dict:
    """One system on one rendered pair: its mono and stereo results."""
    T_true = scene["T"]
    res = {}
    if s.name == "markerpose":
        T, dt = systems.timed(s.estimate, *images)
        res["stereo"] = _judge([] if T is None else [T], T_true, dt)
        res["mono"] = None
        if scene["kind"] == "free":
            res["false_views"] = int(sum(s.tracker.detect(im, view=k) is not None for k, im in enumerate(images)))
        return res
    left, t_left = systems.timed(s.observe, images[0])
    right, t_right = systems.timed(s.observe, images[1])
    poses, t_pnp = systems.timed(s.mono_poses, rig.left, left)
    res["mono"] = _judge(poses, T_true, t_left + t_pnp)
    T, t_tri = systems.timed(s.stereo_pose, rig, left, right)
    res["stereo"] = _judge([] if T is None else [T], T_true, t_left + t_right + t_tri)
    if scene["kind"] == "free":
        res["false_views"] = int(sum(o is not None and not o.wrong_id for o in (left, right)))
    return res


def _judge(poses: list, T_true, seconds: float) -> dict:
    """A pose (the first of ``poses``; the others are its alternatives) against the truth."""
    out = {"seconds": seconds, "pose": bool(poses)}
    if poses and T_true is not None:
        errs = [_errors(T, T_true) for T in poses]
        out["t_err"], out["r_err"] = errs[0]
        out["alt"] = [list(e) for e in errs[1:]]
        out["T"] = poses[0].tolist()
    return out


def _worker(args, report=None):
    import cv2

    cv2.setNumThreads(1)  # one core per worker: the workers already fill the machine
    scene, names = args
    return scene, run_scene(scene, names, _rig())


_RIG: list = []


def _rig() -> StereoRig:
    """This process's rig, loaded once."""
    if not _RIG:
        _RIG.append(StereoRig.default())
    return _RIG[0]


def run(conf: dict, jobs: int | None = None, progress: bool = True) -> list[tuple[dict, dict]]:
    """Every scene of ``conf`` on Ray's ``jobs`` workers where it is installed (one after the
    other where not, or with ``jobs`` 1): [(scene, {system: result})]."""
    tasks = [(sc, measured(conf)) for sc in scenes(conf, _rig())]
    out = run_tasks(_worker, tasks, workers=jobs, desc="scenes", unit="scene", progress=progress, strict=True)
    return sorted(out, key=lambda r: (r[0]["kind"], r[0]["level"], r[0]["seed"]))


# --- statistics ------------------------------------------------------------------------------
def _ok(r: dict | None, conf: dict) -> bool:
    return bool(r and r["pose"] and r["t_err"] <= conf["tolerance_mm"] and r["r_err"] <= conf["tolerance_deg"])


def _flip(r: dict | None, conf: dict) -> bool:
    """A wrong pose whose other IPPE solution is right: the planar ambiguity."""
    return bool(
        r and r["pose"] and not _ok(r, conf) and any(t <= conf["tolerance_mm"] and a <= conf["tolerance_deg"] for t, a in r.get("alt", []))
    )


def _pct(values, q) -> float | None:
    v = np.asarray(values, float)
    return float(np.percentile(v, q)) if len(v) else None


def level_stats(rows: list[dict], conf: dict) -> dict:
    """Detection, wrong poses, flips and the errors of the detections over ``rows``
    (one mode of one system on the scenes of one level)."""
    from ..experiments.reproduce import wilson

    good = [r for r in rows if _ok(r, conf)]
    return {
        "n": len(rows),
        "detection": wilson(len(good), len(rows)),
        "wrong": int(sum(bool(r["pose"]) and not _ok(r, conf) for r in rows)),
        "flips": int(sum(_flip(r, conf) for r in rows)),
        "t_err_median_mm": _pct([r["t_err"] for r in good], 50),
        "t_err_p95_mm": _pct([r["t_err"] for r in good], 95),
        "r_err_median_deg": _pct([r["r_err"] for r in good], 50),
        "r_err_p95_deg": _pct([r["r_err"] for r in good], 95),
        "seconds_median": _pct([r["seconds"] for r in rows], 50),
    }


def jitter_stats(groups: list[list[dict]], conf: dict) -> dict:
    """Pooled RMS spread of the plate centre (mm) and of the rotation (deg) over repeated
    renders of each static pose (only poses found within tolerance count)."""
    d_pos, d_rot, found, total = [], [], 0, 0
    for rows in groups:
        total += len(rows)
        Ts = [np.asarray(r["T"]) for r in rows if _ok(r, conf)]
        found += len(Ts)
        if len(Ts) < 2:
            continue
        c = np.stack([T[:3, :3] @ targets.CENTRE + T[:3, 3] for T in Ts])
        d_pos.extend(np.sum((c - c.mean(0)) ** 2, axis=1))
        R_mean = nearest_rotation(np.mean([T[:3, :3] for T in Ts], axis=0))
        d_rot.extend(np.rad2deg(rotation_angle(T[:3, :3], R_mean)) ** 2 for T in Ts)
    return {
        "position_mm": float(np.sqrt(np.mean(d_pos))) if d_pos else None,
        "rotation_deg": float(np.sqrt(np.mean(d_rot))) if d_rot else None,
        "found": found,
        "renders": total,
    }


def _bins(rows: list[tuple[dict, dict]], key: str, edges, conf: dict) -> list[dict]:
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = [r for sc, r in rows if lo <= sc[key] < hi and _ok(r, conf)]
        out.append(
            {
                "lo": lo,
                "hi": hi,
                "n": len(sel),
                "t_err_median_mm": _pct([r["t_err"] for r in sel], 50),
                "r_err_median_deg": _pct([r["r_err"] for r in sel], 50),
            }
        )
    return out


DISTANCE_BINS = (350.0, 462.5, 575.0, 687.5, 800.01)
TILT_BINS = (0.0, 15.0, 30.0, 45.0, 60.01)


def summarize(results: list[tuple[dict, dict]], conf: dict) -> dict:
    """Per system and mode: every level's statistics, jitter, false detections, errors by
    distance and tilt (α = 1 level), and the headline figures."""
    out = {}
    names = [n for n in measured(conf) if results and n in results[0][1]]
    for name in names:
        entry: dict = {"label": systems.LABELS[name]}
        for mode in ("mono", "stereo"):
            if name == "markerpose" and mode == "mono":
                entry[mode] = None
                continue
            m: dict = {"alpha": {}, "blur": {}}
            for kind in ("alpha", "blur"):
                for lv in sorted({sc["level"] for sc, _ in results if sc["kind"] == kind}):
                    rows = [r[name][mode] for sc, r in results if sc["kind"] == kind and sc["level"] == lv]
                    m[kind][str(lv)] = level_stats(rows, conf)
            if "1.0" in m["alpha"]:
                m["blur"] = {"0.0": m["alpha"]["1.0"], **m["blur"]}
            std = [(sc, r[name][mode]) for sc, r in results if sc["kind"] == "alpha" and sc["level"] == 1.0]
            m["by_distance"] = _bins(std, "distance", DISTANCE_BINS, conf)
            m["by_tilt"] = _bins(std, "tilt", TILT_BINS, conf)
            every = [r[name][mode] for sc, r in results if sc["kind"] in ("alpha", "blur")]
            m["all_levels"] = level_stats(every, conf)
            groups = [
                [r[name][mode] for sc, r in results if sc["kind"] == "jitter" and sc["level"] == p]
                for p in sorted({sc["level"] for sc, _ in results if sc["kind"] == "jitter"})
            ]
            m["jitter"] = jitter_stats(groups, conf)
            free = [r[name] for sc, r in results if sc["kind"] == "free"]
            m["false_poses"] = {"k": int(sum(bool(f[mode]["pose"]) for f in free)), "n": len(free)}
            entry[mode] = m
        free = [r[name] for sc, r in results if sc["kind"] == "free"]
        entry["false_views"] = {"k": int(sum(f["false_views"] for f in free)), "n": 2 * len(free)}
        out[name] = entry
    return out


# --- report ----------------------------------------------------------------------------------
# The headline metrics: (label, getter, lower is better).
HEADLINES = (
    ("position error, median (standard), mm", lambda m: m["alpha"]["1.0"]["t_err_median_mm"], True),
    ("rotation error, median (standard), °", lambda m: m["alpha"]["1.0"]["r_err_median_deg"], True),
    ("static jitter, position RMS, mm", lambda m: m["jitter"]["position_mm"], True),
    ("static jitter, rotation RMS, °", lambda m: m["jitter"]["rotation_deg"], True),
    ("detection at the darkest level", lambda m: m["alpha"][max(m["alpha"], key=lambda a: -float(a))]["detection"]["p"], False),
    ("detection at the longest blur", lambda m: m["blur"][max(m["blur"], key=float)]["detection"]["p"], False),
    ("wrong poses, every level", lambda m: m["all_levels"]["wrong"], True),
    ("time per frame (standard), ms", lambda m: 1e3 * m["alpha"]["1.0"]["seconds_median"], True),
)


def comparison(summary: dict) -> list[dict]:
    """markerpose against the best peer (any mode) on each headline metric."""
    if "markerpose" not in summary or not summary["markerpose"].get("stereo"):
        return []
    ours = summary["markerpose"]["stereo"]
    out = []
    for label, get, lower in HEADLINES:
        peers = [(get(m), name, mode) for name, mode, m in _rows(summary) if name != "markerpose" and get(m) is not None]
        if not peers:
            continue
        v, name, mode = (min if lower else max)(peers, key=lambda p: p[0])
        out.append({"metric": label, "markerpose": get(ours), "best_peer": name, "mode": mode, "peer": v, "lower_is_better": lower})
    return out


def best_settings(summary: dict) -> dict:
    """Per peer and mode, each darkness and blur level's best of the peer's settings (the
    most detections, then the smaller median error): {peer: {mode: {kind: {level:
    {"system", "detection", "t_err_median_mm"}}}}}. Tuned per condition: an upper bound
    for a user who knows the condition in advance."""
    out: dict = {}
    for peer in dict.fromkeys(systems.SETTINGS[n][0] for n in summary if n in systems.SETTINGS):
        names = [n for n in summary if systems.SETTINGS.get(n, ("",))[0] == peer]
        for mode in ("mono", "stereo"):
            levels: dict = {}
            for kind in ("alpha", "blur"):
                for lv in summary[names[0]][mode][kind]:
                    ranked = [
                        (-summary[n][mode][kind][lv]["detection"]["p"], _inf(summary[n][mode][kind][lv]["t_err_median_mm"]), n)
                        for n in names
                    ]
                    _, _, best = min(ranked)
                    st = summary[best][mode][kind][lv]
                    levels.setdefault(kind, {})[lv] = {
                        "system": best,
                        "detection": st["detection"]["p"],
                        "t_err_median_mm": st["t_err_median_mm"],
                    }
            out.setdefault(peer, {})[mode] = levels
    return out


def _inf(x) -> float:
    return math.inf if x is None else x


def _f(x, nd=3) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def _det(s: dict) -> str:
    d = s["detection"]
    return "—" if not d["n"] else f"{100 * d['p']:.1f} %"


def _rows(summary: dict):
    """(system, mode, stats) for every measured mode, markerpose first."""
    for name, e in summary.items():
        for mode in ("stereo", "mono"):
            if e.get(mode):
                yield name, mode, e[mode]


def setup_lines(conf: dict) -> list[str]:
    x0, y0, x1, y1 = targets.PLATE
    im = Imaging()
    return [
        f"- **Printed footprint**: every target is printed on the three-ring marker's plate, {x1 - x0:g} × {y1 - y0:g} mm. "
        f"markerpose: three rings Ø20 mm. AprilTag tag36h11 (ID 0), ArUco `DICT_4X4_50` (ID 0) and STag HD21 (ID 0): a "
        f"{targets.SQUARE_MM:g} mm black square centred on the plate. ChArUco: {targets.CHARUCO_SQUARES[0]} × "
        f"{targets.CHARUCO_SQUARES[1]} squares of {targets.CHARUCO_SQUARE_MM:g} mm ({targets.CHARUCO_SQUARES[0] * targets.CHARUCO_SQUARE_MM:g} × "
        f"{targets.CHARUCO_SQUARES[1] * targets.CHARUCO_SQUARE_MM:g} mm), `DICT_4X4_50` markers of {targets.CHARUCO_MARKER_MM:g} mm, "
        f"{(targets.CHARUCO_SQUARES[0] - 1) * (targets.CHARUCO_SQUARES[1] - 1)} inner corners.",
        "- **Scenes**: the default rig (two 1280×1024 cameras, f ≈ 2500 px, 175 mm baseline, mild barrel distortion), "
        "the plate anywhere both cameras see all of it from 350 to 800 mm, tilt 0–60°, any roll, over cluttered "
        f"backgrounds; the renderer and sensor model of every markerpose experiment (PSF σ = {im.psf_sigma} px, "
        f"shot and read noise, 8 bits). Darkness α scales the exposure; motion blur is a line kernel in a random direction. "
        "Every system sees the same pose, lighting, blur, backgrounds and noise seed.",
        "- **Settings**: each peer twice where its library has settings: at the library's defaults (rows 'library "
        "defaults') and at its documented settings for accuracy; in these tables none is tuned per condition (the last "
        "section adds each peer's further settings and its best per condition). AprilTag "
        "`pupil_apriltags.Detector(families='tag36h11', quad_decimate=1.0, quad_sigma=0.0, refine_edges=1, "
        "decode_sharpening=0.25, nthreads=1)` (full-resolution quads), defaults `quad_decimate=2.0` (the rest the same), its "
        "corners moved by −0.5 px into OpenCV's pixel-centre convention; ArUco `cv2.aruco.ArucoDetector` with "
        "`CORNER_REFINE_SUBPIX` (the most accurate of OpenCV's three refinements on these images), defaults: no "
        "refinement; ChArUco `cv2.aruco.CharucoDetector` (same marker refinement, or none; the detector refines the "
        "chessboard corners), at least 4 corners for a pose; STag `stag.detectMarkers(image, 21)` (its own "
        "ellipse-based corner refinement; error correction at its maximum, the default); markerpose `MarkerPose(rig, preset='default', "
        "threads=1).estimate`. OpenCV one thread per process.",
        "- **Mono** (as the peers' users run them): OpenCV's IPPE from the left view with the full lens model "
        "(`SOLVEPNP_IPPE_SQUARE` for a square tag, `SOLVEPNP_IPPE` for the ChArUco corners), the better solution. "
        "**Stereo**: the points found in both views triangulated with the rig and the rigid fit markerpose uses. "
        "markerpose is stereo only.",
        f"- **Counting**: a pose is a detection when the plate centre is within {conf['tolerance_mm']:g} mm and the "
        f"rotation within {conf['tolerance_deg']:g}° of the truth; any other pose is a wrong pose; a wrong mono pose whose "
        "other IPPE solution is right is a flip. Errors are those of the detections, at the plate centre (the same point "
        "for every system). Jitter: each static pose rendered again with fresh sensor noise; pooled RMS about each pose's "
        "mean. Time: one view (mono) or one pair (stereo), detection plus pose, median over every scene, measured in "
        "the run (two worker processes on two cores, one thread each).",
    ]


def best_markdown(best: dict, conf: dict) -> list[str]:
    """The report's section on each peer at its best setting per condition."""
    if not best:
        return []
    alphas, blurs = [str(float(a)) for a in conf["alphas"]], ["0.0"] + [str(float(b)) for b in conf["blurs"]]
    L = [
        "",
        "## Each peer at its best setting for each condition (tuned per condition)",
        "",
        "Every peer was also run at the further settings its documentation suggests for hard images (below); here, for "
        "each level, the best of each peer's settings (most detections, then the smaller median error), named. This "
        "is tuned per condition: a user gets it only by knowing the condition in advance and switching settings.",
        "",
        "| setting | what it is |",
        "|---|---|",
    ]
    for name, (peer, _, what) in systems.SETTINGS.items():
        if peer in best:
            L.append(f"| `{name}` | {what} |")
    for kind, vals, title in (("alpha", alphas, "darkness α"), ("blur", blurs, "motion blur (px)")):
        L += ["", f"Detection versus {title}, the best setting per level:", ""]
        L += ["| peer | mode | " + " | ".join(f"{float(v):g}" for v in vals) + " |", "|---|---|" + "---|" * len(vals)]
        for peer, modes in best.items():
            for mode in ("stereo", "mono"):
                cells = []
                for v in vals:
                    b = modes[mode][kind].get(v)
                    cells.append("—" if b is None else f"{100 * b['detection']:.1f} % ({_short(b['system'])})")
                L.append(f"| {systems.LABELS[peer].split(',')[0]} | {mode} | " + " | ".join(cells) + " |")
    return L


def _short(name: str) -> str:
    """A setting's name in the best-per-condition tables: the part after the peer's name;
    the peer's own name is its setting for accuracy (STag's: its defaults)."""
    peer = systems.SETTINGS[name][0]
    return name.removeprefix(peer).lstrip("-") or ("defaults" if peer == "stag" else "accuracy")


def report_markdown(summary: dict, conf: dict, command: str, seconds: float, skipped: dict) -> str:
    best = best_settings(summary)
    summary = {n: e for n, e in summary.items() if n not in systems.TUNED}
    n_lv = conf["pairs"]
    alphas, blurs = [str(float(a)) for a in conf["alphas"]], [str(float(b)) for b in conf["blurs"]]
    darkest, longest = alphas[-1], blurs[-1] if blurs else None
    L = [
        "# markerpose and the fiducials people already use, on the same frames",
        "",
        f"Command: `{command}` ({seconds / 60:.1f} min on this machine). Every figure below comes from this run "
        "(`results.json` holds every value).",
        "",
        *setup_lines(conf),
        "",
    ]
    if skipped:
        L += [f"Not installed, skipped: {', '.join(f'{k} (`pip install {v}`)' for k, v in skipped.items())}.", ""]
    L += [
        "## Summary",
        "",
        f"Detection per level over {n_lv} scenes (standard: α = 1, no blur). Errors: detections of the standard level. "
        "Flips and wrong poses: over every darkness and blur scene.",
        "",
        f"| system | mode | detection, standard | darkest (α = {float(darkest):g}) | blur {float(longest or 0):g} px | "
        "position error median / p95 (mm) | rotation error median / p95 (°) | jitter position (mm) / rotation (°) | "
        "wrong poses (flips) | marker-free: views with a detection / poses | time (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, mode, m in _rows(summary):
        std = m["alpha"].get("1.0")
        j, a = m["jitter"], m["all_levels"]
        fv, fp = summary[name]["false_views"], m["false_poses"]
        L.append(
            f"| {systems.LABELS[name]} | {mode} | {_det(std)} | {_det(m['alpha'][darkest])} | "
            f"{_det(m['blur'][longest]) if longest else '—'} | {_f(std['t_err_median_mm'])} / {_f(std['t_err_p95_mm'])} | "
            f"{_f(std['r_err_median_deg'])} / {_f(std['r_err_p95_deg'])} | {_f(j['position_mm'], 4)} / {_f(j['rotation_deg'], 4)} | "
            f"{a['wrong']} ({a['flips']}) | {fv['k']}/{fv['n']} / {fp['k']}/{fp['n']} | "
            f"{_f(1e3 * std['seconds_median'], 1)} |"
        )
    comp = comparison(summary)
    if comp:
        L += [
            "",
            "## markerpose against the best peer on each metric",
            "",
            "| metric | markerpose | best peer | its value | ratio |",
            "|---|---|---|---|---|",
        ]
        for c in comp:
            a, b = c["markerpose"], c["peer"]
            if c["metric"].startswith("detection"):
                vals, ratio = (f"{100 * a:.1f} %", f"{100 * b:.1f} %"), "—"
            elif c["metric"].startswith("wrong"):
                vals, ratio = (str(a), str(b)), "—"
            else:
                nd = 1 if c["metric"].startswith("time") else 4
                vals = (_f(a, nd), _f(b, nd))
                ratio = "—" if not a or not b else (f"markerpose {b / a:.1f}× better" if b >= a else f"peer {a / b:.1f}× better")
            L.append(f"| {c['metric']} | {vals[0]} | {systems.LABELS[c['best_peer']]}, {c['mode']} | {vals[1]} | {ratio} |")
    for kind, vals, title in (
        ("alpha", alphas, "Detection versus darkness α"),
        ("blur", ["0.0"] + blurs, "Detection versus motion blur (px)"),
    ):
        L += [
            "",
            f"## {title}",
            "",
            "| system | mode | " + " | ".join(f"{float(v):g}" for v in vals) + " |",
            "|---|---|" + "---|" * len(vals),
        ]
        for name, mode, m in _rows(summary):
            L.append(f"| {systems.LABELS[name]} | {mode} | " + " | ".join(_det(m[kind][v]) for v in vals) + " |")
    L += [
        "",
        "## Errors by distance and tilt (standard level, detections)",
        "",
        "Position error median (mm) / rotation error median (°) per bin.",
        "",
    ]
    for key, title in (("by_distance", "distance (mm)"), ("by_tilt", "tilt (°)")):
        first = next(iter(_rows(summary)))[2][key]
        L += [
            "| system | mode | "
            + " | ".join(f"{title} {b['lo']:g}–{min(b['hi'], 800 if key == 'by_distance' else 60):g}" for b in first)
            + " |",
            "|---|---|" + "---|" * len(first),
        ]
        for name, mode, m in _rows(summary):
            L.append(
                f"| {systems.LABELS[name]} | {mode} | "
                + " | ".join(f"{_f(b['t_err_median_mm'])} / {_f(b['r_err_median_deg'], 2)} (n={b['n']})" for b in m[key])
                + " |"
            )
        L.append("")
    L += [
        "Plots: `detection.png` (detection versus darkness and blur), `accuracy.png` (errors versus distance and "
        "tilt), `jitter-speed.png` (static jitter and time per frame).",
    ]
    L += best_markdown(best, conf)
    L.append("")
    return "\n".join(L)


# --- plots -----------------------------------------------------------------------------------
_COLORS = {"markerpose": "k", "apriltag": "tab:blue", "aruco": "tab:orange", "charuco": "tab:green", "stag": "tab:red"}
_COLORS.update({f"{n}-defaults": f"{c}" for n, c in _COLORS.items()})
_STYLE = {"stereo": "-", "mono": "--"}


def _marker_style(name: str) -> str:
    """A peer at its library's defaults: crosses, at its settings for accuracy: dots."""
    return "x" if name.endswith("-defaults") else "o"


def _line_label(name: str, mode: str) -> str:
    return f"{systems.LABELS[name]}, {mode}"


def plots(summary: dict, out: Path) -> list[Path]:
    """detection.png, accuracy.png and jitter-speed.png: one line (or bar) per system and mode."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..experiments.plots import legend_below

    paths = []
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    for ax, kind, xlabel in ((axes[0], "alpha", "darkness α (exposure scale)"), (axes[1], "blur", "motion blur length (px)")):
        for name, mode, m in _rows(summary):
            xs = sorted(m[kind], key=float)
            ax.plot(
                [float(x) for x in xs],
                [100 * m[kind][x]["detection"]["p"] for x in xs],
                _STYLE[mode],
                marker=_marker_style(name),
                ms=4,
                color=_COLORS[name],
                label=_line_label(name, mode),
            )
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_xscale("log")
    axes[0].invert_xaxis()
    axes[0].set_ylabel("detection (% of scenes, pose within tolerance)")
    axes[0].set_title("Darkness")
    axes[1].set_title("Motion blur")
    legend_below(fig, axes[0], ncol=3)
    paths.append(out / "detection.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharey="row")
    for col, key, xlabel in ((0, "by_distance", "distance (mm)"), (1, "by_tilt", "tilt (°)")):
        for row, metric, ylabel in (
            (0, "t_err_median_mm", "position error, median (mm)"),
            (1, "r_err_median_deg", "rotation error, median (°)"),
        ):
            ax = axes[row, col]
            for name, mode, m in _rows(summary):
                b = m[key]
                x = [(v["lo"] + v["hi"]) / 2 for v in b]
                y = [np.nan if v[metric] is None else v[metric] for v in b]
                ax.plot(x, y, _STYLE[mode], marker=_marker_style(name), ms=4, color=_COLORS[name], label=_line_label(name, mode))
            ax.set_yscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3, which="both")
    fig.suptitle("Accuracy of the detections (standard level), by distance and tilt")
    legend_below(fig, axes[1, 0], ncol=3)
    paths.append(out / "accuracy.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.8))
    rows = list(_rows(summary))
    labels = [_line_label(n, mo) for n, mo, _ in rows]
    colors = [_COLORS[n] for n, _, _ in rows]
    hatches = ["" if mo == "stereo" else "//" for _, mo, _ in rows]
    vals = (
        ([m["jitter"]["position_mm"] or np.nan for _, _, m in rows], "static jitter, position (mm RMS)"),
        ([m["jitter"]["rotation_deg"] or np.nan for _, _, m in rows], "static jitter, rotation (° RMS)"),
        ([1e3 * (m["alpha"]["1.0"]["seconds_median"] or np.nan) for _, _, m in rows], "time per frame, standard level, median (ms)"),
    )
    y = np.arange(len(rows))
    for ax, (v, title) in zip(axes, vals):
        bars = ax.barh(y, v, color=colors, edgecolor="0.2")
        for b, h, val in zip(bars, hatches, v):
            b.set_hatch(h)
            if np.isfinite(val):
                ax.text(val * 1.08, b.get_y() + b.get_height() / 2, f"{val:.2g}" if val < 100 else f"{val:.0f}", va="center", fontsize=7)
        ax.set_xscale("log")
        ax.set_xlim(right=ax.get_xlim()[1] * 3)  # room for the values
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(title)
        ax.set_yticks(y, labels if ax is axes[0] else [""] * len(rows), fontsize=8)
        ax.invert_yaxis()
        ax.grid(alpha=0.3, axis="x", which="both")
    fig.tight_layout()
    paths.append(out / "jitter-speed.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


# --- main ------------------------------------------------------------------------------------
def plan(quick: bool = False, **overrides) -> dict:
    """The experiment's configuration: the defaults, ``QUICK`` with ``quick``, then overrides."""
    conf = {**default_conf, **(QUICK if quick else {}), **{k: v for k, v in overrides.items() if v is not None}}
    unknown = [n for n in conf["systems"] if n not in systems.SYSTEMS]
    if unknown:
        raise ValueError(f"unknown system(s) {unknown}; known: {list(systems.SYSTEMS)}")
    if conf["pairs"] < 1:
        raise ValueError(f"need at least one scene per level, got pairs={conf['pairs']}")
    return conf


def spread(conf: dict, seeds: int, jobs: int | None = None, progress: bool = True) -> dict:
    """The accuracy lead with its spread: the standard level (α = 1, no blur) of ``conf``
    drawn afresh under seeds 0 .. ``seeds`` - 1; per seed, each system's and mode's median
    position error over its detections, and markerpose's against the best peer's. Returns
    the per-seed medians and the lead's mean, sd and range."""
    per_seed = []
    for seed in range(int(seeds)):
        c = {**conf, "seed": seed, "alphas": (1.0,), "blurs": (), "jitter_poses": 0, "marker_free": 0, "tuned": False}
        rows = run(c, jobs=jobs, progress=progress)
        medians = {}
        for name in c["systems"]:
            for mode in ("stereo", "mono"):
                got = [r[name][mode] for _, r in rows if r[name].get(mode)]
                good = [g["t_err"] for g in got if _ok(g, c)]
                if got:
                    medians[f"{name}/{mode}"] = _pct(good, 50)
        ours = medians.get("markerpose/stereo")
        peers = {k: v for k, v in medians.items() if not k.startswith("markerpose/") and v is not None}
        best = min(peers, key=peers.get) if peers else None
        per_seed.append(
            {"seed": seed, "medians_mm": medians, "best_peer": best, "lead": None if not best or not ours else peers[best] / ours}
        )
    leads = np.array([s["lead"] for s in per_seed if s["lead"] is not None])
    ours = np.array([s["medians_mm"]["markerpose/stereo"] for s in per_seed if s["medians_mm"].get("markerpose/stereo") is not None])
    return {
        "pairs": conf["pairs"],
        "seeds": per_seed,
        "lead_mean": float(leads.mean()) if len(leads) else None,
        "lead_sd": float(leads.std(ddof=1)) if len(leads) > 1 else None,
        "lead_range": [float(leads.min()), float(leads.max())] if len(leads) else None,
        "markerpose_median_mm_mean": float(ours.mean()) if len(ours) else None,
        "markerpose_median_mm_range": [float(ours.min()), float(ours.max())] if len(ours) else None,
    }


def spread_markdown(res: dict, command: str) -> str:
    """The spread's report: markerpose and the best peer per seed, the lead's mean ± sd, and
    each system's median over the seeds."""
    L = [
        "# The accuracy lead over seeds",
        "",
        f"Command: `{command}`. The standard level ({res['pairs']} scenes, α = 1, no blur) drawn under each seed (seed 0: "
        "the full run's standard level); per seed the median position error (mm) of each system's detections, and "
        "markerpose's lead: the best peer's median over markerpose's.",
        "",
        "| seed | markerpose (mm) | best peer | its median (mm) | lead |",
        "|---|---|---|---|---|",
    ]
    for s in res["seeds"]:
        best = s["best_peer"]
        lead = "—" if s["lead"] is None else f"{s['lead']:.1f}×"
        L.append(
            f"| {s['seed']} | {_f(s['medians_mm'].get('markerpose/stereo'), 4)} | {best} | {_f(s['medians_mm'].get(best), 4)} | {lead} |"
        )
    if res["lead_mean"] is not None:
        sd = "" if res["lead_sd"] is None else f" ± {res['lead_sd']:.1f}"
        lo, hi = res["lead_range"]
        L += [
            "",
            f"**Lead over the best peer: {res['lead_mean']:.1f}×{sd}** (mean ± sd over {len(res['seeds'])} seeds; range {lo:.1f}–{hi:.1f}×).",
        ]
    keys = sorted({k for s in res["seeds"] for k in s["medians_mm"]}, key=lambda k: (not k.startswith("markerpose"), k))
    L += ["", "| system / mode | median position error over the seeds: mean (min–max), mm |", "|---|---|"]
    for k in keys:
        v = np.array([s["medians_mm"][k] for s in res["seeds"] if s["medians_mm"].get(k) is not None])
        if len(v):
            L.append(f"| {k} | {v.mean():.4f} ({v.min():.4f}–{v.max():.4f}) |")
    return "\n".join(L) + "\n"


def main(
    conf: dict, out_dir: str | Path = "markerpose-peers", jobs: int | None = None, command: str = "markerpose peers", progress: bool = True
) -> dict:
    """Run the comparison; write report.md, results.json and the plots into ``out_dir``."""
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    skipped = systems.missing([n for n in conf["systems"] if n in systems.PEERS])
    for name, pkg in skipped.items():
        print(f'skipping {name}: its detector is not installed (pip install {pkg}, or pip install -e ".[peers]")')
    conf = {**conf, "systems": tuple(n for n in conf["systems"] if n not in skipped)}
    results = run(conf, jobs=jobs, progress=progress)
    summary = summarize(results, conf)
    seconds = time.perf_counter() - t0
    doc = {
        "command": command,
        "seconds": seconds,
        "conf": {k: list(v) if isinstance(v, tuple) else v for k, v in conf.items()},
        "skipped": skipped,
        "setup": setup_lines(conf),
        "comparison": comparison({n: e for n, e in summary.items() if n not in systems.TUNED}),
        "best_settings": best_settings(summary),
        **summary,
    }
    write_json(out / "results.json", doc)
    paths = plots({n: e for n, e in summary.items() if n not in systems.TUNED}, out)
    (out / "report.md").write_text(report_markdown(summary, conf, command, seconds, skipped))
    doc["files"] = [str(out / "report.md"), str(out / "results.json")] + [str(p) for p in paths]
    return doc
