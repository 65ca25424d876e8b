"""``markerpose bench``: speed of the whole stereo pipeline per preset.

Renders a few 1280x1024 stereo pairs of the marker in the working volume, then times
every preset on the same pairs, interleaved (pair 1 with every preset, then pair 2,
...) so that the machine's state affects them alike. Reports the median time per pair,
frames per second, the ratio to the reference preset (``paper`` when its networks are
present, else ``paper-classical``), the median time of each stage, the median time on
pairs with 25 px of motion blur (where the rings are refitted under a blur model), the
median time on marker-free pairs (what a tracker spends while the marker is out of
view), the worst time on inconsistent pairs (a view given twice, the views swapped, two
different frames, the right view shifted by 40 px: what a mis-wired rig or a dropped
frame feeds a tracker) and the process's peak memory.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_json
from ..marker import Marker
from ..synth import Imaging, look_at_pose, render_stereo
from .configs import available, build
from .endtoend import marker_free_pairs

default_conf = {
    "pairs": 8,
    "blurred_pairs": 4,  # pairs with 25 px of motion blur (timed apart)
    "empty_pairs": 4,  # marker-free pairs (the marker out of both views, clutter with ring distractors)
    "repeats": 3,  # passes over the pairs (the first pass also warms up)
    "seed": 0,
    "inconsistent": True,  # also time the inconsistent pairs built from the first two pairs
    "threads": None,  # torch threads (None: torch's default, all cores)
    "configs": None,  # preset names (markerpose.presets); None = all available
}


def _pairs(n: int, seed: int, blur: float = 0.0):
    rng = np.random.default_rng(seed)
    rig, marker = StereoRig.default(), Marker()
    frames = []
    while len(frames) < n:
        T = look_at_pose(
            [rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(400, 750)],
            rng.uniform(0, 45),
            rng.uniform(0, 360),
            rng.uniform(0, 360),
        )
        im = Imaging(alpha=rng.uniform(0.5, 1.0), motion_blur=blur, motion_angle=rng.uniform(0, 180))
        f = render_stereo(rig, T, marker, im, seed=rng)
        if all(v.in_image.all() for v in f.views):
            frames.append(f)
    return rig, marker, frames


def inconsistent_pairs(frames: list) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(kind, left, right) pairs that no marker pose explains, from the valid ``frames``."""
    out = []
    for f in frames[:2]:
        left, right = f.images
        shifted = np.empty_like(right)
        shifted[:, 40:], shifted[:, :40] = right[:, :-40], right[:, :1]
        out += [
            ("left view twice", left, left),
            ("right view twice", right, right),
            ("views swapped", right, left),
            ("right view shifted 40 px", left, shifted),
        ]
    if len(frames) >= 2:
        out.append(("two different frames", frames[0].images[0], frames[1].images[1]))
    return out


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    """Run the benchmark; returns (and optionally writes as JSON) the figures."""
    c = {**default_conf, **(conf or {})}
    if c["threads"]:
        import torch

        torch.set_num_threads(int(c["threads"]))
    rig, marker, frames = _pairs(c["pairs"], c["seed"])
    blurred = _pairs(c["blurred_pairs"], c["seed"] + 2, blur=25.0)[2]
    # Marker-free pairs: each view's clutter with ring distractors, the marker out of view.
    spec = {"alpha": (0.5, 1.0), "blur": 0.0}
    empty = [f for f, _ in marker_free_pairs(spec, c["empty_pairs"], rig, marker, np.random.default_rng(c["seed"] + 1))]
    trackers = {name: build(name, rig, marker) for name in available(c["configs"])}
    times = {name: [] for name in trackers}
    stages = {name: {} for name in trackers}
    found = dict.fromkeys(trackers, 0)
    times_empty = {name: [] for name in trackers}
    times_blur = {name: [] for name in trackers}
    found_blur = dict.fromkeys(trackers, 0)
    false_poses = dict.fromkeys(trackers, 0)
    odd = inconsistent_pairs(frames) if c["inconsistent"] else []
    worst = {name: {} for name in trackers}  # kind -> (worst ms, poses returned)
    items = [(f.images, "marker") for f in frames] + [(f.images, "blur") for f in blurred] + [(f.images, "empty") for f in empty]
    items += [((lft, rgt), kind) for kind, lft, rgt in odd]
    with tqdm(total=c["repeats"] * len(items), desc="bench", unit="pair", disable=not progress) as bar:
        for rep in range(c["repeats"]):
            for images, kind in items:
                for name, tr in trackers.items():
                    t0 = time.perf_counter()
                    est = tr.estimate(*images)
                    dt = time.perf_counter() - t0
                    if rep == 0:
                        continue  # warm-up pass: caches, lazy initialisation
                    if kind not in ("marker", "blur", "empty"):
                        ms, poses = worst[name].get(kind, (0.0, 0))
                        worst[name][kind] = (max(ms, 1000 * dt), poses + (est is not None))
                        continue
                    if kind == "empty":
                        times_empty[name].append(dt)
                        false_poses[name] += est is not None
                        continue
                    if kind == "blur":
                        times_blur[name].append(dt)
                        found_blur[name] += est is not None
                        continue
                    times[name].append(dt)
                    found[name] += est is not None
                    for k, v in tr.timings.items():
                        stages[name].setdefault(k, []).append(v)
                bar.update()
    ref = "paper" if "paper" in trackers else "paper-classical"
    res = {"conf": dict(c), "reference": ref, "configs": {}}
    for name in trackers:
        med = float(np.median(times[name]))
        res["configs"][name] = {
            "median_ms": 1000 * med,
            "fps": 1.0 / med,
            "speed_vs_reference": float(np.median(times[ref]) / med),
            "stages_ms": {k: 1000 * float(np.median(v)) for k, v in stages[name].items()},
            "found": found[name] / len(times[name]),
            "blur_25_ms": 1000 * float(np.median(times_blur[name])) if times_blur[name] else float("nan"),
            "blur_25_found": found_blur[name] / len(times_blur[name]) if times_blur[name] else float("nan"),
            "marker_free_ms": 1000 * float(np.median(times_empty[name])) if times_empty[name] else float("nan"),
            "false_poses": false_poses[name],
            "inconsistent": {k: {"worst_ms": ms, "poses": p} for k, (ms, p) in worst[name].items()},
        }
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if out:
        write_json(out, res)
    return res


