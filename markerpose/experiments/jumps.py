"""``markerpose bench --jumps``: the marker put down elsewhere between two frames of a stream.

Each trial renders a stereo pair of the marker at a random pose of the working volume,
then a pair where it has jumped: moved by up to ``max_jump`` mm and turned by up to
``max_turn`` degrees about a random axis (both uniform), with motion blur, light and
six ring-like decoys per view drawn as in the held-out sets (a new scene each trial); in
one trial in six the marker has left both views instead. ``MarkerPose.track`` sees the first pair (its prior), then
the second, with the default settings and without the search near the prediction
(``track={"shift_margin": 0}``), the two in alternating order on the same pairs. Reported:
how the jump was found (by the prior itself, by the search, or by stage 1), wrong poses,
poses without the marker and the time of the second pair, by how far and how much turned
the marker jumped.

``main(conf, out_dir) -> dict`` writes ``report.md`` and ``results.json`` into ``out_dir``.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_json
from ..geometry import rotation_angle
from ..marker import Marker
from ..pipeline import MarkerPose
from ..synth import Imaging, clutter_background, look_at_pose, render_stereo
from .configs import settings

default_conf = {
    "trials": 120,
    "seed": 11,
    "max_jump": 60.0,  # mm
    "max_turn": 15.0,  # degrees, about a random axis
    "threads": None,  # the networks' inference threads (None: every core)
}
CONFIGS = {"search": {}, "no search": {"shift_margin": 0}}
JUMP_BINS = ((0, 15), (15, 30), (30, 45), (45, 60))  # mm
TURN_BINS = ((0, 5), (5, 10), (10, 180))  # degrees


def trials(conf: dict, rig: StereoRig, marker: Marker, progress: bool = True):
    """Yield per trial (prior pair, jumped pair, truth dict), deterministic for ``conf["seed"]``."""
    rng = np.random.default_rng(conf["seed"])
    ratio = marker.inner_radius / marker.outer_radius
    for i in tqdm(range(int(conf["trials"])), desc="jumps", unit="trial", disable=not progress):
        bgs = tuple(clutter_background(cam.image_size, rng, ring_distractors=6, ring_ratio=ratio) for cam in rig.cameras)
        pos = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(480, 900)])
        tilt, axis, roll = rng.uniform(0, 45), rng.uniform(0, 360), rng.uniform(-40, 40)
        T_prior = look_at_pose(pos, tilt, axis, roll)
        jump = rng.uniform(0, conf["max_jump"])
        d = rng.normal(size=3)
        d[2] *= 0.5  # less along the line of sight than across it, as a hand moves a marker in view
        d *= jump / np.linalg.norm(d)
        # Turned about the marker's origin by an angle up to max_turn, about a random axis.
        w = rng.normal(size=3)
        w *= np.radians(rng.uniform(0, conf["max_turn"])) / np.linalg.norm(w)
        T = T_prior.copy()
        T[:3, :3] = T_prior[:3, :3] @ cv2.Rodrigues(w)[0]
        T[:3, 3] += d
        blur, alpha = float(rng.choice([0, 0, 5, 10, 15])), float(rng.choice([0.8, 0.8, 0.3, 0.0625]))
        imaging = Imaging(alpha=alpha, motion_blur=blur, motion_angle=rng.uniform(0, 180))
        empty = i % 6 == 5
        if empty:  # the marker gone: put 700 mm to the side, out of both views, the scene as lit and blurred
            T = T.copy()
            T[0, 3] += 700.0
        first = render_stereo(rig, T_prior, marker, Imaging(alpha=alpha), bgs, seed=rng)
        second = render_stereo(rig, T, marker, imaging, bgs, seed=rng)
        truth = {
            "trial": i,
            "jump_mm": float(jump),
            "turn_deg": float(np.degrees(rotation_angle(T_prior[:3, :3], T[:3, :3]))),
            "blur_px": blur,
            "alpha": alpha,
            "empty": empty,
            "visible": not empty and all(v.in_image.all() for v in second.views),
            "T": T,
        }
        yield first.images, second.images, truth


def main(conf: dict | None = None, out_dir: str | Path | None = "markerpose-jumps", progress: bool = True) -> dict:
    """Run every trial with and without the search, report."""
    c = settings(conf, default_conf, "jump")
    if int(c["trials"]) < 1:
        raise ValueError(f"trials must be >= 1, got {c['trials']}")
    rig, marker = StereoRig.default(), Marker()
    opts = {} if c["threads"] is None else {"threads": int(c["threads"])}
    trackers = {name: MarkerPose(rig, marker, track=over, **opts) for name, over in CONFIGS.items()}
    rows = []
    for k, (first, second, truth) in enumerate(trials(c, rig, marker, progress)):
        T = truth.pop("T")
        row = dict(truth)
        for name in list(trackers) if k % 2 == 0 else list(trackers)[::-1]:
            tracker = trackers[name]
            tracker.reset()
            prior = tracker.track(*first)
            t0 = time.perf_counter()
            est = tracker.track(*second) if prior is not None else None
            dt = 1000 * (time.perf_counter() - t0)
            how = None if est is None else "stage 1" if est.source == "detected" else "search" if "search" in tracker.timings else "prior"
            row[name] = {
                "prior": prior is not None,
                "ms": dt if prior is not None else None,
                "how": how,
                "source": None if est is None else est.source,
                "t_mm": None if est is None else float(np.linalg.norm(est.t - T[:3, 3])),
            }
        rows.append(row)
    res = {"conf": c, "summary": {name: summarize(rows, name) for name in CONFIGS}, "trials": rows}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "results.json", res)
        (out / "report.md").write_text(report(res))
    return res


def _median(values: list) -> float | None:
    return float(np.median(values)) if values else None


def summarize(rows: list[dict], name: str) -> dict:
    """Figures of configuration ``name`` over the trials whose first pair gave a prior to
    both configurations (the same trials for both)."""
    rows = [r for r in rows if all(r[n]["prior"] for n in CONFIGS)]
    vis = [r for r in rows if r["visible"]]

    def part(sel):
        return {
            "n": len(sel),
            "search": sum(r[name]["how"] == "search" for r in sel),
            "found": sum(r[name]["source"] is not None for r in sel),
            "median_ms": _median([r[name]["ms"] for r in sel]),
        }

    return {
        "trials": len(rows),
        "visible": len(vis),
        "found": sum(r[name]["source"] is not None for r in vis),
        **{how: sum(r[name]["how"] == how for r in vis) for how in ("prior", "search", "stage 1")},
        "wrong_poses": sum(r[name]["t_mm"] is not None and r[name]["t_mm"] > 1.0 for r in rows if not r["empty"]),
        "false_poses": sum(r[name]["source"] is not None for r in rows if r["empty"]),
        "median_ms": _median([r[name]["ms"] for r in vis]),
        "t_median_mm": _median([r[name]["t_mm"] for r in vis if r[name]["t_mm"] is not None]),
        "by_jump": {f"{lo}-{hi}": part([r for r in vis if lo <= r["jump_mm"] < hi]) for lo, hi in JUMP_BINS},
        "by_turn": {f"{lo}-{hi}": part([r for r in vis if lo <= r["turn_deg"] < hi and r["jump_mm"] < 45]) for lo, hi in TURN_BINS},
        "empty": part([r for r in rows if r["empty"]]),
    }


def _ms(x) -> str:
    return "—" if x is None else f"{x:.1f}"


def report(res: dict) -> str:
    """Markdown of :func:`main`'s result."""
    c, s = res["conf"], res["summary"]
    names = list(CONFIGS)
    first = s[names[0]]
    lines = [
        f"# Jumps: the marker put down elsewhere between two frames ({first['trials']} of {c['trials']} trials)",
        "",
        "(A trial counts when both settings found the marker in its first pair.)",
        "",
        (
            f"Each trial: a pair at a random pose (the prior), then a pair where the marker moved by up to {c['max_jump']:g} mm and "
            f"turned by up to {c['max_turn']:g}° about a random axis (both uniform), motion blur 0–15 px, α 0.0625–0.8, six ring-like decoys "
            "per view, a new scene each trial; one trial in six with the marker out of view in the second pair. `track()` with the default settings (`search`) and with "
            '`track={"shift_margin": 0}` (`no search`: stage 1 near the prediction, then in the whole images), alternating, '
            "on the same pairs; the time is the second pair's."
        ),
        "",
        "| | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
        "| pairs with the marker in view: found | " + " | ".join(f"{s[n]['found']} of {s[n]['visible']}" for n in names) + " |",
        "| … by the prior / the search / stage 1 | "
        + " | ".join(f"{s[n]['prior']} / {s[n]['search']} / {s[n]['stage 1']}" for n in names)
        + " |",
        "| wrong poses (> 1 mm) / poses without the marker | "
        + " | ".join(f"{s[n]['wrong_poses']} / {s[n]['false_poses']}" for n in names)
        + " |",
        "| translation error, median, mm | "
        + " | ".join("—" if s[n]["t_median_mm"] is None else f"{s[n]['t_median_mm']:.4f}" for n in names)
        + " |",
        "| time of the second pair, median (marker in view), ms | " + " | ".join(_ms(s[n]["median_ms"]) for n in names) + " |",
        "",
        "By how far the marker jumped (pairs with it in view): found by the search, of n; median ms.",
        "",
        "| jump, mm | n | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for key in first["by_jump"]:
        lines.append(
            f"| {key} | {first['by_jump'][key]['n']} | "
            + " | ".join(f"{s[n]['by_jump'][key]['search']}, {_ms(s[n]['by_jump'][key]['median_ms'])} ms" for n in names)
            + " |"
        )
    lines += [
        "",
        "By how much it turned (the rotation between the prior and the truth; jumps under 45 mm): found by the search, of n; median ms.",
        "",
        "| turn, ° | n | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for key in first["by_turn"]:
        lines.append(
            f"| {key} | {first['by_turn'][key]['n']} | "
            + " | ".join(f"{s[n]['by_turn'][key]['search']}, {_ms(s[n]['by_turn'][key]['median_ms'])} ms" for n in names)
            + " |"
        )
    e = {n: s[n]["empty"] for n in names}
    lines += [
        "",
        f"Without the marker ({first['empty']['n']} pairs): median "
        + ", ".join(f"{_ms(e[n]['median_ms'])} ms ({n})" for n in names)
        + " (the search, stage 1 near the prediction, then both whole looks).",
    ]
    return "\n".join(lines) + "\n"


__all__ = ["CONFIGS", "default_conf", "main", "report", "summarize", "trials"]
