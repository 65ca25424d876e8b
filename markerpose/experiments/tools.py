"""Several tools at once, on held-out rendered pairs and a rendered video.

``markerpose eval tools`` renders pairs of the default rig with 2-4 tools of one tool set
(:func:`markerpose.tools.tool_set`) in view at once, each anywhere in the working volume
(350-800 mm, tilt up to 60°) under the standard set's conditions (gain α in [0.25, 1],
motion blur ≤ 9 px), a share of them placed behind another tool so that its plate hides
part of their rings, plus marker-free pairs. Each configuration's
:meth:`~markerpose.MarkerPose.estimate_all` runs on every pair, and, for the same tool at
the same pose under the same conditions alone in the pair, the single-tool
:meth:`~markerpose.MarkerPose.estimate`: the reference for the accuracy.

A tool's pose is *right* when its six centres (bias-corrected, three a view) lie within
``tolerance_px`` of the projections of its true ring centres; a pose given to one tool on
another tool's rings is a *swap*; any other pose a *false pose*. Detection counts over
the fully visible tools (every ring inside both images, no part hidden); tools partly
hidden are reported apart (found right, or not at all, is what is asked of them).

The video (:func:`video`): three tools moving independently, the third leaving the view
and coming back, tracked with :meth:`~markerpose.MarkerPose.track_all`. The speed
(:func:`speed`): a cold pair with three tools against a single tool's cold pair, and
tracking 1, 2 and 3 tools through the same video, timed in one run.
"""

from __future__ import annotations

import itertools
import time
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_json
from ..geometry import nearest_rotation, rotation_angle
from ..pipeline import MarkerPose
from ..synth import Imaging, clutter_background, look_at_pose, render_stereo
from ..synth.render import render_tools
from ..tools import least_difference, tool_set
from .endtoend import marker_free_pairs

default_conf = {
    "pairs": 100,  # pairs with tools
    "free": 50,  # marker-free pairs
    "tools": 4,  # the tool set's size; each pair shows 2 to this many
    "configs": ("default", "classical"),  # presets (the paper's decoded detector takes one marker)
    "tolerance_px": 3.0,
    "hidden_share": 0.3,  # pairs where one tool is placed behind another
    "seed": 3200,
    "frames": 120,  # the video's pairs (0: no video)
    "speed_pairs": 20,  # cold pairs timed (0: no timing)
}


def _pose(rng: np.random.Generator, marker, z: float | None = None) -> np.ndarray:
    """A pose around the rig's convergence line, wider than the end-to-end sets place the
    marker (several tools need the room; :func:`_inside` keeps those both cameras see)."""
    z = rng.uniform(350.0, 800.0) if z is None else z
    T = look_at_pose([0, 0, z], rng.uniform(0, 60), rng.uniform(0, 360), rng.uniform(0, 360))
    T[:3, 3] = [rng.uniform(-0.2, 0.2) * z - 0.12 * (z - 560), rng.uniform(-0.25, 0.25) * z, z]
    T[:3, 3] -= T[:3, :3] @ marker.points3d.mean(0)
    return T


def _plate_centre(marker, T: np.ndarray) -> np.ndarray:
    x0, y0, x1, y1 = marker.plate
    return T[:3, :3] @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + T[:3, 3]


def _apart(placed: list, marker, T: np.ndarray) -> bool:
    """Whether the tool at ``T`` keeps clear of the plates ``placed`` in 3D (no plate
    through another): centres farther apart than their plates' half diagonals."""
    x0, y0, x1, y1 = marker.plate
    r = 0.5 * np.hypot(x1 - x0, y1 - y0)
    for m, Tm in placed:
        a0, b0, a1, b1 = m.plate
        if np.linalg.norm(_plate_centre(marker, T) - _plate_centre(m, Tm)) < r + 0.5 * np.hypot(a1 - a0, b1 - b0):
            return False
    return True