def report(res: dict) -> str:
    """The benchmark as a Markdown table."""
    lines = [
        f"Stereo 1280x1024 pairs, median over {res['conf']['pairs'] * (res['conf']['repeats'] - 1)} runs per configuration "
        f"(interleaved); speed relative to **{res['reference']}**; peak memory of the process {res['peak_rss_mb']:.0f} MB.",
        "",
        "| configuration | ms / pair | FPS | speed vs reference | stages (ms) | found | 25 px blur: ms / pair (found) | marker-free ms / pair |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in res["configs"].items():
        st = ", ".join(f"{k} {v:.1f}" for k, v in r["stages_ms"].items() if k != "total")
        free = f"{r['marker_free_ms']:.1f}" + (f" ({r['false_poses']} false poses)" if r["false_poses"] else "")
        blur = f"{r.get('blur_25_ms', float('nan')):.1f} ({r.get('blur_25_found', float('nan')):.2f})"
        lines.append(
            f"| {name} | {r['median_ms']:.1f} | {r['fps']:.1f} | {r['speed_vs_reference']:.2f}x | {st} | {r['found']:.2f} | {blur} | {free} |"
        )
    kinds = list(dict.fromkeys(k for r in res["configs"].values() for k in r.get("inconsistent", {})))
    if kinds:
        runs = res["conf"]["repeats"] - 1
        lines += [
            "",
            f"Inconsistent pairs (no marker pose explains them): the worst time of {runs} runs per pair, ms "
            "(poses returned, where any; each kind is built from the first two pairs).",
            "",
            "| configuration | " + " | ".join(kinds) + " | worst |",
            "|---|" + "---|" * (len(kinds) + 1),
        ]
        for name, r in res["configs"].items():
            inc = r.get("inconsistent", {})
            cells = [
                f"{inc[k]['worst_ms']:.0f}" + (f" ({inc[k]['poses']} poses)" if inc[k]["poses"] else "") if k in inc else "—" for k in kinds
            ]
            lines.append(
                f"| {name} | " + " | ".join(cells) + f" | {max((v['worst_ms'] for v in inc.values()), default=float('nan')):.0f} |"
            )
    return "\n".join(lines)


__all__ = ["default_conf", "main", "report"]
