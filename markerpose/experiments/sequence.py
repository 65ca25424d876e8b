"""``markerpose bench --sequence``: a hand-held-like stereo video, tracked and detected.

A 60 frames/s sequence of the default rig (``frames``, 240 by default: four seconds) in
five segments: the marker held still (fresh sensor noise every frame: the jitter), moved
by hand, moved fast (the motion itself blurs each view, for half of the frame interval),
gone from both views and back, and moved slowly in the dark (α 0.0625). One clutter
background per camera for the whole sequence, as a fixed scene would give. Segments
join by a jump of the pose (a test of losing and finding the marker again). In one run,
on the same frames: ``MarkerPose.track`` (the default preset), ``MarkerPose.estimate``
(the default, cold) and the paper's configuration (cold).

Each method runs the whole sequence as a live stream: the frames are rendered first (their
images held in memory, ~2.6 MB a frame), then handed to the method on the stream's clock
(frame k at k / fps from the stream's start; a call that is late takes its frame at
once). The methods run one after the other, in ``passes`` passes whose order alternates
(track, estimate, paper, then paper, estimate, track), so that a change of the machine's
speed during the run affects them alike. The statistics pool the passes' latencies; the
plot shows each frame's mean. A method called after a long pause is slower on its first
call: a stream calls it every frame, and so does this benchmark.

``main(conf, out_dir) -> dict`` writes ``report.md``, ``results.json`` and
``sequence.png`` (latency and error along the sequence) into ``out_dir``.
"""

from __future__ import annotations

import gc
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_json
from ..geometry import nearest_rotation, rotation_angle
from ..marker import Marker
from ..synth import Imaging, clutter_background, look_at_pose, render_stereo
from .configs import build, settings

default_conf = {
    "frames": 240,  # at 60 frames/s
    "fps": 60.0,
    "exposure": 0.5,  # fraction of the frame interval the shutter is open (the motion blur)
    "seed": 0,
    "threads": None,  # the networks' inference threads (None: every core)
    "passes": 2,  # passes over the sequence per method, in alternating order (the statistics pool them)
    "pace": True,  # hand each method the frames at the stream's rate (False: back to back)
    "preset": "default",  # the configuration (a preset or an ablation) of track and estimate (the paper's is the reference)
}
# Fractions of the sequence: still, by hand, fast, gone, dark.
SEGMENTS = (("static", 0.25), ("hand-held", 0.25), ("fast", 0.125), ("out of view", 0.125), ("dark", 0.25))
METHODS = ("track", "estimate", "paper")


def segments(n: int) -> list[str]:
    """The segment name of each of ``n`` frames."""
    names, edges = [s for s, _ in SEGMENTS], np.cumsum([0.0] + [f for _, f in SEGMENTS]) * n
    return [names[min(int(np.searchsorted(edges, k, side="right")) - 1, len(names) - 1)] for k in range(n)]


def trajectory(n: int, fps: float) -> tuple[list[np.ndarray], list[str]]:
    """T_left_marker of each frame and its segment: small smooth motions about a working
    pose 560 mm away, 40 mm/s by hand, ~500 mm/s fast, 700 mm to the side while gone."""
    seg = segments(n)
    out = []
    for k, s in enumerate(seg):
        t = k / fps
        x, y, z, tilt, roll = -5.0, 0.0, 560.0, 30.0, 10.0
        if s == "hand-held":
            x += 15 * np.sin(2 * np.pi * 0.4 * t)
            y += 8 * np.sin(2 * np.pi * 0.55 * t)
            z += 10 * np.sin(2 * np.pi * 0.3 * t)
            roll += 4 * np.sin(2 * np.pi * 0.5 * t)
        elif s == "fast":
            x += 40 * np.sin(2 * np.pi * 2.0 * t)
            roll += 10 * np.sin(2 * np.pi * 2.0 * t)
        elif s == "out of view":
            x += 700.0
        elif s == "dark":
            x += 10 * np.sin(2 * np.pi * 0.3 * t)
            tilt += 5 * np.sin(2 * np.pi * 0.2 * t)
        T = look_at_pose([x, y, z], tilt, 45.0, roll)
        out.append(T)
    return out, seg