def _outlines(rig: StereoRig, marker, T: np.ndarray) -> list:
    """Per view, the plate's projected corners (4, 2) float32."""
    P = marker.plate_corners3d @ T[:3, :3].T + T[:3, 3]
    return [cam.project(X).astype(np.float32) for cam, X in zip(rig.cameras, (P, rig.to_right(P)))]


def _inside(rig: StereoRig, marker, T: np.ndarray) -> bool:
    """Whether the whole plate lies inside both images, in front of both cameras."""
    P = marker.plate_corners3d @ T[:3, :3].T + T[:3, 3]
    if P[:, 2].min() <= 0 or rig.to_right(P)[:, 2].min() <= 0:
        return False
    return all(np.all((uv >= 0) & (uv <= np.array(cam.image_size) - 1)) for cam, uv in zip(rig.cameras, _outlines(rig, marker, T)))


def _overlap(rig: StereoRig, a: tuple, b: tuple) -> bool:
    """Whether the plates of (marker, T) ``a`` and ``b`` overlap in either view."""
    import cv2

    return any(cv2.intersectConvexConvex(pa, pb)[0] > 0 for pa, pb in zip(_outlines(rig, *a), _outlines(rig, *b)))


def _behind(rng: np.random.Generator, front, T_front: np.ndarray, marker) -> np.ndarray:
    """A pose of ``marker`` behind the tool at ``T_front``, shifted sideways by about half
    a plate, so that the front plate may hide part of its rings."""
    T = _pose(rng, marker, z=T_front[2, 3] + rng.uniform(60, 160))
    c = _plate_centre(front, T_front)
    shift = rng.uniform(25, 50) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a), 0.0])
    T[:2, 3] += (c * T[2, 3] / c[2])[:2] + shift[:2] - _plate_centre(marker, T)[:2]
    return T


def scenes(n: int, rig: StereoRig, tools: list, seed, hidden_share: float = 0.3):
    """Yield (ToolsFrame, backgrounds, imaging, conditions) for ``n`` held-out pairs with 2
    to ``len(tools)`` tools, every ring of every tool inside both images, the plates apart
    in both views but in the ``hidden_share`` of the pairs where the second tool is placed
    behind the first."""
    rng = np.random.default_rng(seed)
    made = 0
    while made < n:
        k = int(rng.integers(2, len(tools) + 1))
        chosen = [tools[i] for i in rng.choice(len(tools), k, replace=False)]
        hide = rng.random() < hidden_share
        placed: list = []
        while len(placed) < k:  # as many tools as drawn: placed afresh until they all fit
            placed = []
            for j, m in enumerate(chosen):
                for _ in range(20):
                    T = _behind(rng, *placed[0], m) if hide and j == 1 else _pose(rng, m)
                    # Apart in 3D; and in the images too, but for the one placed behind another.
                    clear = all(not _overlap(rig, p, (m, T)) for p in placed[int(hide and j == 1) :])
                    if _inside(rig, m, T) and _apart(placed, m, T) and clear:
                        placed.append((m, T))
                        break
                if len(placed) <= j:
                    break
        alpha, blur, angle = rng.uniform(0.25, 1.0), rng.uniform(0.0, 9.0), rng.uniform(0, 180)
        imaging = Imaging(alpha=alpha, motion_blur=blur, motion_angle=angle)
        bgs = tuple(clutter_background(c.image_size, rng) for c in rig.cameras)
        try:
            frame = render_tools(rig, placed, imaging, bgs, seed=rng)
        except ValueError:  # a plate behind a camera
            continue
        if not all(v.in_image.all() for t in frame.truths.values() for v in t.views):
            continue
        made += 1
        yield frame, bgs, imaging, {"tools": k, "hidden": bool(hide), "alpha": alpha, "blur": blur}


def judge(est, truth, others: dict, tol: float) -> str:
    """ "right", "swap" (on another tool's rings) or "false" for a pose given to a tool."""
    centres = np.concatenate(list(est.centers))
    if np.all(np.linalg.norm(centres - np.concatenate([v.centers for v in truth.views]), axis=1) <= tol):
        return "right"
    for other in others.values():
        true = np.concatenate([v.centers for v in other.views])
        if np.all(np.min(np.linalg.norm(centres[:, None] - true[None], axis=2), axis=1) <= tol):
            return "swap"
    return "false"


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(np.rad2deg(rotation_angle(nearest_rotation(T[:3, :3]), T_true[:3, :3])))


