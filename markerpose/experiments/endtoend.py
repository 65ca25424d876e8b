"""End-to-end accuracy on held-out stereo pairs: detection, centres and pose against ground truth.

Held-out pairs of the default rig (seeded, never trained on) with the marker anywhere in
the working volume (350-800 mm, tilt up to 60°, any in-plane rotation, all three rings in
both views), under standard conditions (gain α in [0.25, 1], motion blur ≤ 9 px), in the
dark (α = 0.0625) and with 25 px motion blur; and marker-free pairs (clutter with many
single rings and dark disks, the marker out of both views), where any pose — and, with
``single_view``, any detection in a view — is a false positive. Every preset
(:mod:`markerpose.presets`) runs on the same pairs.

A pair is *detected* when all six centres (three per view) lie within ``tolerance_px``
of the ground truth with the right IDs; a failure counts as a failure (error = inf),
never dropped. Centre errors are measured against the true centre of the imaged outer
ellipse (what an ellipse fit estimates) and against the projection of the ring's 3D
centre (they differ by the perspective bias); pose errors against the true pose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..engine import run_tasks
from ..formats import write_json
from ..geometry import nearest_rotation, rotation_angle
from ..marker import Marker
from ..pipeline import MarkerPose
from ..synth import Imaging, clutter_background, look_at_pose, realism, render_stereo
from .configs import available, build

SETS = {
    "standard": {"seed": 3001, "alpha": (0.25, 1.0), "blur": (0.0, 9.0)},
    "dark_0.0625": {"seed": 3002, "alpha": 0.0625, "blur": (0.0, 9.0)},
    "blur_25": {"seed": 3003, "alpha": (0.25, 1.0), "blur": 25.0},
    "marker_free": {"seed": 3004, "alpha": (0.25, 1.0), "blur": (0.0, 9.0), "marker_free": True},
    # Beyond the paper's working volume (rings under ~12 px at stage 1's 320x240 input):
    # what stage 1's second look is for. Not among the default sets.
    "far": {"seed": 3005, "alpha": (0.25, 1.0), "blur": (0.0, 9.0), "distance": (800.0, 1600.0)},
}
# The realism sets: the standard set's conditions with one effect of real recordings each
# (markerpose.synth.realism); `--sets realism` names them all. Not among the default sets.
REALISM = tuple(f"realism_{e}" for e in realism.EFFECTS)
SETS.update(
    {
        name: {"seed": 3100 + k, "alpha": (0.25, 1.0), "blur": (0.0, 9.0), "effect": e}
        for k, (name, e) in enumerate(zip(REALISM, realism.EFFECTS))
    }
)

default_conf = {
    "pairs": 200,  # per set
    "sets": ("standard", "dark_0.0625", "blur_25", "marker_free"),
    "configs": None,  # preset names; None: all available
    "tolerance_px": 3.0,
    "single_view": False,  # also each view alone (MarkerPose.detect)
    "workers": 1,  # processes running sets at once
}


def _draw(rng, v):
    return float(rng.uniform(*v)) if isinstance(v, (tuple, list)) else float(v)


def pairs(name: str, n: int, rig: StereoRig, marker: Marker):
    """Yield (frame, conditions) for ``n`` held-out pairs of a set (deterministic)."""
    return random_pairs(SETS[name], n, rig, marker)


def random_pairs(spec: dict, n: int, rig: StereoRig, marker: Marker):
    """Yield (frame, conditions) for ``n`` pairs with the marker anywhere in the working
    volume: ``spec`` gives the ``seed`` (anything ``default_rng`` takes), the ``alpha``
    and ``blur`` (a value or a (lo, hi) range) and optionally the ``distance`` range in mm
    (default: the paper's 350-800) and ``noise`` (False: the sensor's noise left out)."""
    rng = np.random.default_rng(spec["seed"])
    if spec.get("marker_free"):
        yield from marker_free_pairs(spec, n, rig, marker, rng)
        return
    made = 0
    while made < n:
        z = rng.uniform(*spec.get("distance", (350.0, 800.0)))
        tilt = rng.uniform(0, 60)
        T = look_at_pose([0, 0, z], tilt, rng.uniform(0, 360), rng.uniform(0, 360))
        # Anywhere both cameras see it: around the rig's convergence line, spread with depth.
        T[:3, 3] = [rng.uniform(-0.1, 0.1) * z - 0.12 * (z - 560), rng.uniform(-0.15, 0.15) * z, z]
        T[:3, 3] -= T[:3, :3] @ marker.points3d.mean(0)
        alpha, blur = _draw(rng, spec["alpha"]), _draw(rng, spec["blur"])
        angle = rng.uniform(0, 180)
        effect = spec.get("effect")
        extra = realism.imaging_settings(effect, rng, marker) if effect else {}
        im = Imaging(alpha=alpha, motion_blur=blur, motion_angle=angle, noise=spec.get("noise", True), **extra)
        bgs = None
        if effect == "ring_object":
            bgs = realism.ring_object_backgrounds(rig, T, marker, tuple(clutter_background(c.image_size, rng) for c in rig.cameras), rng)
        frame = render_stereo(rig, T, marker, im, bgs, seed=rng)
        if not all(v.in_image.all() for v in frame.views):
            continue
        made += 1
        yield frame, {"distance": float(T[2, 3]), "tilt": float(tilt), "alpha": alpha, "blur": blur, "blur_angle": float(angle)}


def marker_free_pairs(spec: dict, n: int, rig: StereoRig, marker: Marker, rng: np.random.Generator):
    """Yield (frame, conditions) for ``n`` pairs without the marker: each view's own clutter
    with 3-10 ring distractors (single rings with the marker's inner/outer ratio, dark
    disks) and the marker far outside both views; ``spec`` gives ``alpha`` and ``blur``."""
    T = np.eye(4)
    T[:3, 3] = [0.0, 3000.0, 1000.0]  # ~70° above both cameras' axes, in front of them
    ratio = marker.inner_radius / marker.outer_radius
    for _ in range(n):
        bgs = tuple(
            clutter_background(cam.image_size, rng, ring_distractors=int(rng.integers(3, 11)), ring_ratio=ratio) for cam in rig.cameras
        )
        alpha, blur = _draw(rng, spec["alpha"]), _draw(rng, spec["blur"])
        angle = rng.uniform(0, 180)
        frame = render_stereo(rig, T, marker, Imaging(alpha=alpha, motion_blur=blur, motion_angle=angle), bgs, seed=rng)
        yield frame, {"alpha": alpha, "blur": blur, "blur_angle": float(angle)}


def evaluate_marker_free(tracker: MarkerPose, frame, single_view: bool) -> dict:
    """One tracker on a marker-free pair: whether it returns a pose (a false pose) and, with
    ``single_view``, how many views :meth:`MarkerPose.detect` claims the marker in."""
    out = {"false_pose": tracker.estimate(*frame.images) is not None}
    if single_view:
        out["false_views"] = sum(tracker.detect(image, view=k) is not None for k, image in enumerate(frame.images))
    return out


def evaluate_pair(tracker: MarkerPose, frame, tol: float) -> dict:
    """One tracker on one pair: detected (all six centres within ``tol`` px, right IDs),
    centre errors (6,) against the imaged ellipse centres and the projected 3D centres,
    translation (mm) and rotation (°) errors; a failure gives inf errors."""
    est = tracker.estimate(*frame.images)
    inf3 = np.full(6, np.inf)
    if est is None:
        return {"detected": False, "err": inf3, "err3d": inf3, "t_mm": np.inf, "r_deg": np.inf}
    raw = np.concatenate([d.centers for d in est.detections])  # (6, 2): the fitted centres
    true = np.concatenate([v.outer_centers for v in frame.views])
    proj = np.concatenate([v.centers for v in frame.views])
    err = np.linalg.norm(raw - true, axis=1)
    # The 3D-centre comparison uses the pipeline's output centres (bias-corrected when on).
    err3d = np.linalg.norm(np.concatenate(list(est.centers)) - proj, axis=1)
    T = frame.T_left_marker
    return {
        "detected": bool(np.all(err <= tol)),
        "err": err,
        "err3d": err3d,
        "t_mm": float(np.linalg.norm(est.t - T[:3, 3])),
        # The paper's R is not exactly orthonormal: its angle to the truth is measured on
        # the nearest rotation.
        "r_deg": float(np.rad2deg(rotation_angle(nearest_rotation(est.R), T[:3, :3]))),
    }


def evaluate_views(tracker: MarkerPose, frame, tol: float) -> list[bool]:
    """Each view alone (:meth:`MarkerPose.detect`): all three centres within ``tol`` px of
    the imaged ellipse centres, in ID order."""
    out = []
    for k, (image, view) in enumerate(zip(frame.images, frame.views)):
        det = tracker.detect(image, view=k)
        out.append(det is not None and bool(np.all(np.linalg.norm(det.centers - view.outer_centers, axis=1) <= tol)))
    return out


def summarize(rows: list[dict]) -> dict:
    """Detection rate, centre and pose error percentiles (failures count as inf) and recalls."""
    det = np.array([r["detected"] for r in rows])
    err = np.concatenate([r["err"] for r in rows])
    err3d = np.concatenate([r["err3d"] for r in rows])
    t = np.array([r["t_mm"] for r in rows])
    rot = np.array([r["r_deg"] for r in rows])
    fin = np.isfinite(err)

    def pct(x, q):
        return float(np.percentile(x, q, method="higher"))

    returned = np.array([np.isfinite(r["err"]).all() for r in rows])
    return {
        "pairs": len(rows),
        "detected": float(det.mean()),
        # A pose returned although a centre is beyond the tolerance: a wrong pose, not a miss.
        "returned_wrong": float(np.mean(returned & ~det)),
        "center_median_px": pct(err, 50),
        "center_p95_px": pct(err, 95),
        "center3d_median_px": pct(err3d, 50),
        "center3d_p95_px": pct(err3d, 95),
        "center_median_px_found": float(np.median(err[fin])) if fin.any() else float("inf"),
        "t_median_mm": pct(t, 50),
        "t_p95_mm": pct(t, 95),
        "r_median_deg": pct(rot, 50),
        "r_p95_deg": pct(rot, 95),
        "recall_t_0.1mm": float(np.mean(t <= 0.1)),
        "recall_t_1mm": float(np.mean(t <= 1.0)),
        "recall_r_0.1deg": float(np.mean(rot <= 0.1)),
        "recall_r_1deg": float(np.mean(rot <= 1.0)),
    }


def run_set(set_name: str, conf: dict, progress: bool = True, position: int = 0) -> dict:
    """Every preset of ``conf["configs"]`` on one held-out set; returns {preset: figures}."""
    c = {**default_conf, **conf}
    rig, marker = StereoRig.default(), Marker()
    trackers = {name: build(name, rig, marker) for name in available(c["configs"])}
    rows = {name: [] for name in trackers}
    views = {name: [] for name in trackers}
    conds = []
    free = SETS[set_name].get("marker_free", False)
    bar = tqdm(
        pairs(set_name, c["pairs"], rig, marker), total=c["pairs"], desc=set_name, unit="pair", disable=not progress, position=position
    )
    for frame, cond in bar:
        conds.append(cond)
        for name, tr in trackers.items():
            if free:
                rows[name].append(evaluate_marker_free(tr, frame, c["single_view"]))
                continue
            rows[name].append(evaluate_pair(tr, frame, c["tolerance_px"]))
            if c["single_view"]:
                views[name] += evaluate_views(tr, frame, c["tolerance_px"])
    out_set = {}
    for name in trackers:
        if free:
            out_set[name] = summarize_marker_free(rows[name])
            continue
        s = summarize(rows[name])
        s["by_condition"] = by_condition(rows[name], conds)
        if views[name]:
            s["single_view_detected"] = float(np.mean(views[name]))
            s["single_views"] = len(views[name])
        out_set[name] = s
    return out_set


def _run_set_alone(args, report=None) -> tuple[str, dict]:
    """:func:`run_set` in a worker process: one torch thread, so workers do not contend."""
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    return args[0], run_set(*args)


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    """Run every preset on the held-out pairs; returns (and writes as JSON) the figures.

    With ``conf["workers"]`` > 1 the sets run in that many processes at once, started in
    the order of ``conf["sets"]`` (put the slowest first; same pairs, same figures; each
    process uses one torch thread). ``out`` is rewritten as each set finishes, so a
    stopped run keeps what it finished. Sets are reported in the order of :data:`SETS`.
    """
    c = {**default_conf, **(conf or {})}
    available(c["configs"])  # unknown names fail here, before any work
    c["sets"] = tuple(dict.fromkeys(m for n in c["sets"] for m in (REALISM if n == "realism" else (n,))))
    unknown = [n for n in c["sets"] if n not in SETS]
    if unknown:
        raise ValueError(f"unknown set(s) {unknown}; known: {list(SETS)}")
    if c["workers"] < 1:
        raise ValueError(f"workers must be >= 1, got {c['workers']}")
    res = {"conf": {k: list(v) if isinstance(v, tuple) else v for k, v in c.items()}, "sets": {}}

    def done(name, out_set):  # the JSON is rewritten after every set: a stopped run keeps the finished ones
        res["sets"][name] = out_set
        res["sets"] = {n: res["sets"][n] for n in SETS if n in res["sets"]}
        if out:
            write_json(out, res)

    if c["workers"] == 1 or len(c["sets"]) == 1:
        for set_name in c["sets"]:
            done(set_name, run_set(set_name, c, progress))
    else:  # on Ray where it is installed, else one set after the other
        jobs = [(name, c, False, k) for k, name in enumerate(c["sets"])]
        run_tasks(
            _run_set_alone,
            jobs,
            workers=c["workers"],
            on_result=lambda i, r: done(*r),
            desc="sets",
            unit="set",
            progress=progress,
            strict=True,
        )
    return res


def summarize_marker_free(rows: list[dict]) -> dict:
    """Fraction of marker-free pairs given a pose and, when measured, of views given a detection."""
    s = {"pairs": len(rows), "false_poses": float(np.mean([r["false_pose"] for r in rows]))}
    if rows and "false_views" in rows[0]:
        s["single_views"] = 2 * len(rows)
        s["single_view_false"] = float(sum(r["false_views"] for r in rows) / (2 * len(rows)))
    return s


def by_condition(rows, conds) -> list[dict]:
    """:func:`summarize` by distance and by tilt bins of the pairs' conditions."""
    out = []
    for key, edges in (("distance", (350, 500, 650, 801, 1000, 1200, 1401, 1601)), ("tilt", (0, 20, 40, 61))):
        v = np.array([cd[key] for cd in conds])
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = np.nonzero((v >= lo) & (v < hi))[0]
            if len(sel):
                s = summarize([rows[i] for i in sel])
                out.append(
                    {
                        "bin": f"{key} {lo}-{hi}",
                        **{k: s[k] for k in ("pairs", "detected", "center_median_px", "center3d_median_px", "t_median_mm", "r_median_deg")},
                    }
                )
    return out