def _blur(rig: StereoRig, marker: Marker, T_prev: np.ndarray, T: np.ndarray, exposure: float) -> list[tuple[float, float]]:
    """Per view, (length px, angle deg) of the plate centre's image motion while the shutter is open."""
    c = marker.points3d.mean(0)
    a = rig.project((T_prev[:3, :3] @ c + T_prev[:3, 3])[None])[:, 0]
    b = rig.project((T[:3, :3] @ c + T[:3, 3])[None])[:, 0]
    d = (b - a) * exposure
    return [(float(np.hypot(*v)), float(np.degrees(np.arctan2(v[1], v[0])))) for v in d]


def render(conf: dict, rig: StereoRig, marker: Marker, progress: bool = True):
    """Yield (frame, segment) for the whole sequence (deterministic for ``conf["seed"]``)."""
    rng = np.random.default_rng(conf["seed"])
    poses, seg = trajectory(conf["frames"], conf["fps"])
    ratio = marker.inner_radius / marker.outer_radius
    bgs = tuple(clutter_background(cam.image_size, rng, ring_distractors=4, ring_ratio=ratio) for cam in rig.cameras)
    for k in tqdm(range(len(poses)), desc="render", unit="frame", disable=not progress):
        jump = k == 0 or seg[k] != seg[k - 1]  # segments join by a jump: no motion to blur
        blur = [(0.0, 0.0)] * 2 if jump else _blur(rig, marker, poses[k - 1], poses[k], conf["exposure"])
        alpha = 0.0625 if seg[k] == "dark" else 0.8
        imaging = tuple(Imaging(alpha=alpha, motion_blur=L, motion_angle=a) for L, a in blur)
        yield render_stereo(rig, poses[k], marker, imaging, bgs, seed=rng), seg[k], max(L for L, _ in blur)


def main(conf: dict | None = None, out_dir: str | Path | None = "markerpose-sequence", progress: bool = True) -> dict:
    """Render the sequence, run the three methods on every frame, report."""
    c = settings(conf, default_conf, "sequence")
    if int(c["frames"]) < 40:
        raise ValueError(f"frames must be >= 40 (five segments), got {c['frames']}")
    passes = int(c["passes"])
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {c['passes']}")
    rig, marker = StereoRig.default(), Marker()
    opts = {} if c["threads"] is None else {"threads": int(c["threads"])}
    runners = {
        "track": build(c["preset"], rig, marker, **opts),
        "estimate": build(c["preset"], rig, marker, **opts),
        "paper": build("paper", rig, marker, **opts),
    }
    calls = {"track": runners["track"].track, "estimate": runners["estimate"].estimate, "paper": runners["paper"].estimate}
    # The images and the truth only (a rendered frame also holds its ring masks).
    frames, rows = [], []
    for k, (f, sg, b) in enumerate(render(c, rig, marker, progress)):
        frames.append((f.images, f.T_left_marker))
        rows.append({"frame": k, "segment": sg, "visible": all(v.in_image.all() for v in f.views), "blur_px": b})
    for m in METHODS:  # warm-up: lazy initialisation and caches, not timed (track's prior is reset below)
        runners[m].estimate(*frames[0][0])
    # The rendered frames are this benchmark's, not what a stream holds: Python's cyclic
    # collector skips them, as a MarkerPose has it skip what was alive when it was built.
    gc.collect()
    gc.freeze()
    period = 1.0 / float(c["fps"]) if c["pace"] else 0.0
    for p in tqdm(range(passes), desc="passes", unit="pass", disable=not progress):
        for m in METHODS if p % 2 == 0 else METHODS[::-1]:
            runners[m].reset()  # a new stream (track's prior; the others keep none)
            start = time.perf_counter()
            for k, (images, T) in enumerate(frames):
                wait = start + k * period - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                t0 = time.perf_counter()
                est = calls[m](*images)
                dt = 1000 * (time.perf_counter() - t0)
                if p == 0:
                    rows[k][m] = {
                        "ms": 0.0,
                        "ms_passes": [],
                        "found": est is not None,
                        "source": None if est is None else est.source,
                        "t_mm": None if est is None else float(np.linalg.norm(est.t - T[:3, 3])),
                        "r_deg": None if est is None else float(np.degrees(rotation_angle(nearest_rotation(est.R), T[:3, :3]))),
                        "t": None if est is None else est.t.tolist(),
                        "R": None if est is None else nearest_rotation(est.R).tolist(),
                    }
                rows[k][m]["ms_passes"].append(dt)
                rows[k][m]["ms"] = float(np.mean(rows[k][m]["ms_passes"]))
    res = {"conf": c, "summary": {m: summarize(rows, m) for m in METHODS}, "frames": rows}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "results.json", res)
        (out / "report.md").write_text(report(res))
        plot(rows, out / "sequence.png")
    return res