def _pair_rows(name: str, trackers: dict, singles: dict, frame, bgs, imaging, tol: float, rig) -> tuple[list, list]:
    """Per tool of one pair, one row (outcome, errors, the single-tool reference's); and the
    relative pose errors of the pairs of tools both found right."""
    multi = trackers[name].estimate_all(*frame.images)
    rows, rel = [], []
    for tool, truth in frame.truths.items():
        others = {k: v for k, v in frame.truths.items() if k != tool}
        est = multi.get(tool)
        row = {
            "tool": tool,
            "full": truth.fully_visible,
            "visible": float(truth.visible.min()),  # the least visible ring's share
            "outcome": "missed" if est is None else judge(est, truth, others, tol),
        }
        if est is None and truth.fully_visible:
            row["why"] = trackers[name].whys.get(tool)
        if row["outcome"] == "right":
            row["t_mm"], row["r_deg"] = _errors(est.T, truth.T_left_marker)
        if truth.fully_visible:  # the same tool, pose and conditions, alone in the pair
            alone = render_stereo(rig, truth.T_left_marker, truth.marker, imaging, bgs, seed=zlib.crc32(tool.encode()))
            one = singles[name][tool].estimate(*alone.images)
            if one is not None and judge(one, truth, {}, tol) == "right":
                row["single_t_mm"] = _errors(one.T, truth.T_left_marker)[0]
        rows.append(row)
    for a, b in itertools.combinations([r["tool"] for r in rows if r["outcome"] == "right"], 2):
        Ta, Tb = frame.truths[a].T_left_marker, frame.truths[b].T_left_marker
        rel.append(_errors(np.linalg.inv(multi[a].T) @ multi[b].T, np.linalg.inv(Ta) @ Tb))
    return rows, rel


def summarize(rows: list, rel: list, free: list) -> dict:
    """Per tool and over all tools: detection of fully visible tools, partly hidden ones,
    swaps, false poses, translation error against the single-tool reference."""

    def med(v):
        return float(np.median(v)) if len(v) else float("nan")

    def stats(rs):
        full = [r for r in rs if r["full"]]
        hidden = [r for r in rs if not r["full"]]
        t = [r["t_mm"] for r in full if "t_mm" in r]
        both = [r for r in full if "t_mm" in r and "single_t_mm" in r]
        most = [r for r in hidden if r["visible"] >= 0.75]
        return {
            "fully_visible": len(full),
            "detected": float(np.mean([r["outcome"] == "right" for r in full])) if full else float("nan"),
            "partly_hidden": len(hidden),
            "hidden_found_right": float(np.mean([r["outcome"] == "right" for r in hidden])) if hidden else float("nan"),
            "mostly_visible": len(most),  # partly hidden, every ring at least three quarters visible
            "mostly_visible_found_right": float(np.mean([r["outcome"] == "right" for r in most])) if most else float("nan"),
            "missed": [r.get("why") for r in full if r["outcome"] == "missed"],
            "swaps": sum(r["outcome"] == "swap" for r in rs),
            "false_poses": sum(r["outcome"] == "false" for r in rs),
            "t_median_mm": med(t),
            "t_median_mm_both": med([r["t_mm"] for r in both]),
            "single_t_median_mm_both": med([r["single_t_mm"] for r in both]),
            "r_median_deg": med([r["r_deg"] for r in full if "r_deg" in r]),
        }

    names = sorted({r["tool"] for r in rows})
    rel = np.array(rel).reshape(-1, 2)
    return {
        "all": stats(rows),
        "per_tool": {n: stats([r for r in rows if r["tool"] == n]) for n in names},
        "relative": {
            "pairs": len(rel),
            "t_median_mm": med(rel[:, 0]),
            "t_p95_mm": float(np.percentile(rel[:, 0], 95)) if len(rel) else float("nan"),
            "r_median_deg": med(rel[:, 1]),
        },
        "marker_free": {"pairs": len(free), "false_poses": int(sum(free))},
    }