def report(res: dict) -> str:
    """Markdown tables of :func:`main`'s result."""
    lines = []
    for set_name, per in res["sets"].items():
        first = next(iter(per.values()))
        if "false_poses" in first:
            views = "single_view_false" in first
            lines += [
                f"**{set_name}** ({first['pairs']} pairs without the marker; any output is a false positive)",
                "",
                "| configuration | false poses (pairs) |"
                + (f" false detections (`MarkerPose.detect`, {first['single_views']} views) |" if views else ""),
                "|---|---|" + ("---|" if views else ""),
            ]
            for name, s in per.items():
                cells = f"{100 * s['false_poses']:.2f} %" + (f" | {100 * s['single_view_false']:.2f} %" if views else "")
                lines.append(f"| {name} | {cells} |")
            lines.append("")
            continue
        lines += [
            f"**{set_name}** ({first['pairs']} pairs; detected = all six centres within {res['conf']['tolerance_px']:g} px, right IDs)",
            "",
            "| configuration | detected | centre median / p95 (px, vs ellipse centre) | vs projected 3D centre | translation median / p95 (mm) | rotation median / p95 (°) |",
            "|---|---|---|---|---|---|",
        ]
        for name, s in per.items():
            lines.append(
                f"| {name} | {s['detected']:.4f} | {s['center_median_px']:.3f} / {s['center_p95_px']:.3f} | "
                f"{s['center3d_median_px']:.3f} / {s['center3d_p95_px']:.3f} | {s['t_median_mm']:.4f} / {s['t_p95_mm']:.4f} | "
                f"{s['r_median_deg']:.4f} / {s['r_p95_deg']:.4f} |"
            )
        if any("returned_wrong" in s for s in per.values()):
            lines += [
                "",
                "Returned although a centre is beyond the tolerance (wrong poses, counted as not detected): "
                + "; ".join(f"{name} {100 * s['returned_wrong']:.2f} %" for name, s in per.items() if "returned_wrong" in s),
            ]
        if any("single_view_detected" in s for s in per.values()):
            lines += [
                "",
                f"Each view alone (`MarkerPose.detect`, {first['single_views']} views; all three centres within {res['conf']['tolerance_px']:g} px, right IDs): "
                + "; ".join(f"{name} {100 * s['single_view_detected']:.2f} %" for name, s in per.items()),
            ]
        lines.append("")
        # By distance and tilt: detection; centre median vs the ellipse centre / vs the
        # projected 3D centre (they differ by the perspective bias, which grows with tilt).
        bins = [b["bin"] for b in first["by_condition"]]
        lines += [
            f"*{set_name} by distance (mm) and tilt (°)*: detected; centre median px vs ellipse centre / vs projected 3D centre",
            "",
            "| bin | pairs | " + " | ".join(per) + " |",
            "|---|---|" + "---|" * len(per),
        ]
        for k, b in enumerate(bins):
            cells = []
            for s in per.values():
                c = s["by_condition"][k]
                cells.append(f"{100 * c['detected']:.1f} %; {c['center_median_px']:.3f} / {c['center3d_median_px']:.3f}")
            lines.append(f"| {b} | {first['by_condition'][k]['pairs']} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


__all__ = [
    "SETS",
    "by_condition",
    "default_conf",
    "evaluate_marker_free",
    "evaluate_pair",
    "evaluate_views",
    "main",
    "marker_free_pairs",
    "pairs",
    "random_pairs",
    "report",
    "run_set",
    "summarize",
    "summarize_marker_free",
]