def _passes(rows: list[dict], m: str) -> list[float]:
    """Every latency of method ``m`` on ``rows``, all passes pooled (ms)."""
    return [v for r in rows for v in r[m].get("ms_passes", [r[m]["ms"]])]


def summarize(rows: list[dict], m: str) -> dict:
    """Latency, detection, errors, jitter, false poses and re-acquisition of method ``m``."""
    ms = np.array(_passes(rows[1:], m))  # the first frame also initialises
    vis = [r for r in rows if r["visible"]]
    found = [r for r in vis if r[m]["found"]]
    t_err = np.array([r[m]["t_mm"] for r in found]) if found else np.array([np.inf])
    r_err = np.array([r[m]["r_deg"] for r in found]) if found else np.array([np.inf])
    static = [r for r in rows if r["segment"] == "static" and r[m]["found"]]
    jitter_t = jitter_r = None
    if len(static) > 2:
        t = np.array([r[m]["t"] for r in static])
        jitter_t = float(np.sqrt(np.mean(np.sum((t - t.mean(0)) ** 2, axis=1))))
        Rs = np.array([r[m]["R"] for r in static])
        R_mean = nearest_rotation(Rs.sum(0))
        jitter_r = float(np.sqrt(np.mean([np.degrees(rotation_angle(R, R_mean)) ** 2 for R in Rs])))
    back = [r["frame"] for r in rows if r["visible"] and r["frame"] > 0 and not rows[r["frame"] - 1]["visible"]]
    reacquire = None
    if back:
        k0 = back[0]
        later = [r["frame"] - k0 for r in rows[k0:] if r[m]["found"]]
        reacquire = later[0] if later else None
    by_seg = {}
    for s, _ in SEGMENTS:
        seg_rows = [r for r in rows[1:] if r["segment"] == s]
        if seg_rows:
            v = [r for r in seg_rows if r["visible"]]
            by_seg[s] = {
                "median_ms": float(np.median(_passes(seg_rows, m))),
                "detected": float(np.mean([r[m]["found"] for r in v])) if v else None,
            }
    return {
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "fps": float(1000 / np.median(ms)),
        "detected": len(found) / max(len(vis), 1),
        "tracked_share": float(np.mean([r[m]["source"] == "tracked" for r in found])) if found else 0.0,
        "t_median_mm": float(np.median(t_err)),
        "t_p95_mm": float(np.percentile(t_err, 95)),
        "r_median_deg": float(np.median(r_err)),
        "wrong_poses": int(np.sum(t_err > 1.0)) if found else 0,
        "false_poses": sum(r[m]["found"] for r in rows if not r["visible"]),
        "jitter_mm": jitter_t,
        "jitter_deg": jitter_r,
        "frames_to_reacquire": reacquire,
        "by_segment": by_seg,
    }


def _f(x, nd=3):
    return "—" if x is None else f"{x:.{nd}f}"