def main(conf: dict | None = None, out: str | Path | None = None, progress: bool = True) -> dict:
    """Every configuration of ``conf["configs"]`` on the held-out tool pairs and the
    marker-free pairs; then the video and the speed (the default preset). With ``out``
    (a folder): results.json, report.md, the tracked video tools.mp4 and its plot
    tools-video.png."""
    c = {**default_conf, **(conf or {})}
    rig = StereoRig.default()
    tools = tool_set(int(c["tools"]))
    trackers = {name: MarkerPose(rig, markers=tools, preset=name) for name in c["configs"]}
    singles = {name: {t.name: MarkerPose(rig, t, preset=name) for t in tools} for name in c["configs"]}
    rows: dict = {n: [] for n in trackers}
    rel: dict = {n: [] for n in trackers}
    conds = []
    for frame, bgs, imaging, cond in tqdm(
        scenes(c["pairs"], rig, tools, c["seed"], c["hidden_share"]), total=c["pairs"], desc="tools", unit="pair", disable=not progress
    ):
        conds.append(cond)
        for name in trackers:
            r, e = _pair_rows(name, trackers, singles, frame, bgs, imaging, c["tolerance_px"], rig)
            rows[name] += r
            rel[name] += e
    free: dict = {n: [] for n in trackers}
    spec = {"alpha": (0.25, 1.0), "blur": (0.0, 9.0)}
    rng = np.random.default_rng(c["seed"] + 1)
    for frame, _ in tqdm(
        marker_free_pairs(spec, c["free"], rig, tools[0], rng), total=c["free"], desc="marker-free", unit="pair", disable=not progress
    ):
        for name, tr in trackers.items():
            free[name].append(len(tr.estimate_all(*frame.images)) > 0)
    res = {
        "conf": {k: list(v) if isinstance(v, tuple) else v for k, v in c.items()},
        "tools": [t.to_dict() for t in tools],
        "least_difference_mm": least_difference(tools),
        "pairs_by_count": {str(k): sum(cd["tools"] == k for cd in conds) for k in range(2, len(tools) + 1)},
        "configs": {n: summarize(rows[n], rel[n], free[n]) for n in trackers},
    }
    if c["frames"] or c["speed_pairs"]:
        frames = video(rig, tools, max(int(c["frames"]), 30), seed=c["seed"] + 100)
        if c["frames"]:
            res["video"] = track_video(MarkerPose(rig, markers=tools[:3]), frames, c["tolerance_px"])
            res["video"]["frames"] = len(frames)
        if c["speed_pairs"]:
            res["speed"] = speed(rig, tools, frames, c["speed_pairs"], c["seed"] + 200, progress)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "results.json", res)
        (out / "report.md").write_text(report(res) + "\n")
        if "video" in res:
            write_video(out / "tools.mp4", rig, tools[:3], frames)
            plot_video(res["video"], out / "tools-video.png")
    return res


def plot_video(video: dict, path: Path) -> Path:
    """Per tool along the video: how each pair's pose came (tracked, detected, missed while
    fully visible or partly hidden, out of view, wrong) and its translation error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tools = [n for n in video if n != "frames"]
    colors = {
        "tracked": "tab:green",
        "detected": "tab:blue",
        "missed": "tab:orange",
        "hidden": "#f7c98f",
        "out of view": "0.85",
        "swap": "red",
        "false": "red",
    }
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5), sharex=True, gridspec_kw={"height_ratios": [1, 2]})
    for row, name in enumerate(tools):
        for k, what, _ in video[name]["log"]:
            top.barh(row, 1, left=k - 0.5, color=colors[what], height=0.7)
        log = [(k, t) for k, _, t in video[name]["log"] if t is not None]
        if log:
            bottom.semilogy(*zip(*log), ".", ms=4, label=name)
    top.set_yticks(range(len(tools)), tools)
    top.invert_yaxis()
    top.legend(
        handles=[plt.Rectangle((0, 0), 1, 1, color=colors[k]) for k in ("tracked", "detected", "missed", "hidden", "out of view", "false")],
        labels=["tracked", "detected", "missed", "missed, partly hidden", "out of view", "wrong"],
        ncol=6,
        fontsize=8,
        loc="lower center",
        bbox_to_anchor=(0.5, 1.0),
    )
    bottom.set_xlabel("pair")
    bottom.set_ylabel("translation error (mm)")
    bottom.legend(fontsize=8)
    bottom.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_video(path: Path, rig: StereoRig, tools: list, frames: list) -> Path:
    """The video's pairs tracked again, each tool's axes and name drawn (what ``markerpose
    track --tools ... --video`` writes)."""
    from ..video import VideoSink

    tracker = MarkerPose(rig, markers=tools)
    sink = VideoSink(path, rig, 30.0)
    try:
        for k, f in enumerate(frames):
            sink(k, k / 30.0, *f.images, tracker.track_all(*f.images))
    finally:
        sink.close()
    return path


# --- the video -------------------------------------------------------------------------
def _path(k: int, frames: int, phase: float, centre: np.ndarray, marker) -> np.ndarray:
    """A smooth pose along a tool's own loop (position and orientation change every frame)."""
    s = 2 * np.pi * k / frames + phase
    T = look_at_pose(
        centre + np.array([35 * np.sin(s), 10 * np.sin(2 * s + 1), 40 * np.cos(s)]),
        25 + 15 * np.sin(s + 2),
        (60 * phase + 40 * s) % 360,
        (90 * phase + 30 * np.sin(s)) % 360,
    )
    T[:3, 3] -= T[:3, :3] @ marker.points3d.mean(0)
    return T


OUT_OF_VIEW = (0.35, 0.55)  # the share of the video during which the third tool is out of view


def video(rig: StereoRig, tools: list, frames: int = 120, seed: int = 3300) -> list:
    """``frames`` pairs (ToolsFrame) of the first three ``tools`` moving independently, the
    third out of both views for the :data:`OUT_OF_VIEW` share of the video; the cameras'
    backgrounds fixed, the sensor's noise new each frame."""
    rng = np.random.default_rng(seed)
    bgs = tuple(clutter_background(c.image_size, rng) for c in rig.cameras)
    centres = [np.array([-25.0, -95, 760]), np.array([-5.0, 0, 740]), np.array([-45.0, 95, 720])]
    out = []
    for k in range(frames):
        poses = [(m, _path(k, frames, 2.1 * j, centres[j], m)) for j, m in enumerate(tools[:3])]
        if OUT_OF_VIEW[0] <= k / frames < OUT_OF_VIEW[1]:
            poses = poses[:2]
        out.append(render_tools(rig, poses, Imaging(motion_blur=2.0, motion_angle=30.0), bgs, seed=rng))
    return out


def track_video(tracker: MarkerPose, frames: list, tol: float = 3.0) -> dict:
    """``track_all`` through ``frames``: per tool the frames in view (fully visible), found
    right, swaps, false poses, and the frames it was missed though in view; and whether
    each re-entry was found on its first frame back."""
    tracker.reset()
    per = {
        n: {"in_view": 0, "right": 0, "swaps": 0, "false_poses": 0, "missed_frames": [], "reentries": [], "tracked": 0, "log": []}
        for n in tracker.tools
    }
    for k, f in enumerate(frames):
        found = tracker.track_all(*f.images)
        for n, p in per.items():
            truth = f.truths.get(n)
            est = found.get(n)
            if truth is None:
                if est is not None:
                    p["false_poses"] += 1
                p["log"].append([k, "out of view" if est is None else "false", None])
                continue
            back = k > 0 and n not in frames[k - 1].truths
            outcome = "missed" if est is None else judge(est, truth, {m: t for m, t in f.truths.items() if m != n}, tol)
            if truth.fully_visible:
                p["in_view"] += 1
                if outcome == "missed":
                    p["missed_frames"].append(k)
            p["right"] += outcome == "right"
            p["swaps"] += outcome == "swap"
            p["false_poses"] += outcome == "false"
            p["tracked"] += est is not None and est.source == "tracked"
            t_mm = None if outcome != "right" else _errors(est.T, truth.T_left_marker)[0]
            what = est.source if outcome == "right" else outcome
            p["log"].append([k, "hidden" if what == "missed" and not truth.fully_visible else what, t_mm])
            if back:
                p["reentries"].append({"frame": k, "found": outcome == "right"})
    return per