def report(res: dict) -> str:
    """Markdown of :func:`main`'s result."""
    c, s = res["conf"], res["summary"]
    n = len(res["frames"])
    lines = [
        f"# Sequence benchmark: {n} stereo frames at {c['fps']:g} frames/s",
        "",
        "Segments: "
        + ", ".join(f"{name} ({int(round(f * n))} frames)" for name, f in SEGMENTS)
        + f". `track` is the `{c.get('preset', 'default')}` configuration's `track()`; `estimate` is the same configuration detecting every frame cold;"
        ' `paper` is `MarkerPose(rig, preset="paper").estimate`. All three on the same frames, each as a live stream '
        + (
            f"(a frame handed over every {1000 / c['fps']:.1f} ms, or as soon as the method is free)"
            if c.get("pace", True)
            else "(back to back)"
        )
        + f"; {c.get('passes', 1)} pass(es) per method in alternating order, the latencies of all passes pooled.",
        "",
        "| method | median ms | p99 ms | max ms | FPS | speed vs paper | detected | tracked share | translation error median / p95 (mm) "
        "| rotation error median (°) | static jitter: origin RMS (mm) / rotation RMS (°) | wrong poses (> 1 mm) | false poses | frames to re-acquire |",
        "|" + "---|" * 14,
    ]
    ref = s["paper"]["median_ms"]
    for m in METHODS:
        r = s[m]
        lines.append(
            f"| {m} | {r['median_ms']:.1f} | {r['p99_ms']:.1f} | {r['max_ms']:.1f} | {r['fps']:.1f} | {ref / r['median_ms']:.2f}x | "
            f"{100 * r['detected']:.1f} % | {100 * r['tracked_share']:.0f} % | {_f(r['t_median_mm'], 4)} / {_f(r['t_p95_mm'], 4)} | "
            f"{_f(r['r_median_deg'], 4)} | {_f(r['jitter_mm'], 4)} / {_f(r['jitter_deg'], 4)} | {r['wrong_poses']} | {r['false_poses']} | "
            f"{_f(r['frames_to_reacquire'], 0) if r['frames_to_reacquire'] is not None else 'never'} |"
        )
    lines += [
        "",
        "By segment: median ms per frame (detected share of the frames where the marker is fully in both views).",
        "",
        "| segment | " + " | ".join(METHODS) + " |",
        "|---|" + "---|" * len(METHODS),
    ]
    for seg, _ in SEGMENTS:
        cells = []
        for m in METHODS:
            b = s[m]["by_segment"].get(seg)
            share = "—" if b is None or b["detected"] is None else f"{100 * b['detected']:.0f} %"
            cells.append("—" if b is None else f"{b['median_ms']:.1f} ({share})")
        lines.append(f"| {seg} | " + " | ".join(cells) + " |")
    blur = [r["blur_px"] for r in res["frames"] if r["segment"] == "fast"]
    if blur:
        lines += ["", f"Motion blur in the fast segment: up to {max(blur):.1f} px (median {np.median(blur):.1f} px)."]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> Path:
    """Latency and translation error of each method along the sequence, segments shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.array([r["frame"] for r in rows])
    fig, axes = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True)
    for m in METHODS:
        axes[0].plot(k, [r[m]["ms"] for r in rows], lw=1, label=m)
        err = [np.nan if r[m]["t_mm"] is None else max(r[m]["t_mm"], 1e-5) for r in rows]
        axes[1].plot(k, err, lw=1, marker=".", ms=3, label=m)
    segs = [r["segment"] for r in rows]
    start = 0
    for i in range(1, len(segs) + 1):
        if i == len(segs) or segs[i] != segs[start]:
            for ax in axes:
                ax.axvspan(start - 0.5, i - 0.5, color="0.92" if len(set(segs[:i])) % 2 else "white", zorder=0)
            axes[0].text((start + i) / 2, 0.97, segs[start], transform=axes[0].get_xaxis_transform(), ha="center", va="top", fontsize=8)
            start = i
    axes[0].set_yscale("log")
    axes[0].set_ylabel("time per stereo pair (ms)")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("translation error (mm)")
    axes[1].set_xlabel("frame (60 frames/s)")
    for ax in axes:
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=3, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["METHODS", "SEGMENTS", "default_conf", "main", "plot", "render", "report", "segments", "summarize", "trajectory"]