def speed(rig: StereoRig, tools: list, frames: list, pairs: int = 20, seed: int = 3400, progress: bool = True) -> dict:
    """In one run: the cold pair (``estimate_all``, 3 tools in view) against the first
    tool's cold pair alone (``estimate``), on ``pairs`` scenes in alternating order; and
    ``track_all`` with 1, 2 and 3 tools through the frames of ``frames`` where all three
    are in view (three passes, the three trackers on each pair in turn; the medians of the
    pairs where every tool was tracked, in all and per stage)."""
    three, one = MarkerPose(rig, markers=tools[:3]), MarkerPose(rig, tools[0])
    rng = np.random.default_rng(seed)
    cold = {"three": [], "one": []}
    for frame, bgs, imaging, _ in tqdm(_three_scenes(pairs, rig, tools, rng), total=pairs, desc="cold", unit="pair", disable=not progress):
        alone = render_stereo(rig, frame.truths[tools[0].name].T_left_marker, tools[0], imaging, bgs, seed=rng)
        runs = [("three", three.estimate_all, frame.images), ("one", one.estimate, alone.images)]
        for name, fn, images in runs if len(cold["one"]) % 2 else runs[::-1]:
            times = []
            for _ in range(3):  # the best of three: a timing is a lower bound on a noisy machine
                t = time.perf_counter()
                fn(*images)
                times.append(time.perf_counter() - t)
            best = min(times)
            cold[name].append(best)
    in_view = [f for f in frames if len(f.truths) == 3]
    trackers = {k: MarkerPose(rig, markers=tools[:k]) for k in (1, 2, 3)}
    tracked: dict = {k: [] for k in trackers}
    stages: dict = {k: [] for k in trackers}
    for rep in range(3):
        for tr in trackers.values():
            tr.reset()
        for i, f in enumerate(in_view):  # the three trackers on each pair in turn: the machine's drift is theirs alike
            for k, tr in sorted(trackers.items(), reverse=(rep + i) % 2 == 1):
                t = time.perf_counter()
                found = tr.track_all(*f.images)
                dt = time.perf_counter() - t
                if len(found) == k and all(e.source == "tracked" for e in found.values()):
                    tracked[k].append(dt)
                    stages[k].append(dict(tr.timings))
    med = {k: float(np.median(v)) * 1e3 if v else float("nan") for k, v in tracked.items()}
    names = ("refine", "verify", "solve")
    per_stage = {
        k: {n: float(np.median([st.get(n, 0.0) for st in v])) * 1e3 if v else float("nan") for n in names} for k, v in stages.items()
    }
    return {
        "cold_three_ms": float(np.median(cold["three"])) * 1e3,
        "cold_one_ms": float(np.median(cold["one"])) * 1e3,
        "cold_ratio": float(np.median(cold["three"]) / np.median(cold["one"])),
        "tracked_ms": {str(k): v for k, v in med.items()},
        "tracked_frames": {str(k): len(v) for k, v in tracked.items()},
        "tracked_stages_ms": {str(k): v for k, v in per_stage.items()},
        "per_extra_tool_ms": (med[3] - med[1]) / 2,
        "per_extra_tool_stages_ms": {n: (per_stage[3][n] - per_stage[1][n]) / 2 for n in names},
    }


def _three_scenes(n: int, rig: StereoRig, tools: list, rng: np.random.Generator):
    """Pairs with exactly the first three tools in view, none hidden."""
    made = 0
    for frame, bgs, imaging, cond in scenes(10 * n, rig, tools[:3], rng, hidden_share=0.0):
        if cond["tools"] == 3 and all(t.fully_visible for t in frame.truths.values()):
            made += 1
            yield frame, bgs, imaging, cond
            if made == n:
                return


def report(res: dict) -> str:
    """Markdown tables of :func:`main`'s result."""
    lines = [
        f"Tools: {', '.join(t['name'] for t in res['tools'])} (least layout difference {res['least_difference_mm']:.2f} mm); "
        f"pairs by tools in view: {res['pairs_by_count']}",
        "",
        "| configuration | tool | fully visible | detected | partly hidden: found right (every ring ≥ 75 % visible) | swaps | "
        "false poses | t median (mm) | same pairs: t median / single tool (mm) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in res["configs"].items():
        for tool, st in [*s["per_tool"].items(), ("all", s["all"])]:
            lines.append(
                f"| {name} | {tool} | {st['fully_visible']} | {100 * st['detected']:.1f} % | "
                f"{100 * st['hidden_found_right']:.0f} % of {st['partly_hidden']} ({100 * st['mostly_visible_found_right']:.0f} % of "
                f"{st['mostly_visible']}) | {st['swaps']} | {st['false_poses']} | "
                f"{st['t_median_mm']:.3f} | {st['t_median_mm_both']:.3f} / {st['single_t_median_mm_both']:.3f} |"
            )
    lines += [
        "",
        "| configuration | relative pose: pairs | t median / p95 (mm) | r median (°) | marker-free: false poses |",
        "|---|---|---|---|---|",
    ]
    for name, s in res["configs"].items():
        r, f = s["relative"], s["marker_free"]
        lines.append(
            f"| {name} | {r['pairs']} | {r['t_median_mm']:.3f} / {r['t_p95_mm']:.3f} | {r['r_median_deg']:.3f} | {f['false_poses']} of {f['pairs']} |"
        )
    if "video" in res:
        v = res["video"]
        lines += [
            "",
            f"Video ({v['frames']} pairs, three tools moving, the third out of view for a while), `track_all`:",
            "",
            "| tool | pairs fully in view | found right (all pairs) | missed while fully in view | swaps | false poses | re-entries found on the first pair back |",
            "|---|---|---|---|---|---|---|",
        ]
        for tool, p in v.items():
            if tool == "frames":
                continue
            back = ", ".join(f"pair {r['frame']}: {'yes' if r['found'] else 'no'}" for r in p["reentries"]) or "-"
            lines.append(
                f"| {tool} | {p['in_view']} | {p['right']} | {len(p['missed_frames'])} | {p['swaps']} | {p['false_poses']} | {back} |"
            )
    if "speed" in res:
        sp = res["speed"]
        t = sp["tracked_ms"]
        lines += [
            "",
            "| speed (one run, this machine) | figure |",
            "|---|---|",
            f"| cold pair, 3 tools in view (`estimate_all`) / one tool alone (`estimate`), median ms | "
            f"{sp['cold_three_ms']:.1f} / {sp['cold_one_ms']:.1f} = **{sp['cold_ratio']:.2f}x** |",
            f"| tracked pair, 1 / 2 / 3 tools (`track_all`), median ms | {t['1']:.1f} / {t['2']:.1f} / {t['3']:.1f} |",
            f"| each extra tracked tool, ms | **{sp['per_extra_tool_ms']:.1f}** |",
        ]
        if "per_extra_tool_stages_ms" in sp:
            e = sp["per_extra_tool_stages_ms"]
            lines.append(f"| ... of which edge fits / checks / solve, ms | {e['refine']:.2f} / {e['verify']:.2f} / {e['solve']:.2f} |")
    return "\n".join(lines)


__all__ = ["default_conf", "judge", "main", "report", "scenes", "speed", "summarize", "track_video", "plot_video", "video", "write_video"]
