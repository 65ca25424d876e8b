"""``markerpose eval blur-distance``: the distance c0-c1 under motion blur along it.

When the marker moves along the line c0 -> c1 during the exposure, both rings are smeared
toward and away from each other. A ring fit biased along the motion (an edge fit whose
profiles along the motion never reach the ink or the paper) moves the two centres
unequally, and the triangulated distance c0-c1 comes out too short or too long: a known
length along the motion shows it. Here the same poses (``default_conf``: 450-700 mm,
tilt up to 40°, any roll, so that c0 -> c1 takes every direction in the image) are
rendered with linear motion blur of each length along the image direction of c0 -> c1
in each view, and every configuration's distance |c1 - c0| is compared with the
marker's (25 mm for the default marker).

A second part repeats a robot's path as an independent renderer set it up: the marker,
facing the left camera at ``path_distance``, put down ``path_poses`` times ``path_step``
mm apart along c0 -> c1, and every pair blurred in BOTH views along the LEFT image's
direction of that travel (the right view's own direction differs by the rig's
convergence). From 22 px of blur on at 560 mm, the blurred rings c0 and c1 reach into
each other (their outer edges are 5 mm apart). It reports c0-c1, c0-c2 and the
displacement between consecutive poses.

A third part repeats the path with the plate cut tight around the rings
(``tight_margin`` mm beyond their outer edges) on a dark ground, the trackers given that
plate: what lies beyond the plate, blurred, reaches into the rings' edges as a
neighbouring ring's blur does, and an edge fit that took it in would be biased along the
motion (the plate's edges on both sides of c0 -> c1 pull c0 and c1 apart or together).

The blur is the renderer's: a line kernel in each image (:class:`~markerpose.synth.Imaging`),
the model the blurred-ring fit assumes. Real motion adds what that model leaves out
(rolling shutter, a motion that turns or speeds up within the exposure, the camera's
response curve); this measures the fit on its own model, not on real recordings.

``main(conf, out_dir) -> dict`` writes ``report.md``, ``results.json`` and
``blur-distance.png`` (the mean error against the blur length) into ``out_dir``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..camera import StereoRig
from ..formats import write_json
from ..marker import Marker
from ..synth import Imaging, look_at_pose, render_stereo
from .configs import available, build

default_conf = {
    "pairs": 40,  # poses, each rendered at every blur length
    "lengths": (0.0, 5.0, 9.0, 13.0, 17.0, 21.0, 25.0),  # motion blur along c0 -> c1, px
    "configs": ("default", "paper"),  # presets
    "distance": (450.0, 700.0),  # marker distance, mm
    "offset": (40.0, 30.0),  # largest sideways offset of c0 in x and y, mm (both views see it)
    "tilt": 40.0,  # largest tilt, degrees
    "roll": 360.0,  # roll drawn from [0, this), degrees: the motion's direction in the image
    "alpha": 0.7,  # exposure gain (1: a full white level)
    "seed": 4001,
    "path_poses": 20,  # the robot path: poses (0: none) ...
    "path_step": 10.0,  # ... this far apart along c0 -> c1, mm ...
    "path_distance": 560.0,  # ... at this distance from the left camera, facing it, mm
    "tight_margin": 3.0,  # the path again with the plate this tight around the rings, mm (0: not) ...
    "tight_background": 0.05,  # ... on a dark ground (reflectance; the paper's is 0.85)
}


def check_conf(conf: dict) -> dict:
    """``conf`` with its values checked (``ValueError`` naming the key)."""
    if int(conf["pairs"]) < 1:
        raise ValueError(f"pairs must be >= 1, got {conf['pairs']!r}")
    if int(conf["path_poses"]) < 0 or int(conf["path_poses"]) == 1:
        raise ValueError(f"path_poses must be 0 (no path) or at least 2, got {conf['path_poses']!r}")
    if not (np.isfinite(conf["tight_margin"]) and conf["tight_margin"] >= 0 and 0 <= conf["tight_background"] <= 1):
        raise ValueError(
            f"tight_margin must be >= 0 mm and tight_background a reflectance in [0, 1], got {conf['tight_margin']!r}, "
            f"{conf['tight_background']!r}"
        )
    if not (np.isfinite(conf["path_step"]) and conf["path_step"] > 0 and np.isfinite(conf["path_distance"]) and conf["path_distance"] > 0):
        raise ValueError(f"path_step and path_distance must be > 0 mm, got {conf['path_step']!r} and {conf['path_distance']!r}")
    lengths = list(dict.fromkeys(float(v) for v in conf["lengths"]))  # each once, in order
    # The renderer blurs only beyond a pixel: a length in (0, 1] would be reported blurred.
    if not lengths or not all(np.isfinite(v) and (v == 0 or v > 1) for v in lengths):
        raise ValueError(f"lengths must be blur lengths of 0 or more than 1 px, got {conf['lengths']!r}")
    return {**conf, "lengths": tuple(lengths)}


def _poses(conf: dict) -> list[np.ndarray]:
    rng = np.random.default_rng(conf["seed"])
    lo, hi = conf["distance"]
    dx, dy = conf["offset"]
    return [
        look_at_pose(
            [rng.uniform(-dx, dx), rng.uniform(-dy, dy), rng.uniform(lo, hi)],
            rng.uniform(0, conf["tilt"]),
            rng.uniform(0, 360),
            rng.uniform(0, conf["roll"]),
        )
        for _ in range(int(conf["pairs"]))
    ]


def path_poses(conf: dict) -> list[np.ndarray]:
    """The robot path: the marker facing the left camera (unrolled: c0 -> c1 along the
    camera's x) at ``path_distance``, ``path_poses`` poses ``path_step`` mm apart along x,
    centred on the optical axis."""
    n, step = int(conf["path_poses"]), float(conf["path_step"])
    return [look_at_pose([(k - (n - 1) / 2) * step, 0.0, float(conf["path_distance"])]) for k in range(n)]


def along_travel(rig: StereoRig, T_left_marker: np.ndarray) -> float:
    """The LEFT image's direction (degrees) of the marker's travel along its x axis (c0 ->
    c1) at pose ``T_left_marker``: what the path's blur takes in both views."""
    T = T_left_marker
    ends = np.array([T[:3, 3], T[:3, 3] + T[:3, 0]])  # the origin and 1 mm along the travel
    d = rig.left.project(ends)
    d = d[1] - d[0]
    return float(np.degrees(np.arctan2(d[1], d[0])))


def along_c0_c1(rig: StereoRig, marker: Marker, T_left_marker: np.ndarray) -> list[float]:
    """Per view, the image direction of c0 -> c1 (degrees, image axes: x right, y down)."""
    T = T_left_marker
    p = rig.project(marker.points3d[:2] @ T[:3, :3].T + T[:3, 3])  # (view, c0/c1, xy)
    d = p[:, 1] - p[:, 0]
    return [float(a) for a in np.degrees(np.arctan2(d[:, 1], d[:, 0]))]


def main(conf: dict | None = None, out_dir: str | Path | None = None, progress: bool = True) -> dict:
    """Render, estimate, summarise; with ``out_dir``, write the report, JSON and plot."""
    c = check_conf({**default_conf, **(conf or {})})
    rig, marker = StereoRig.default(), Marker()
    names = available(c["configs"], require=True)
    out = None
    if out_dir is not None:  # before the work: a path that cannot be a folder fails now
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
    lengths = [float(v) for v in c["lengths"]]
    poses, path = _poses(c), path_poses(c)
    # The path on a tight plate: the trackers know the plate they track (its tool file's margin).
    tight = Marker(margin=float(c["tight_margin"])) if c["tight_margin"] and path else None
    parts = [("poses", poses, marker, None), ("path", path, marker, None)]
    if tight is not None:
        ground = tuple(np.full(cam.image_size[::-1], c["tight_background"], np.float32) for cam in rig.cameras)
        parts.append(("tight", path, tight, ground))
    trackers = {id(mk): {name: build(name, rig, mk) for name in names} for mk in {id(m): m for _, _, m, _ in parts}.values()}
    # Per configuration and length, per pose: (c0-c1 error, c0-c2 error, translation) or None.
    found: dict = {part: {name: {L: [] for L in lengths} for name in names} for part, *_ in parts}
    with tqdm(total=sum(len(Ts) for _, Ts, _, _ in parts) * len(lengths), desc="blur-distance", unit="pair", disable=not progress) as bar:
        for part, Ts, mk, ground in parts:
            for n, T in enumerate(Ts):
                angles = along_c0_c1(rig, mk, T) if part == "poses" else [along_travel(rig, T)] * 2
                for L in lengths:
                    imaging = tuple(Imaging(alpha=c["alpha"], motion_blur=L, motion_angle=a) for a in angles)
                    seed = c["seed"] + 1 + n + (10_000 if part != "poses" else 0)
                    frame = render_stereo(rig, T, mk, imaging, ground, seed=seed)
                    for name, tr in trackers[id(mk)].items():
                        found[part][name][L].append(_measured(tr.estimate(*frame.images), mk))
                    bar.update()
    true = float(np.linalg.norm(marker.points3d[1] - marker.points3d[0]))
    res = {
        "conf": {**c, "lengths": lengths},
        "true_mm": true,
        "true_c0_c2_mm": float(np.linalg.norm(marker.points3d[2] - marker.points3d[0])),
        "summary": {name: [_summary(L, _column(found["poses"][name][L], 0)) for L in lengths] for name in names},
        "summary_c0_c2": {name: [_summary(L, _column(found["poses"][name][L], 1)) for L in lengths] for name in names},
        "path": {name: [_path_summary(L, found["path"][name][L], path) for L in lengths] for name in names} if path else {},
        "tight": {name: [_path_summary(L, found["tight"][name][L], path) for L in lengths] for name in names} if tight else {},
        "errors": {name: {str(L): _column(v, 0) for L, v in e.items()} for name, e in found["poses"].items()},
        "errors_c0_c2": {name: {str(L): _column(v, 1) for L, v in e.items()} for name, e in found["poses"].items()},
        **{
            f"{part}_errors": {
                name: {str(L): [None if m is None else [m[0], m[1]] for m in v] for L, v in e.items()} for name, e in found[part].items()
            }
            for part in ("path", "tight")
            if part in found
        },
    }
    if out is not None:
        write_json(out / "results.json", res)
        (out / "report.md").write_text(report(res))
        plot(res, out / "blur-distance.png")
    return res


def _measured(est, marker: Marker) -> tuple | None:
    """(c0-c1 error, c0-c2 error, translation (3,)) of an estimate, mm; None without one."""
    if est is None:
        return None
    p, m = est.points3d, marker.points3d
    e01 = float(np.linalg.norm(p[1] - p[0]) - np.linalg.norm(m[1] - m[0]))
    e02 = float(np.linalg.norm(p[2] - p[0]) - np.linalg.norm(m[2] - m[0]))
    return e01, e02, np.asarray(est.T[:3, 3], np.float64)


def _column(rows: list, k: int) -> list:
    return [None if r is None else r[k] for r in rows]


def _path_summary(length: float, rows: list, poses: list) -> dict:
    """The path's c0-c1 and c0-c2 errors, and the error of each displacement between
    consecutive poses both found (its length against the true one), mm."""
    moved = []
    for a, b, Ta, Tb in zip(rows, rows[1:], poses, poses[1:]):
        if a is not None and b is not None:
            moved.append(float(np.linalg.norm(b[2] - a[2]) - np.linalg.norm(Tb[:3, 3] - Ta[:3, 3])))
    return {
        "length_px": length,
        "c0_c1": _summary(length, _column(rows, 0)),
        "c0_c2": _summary(length, _column(rows, 1)),
        "displacement": _summary(length, moved) if moved else _summary(length, [None]),
        "same_sign_c0_c1": _same_sign(_column(rows, 0)),
    }


def _same_sign(errors: list) -> float | None:
    """The share of the errors with the sign of their mean (None without any)."""
    e = np.array([v for v in errors if v is not None], np.float64)
    return None if not len(e) else float(np.mean(np.sign(e) == np.sign(e.mean())))


def _summary(length: float, errs: list) -> dict:
    e = np.array([v for v in errs if v is not None], np.float64)
    found = len(e) / len(errs)
    if not len(e):
        return {
            "length_px": length,
            "found": found,
            "mean_mm": None,
            "sd_mm": None,
            "median_mm": None,
            "p95_abs_mm": None,
            "max_abs_mm": None,
        }
    return {
        "length_px": length,
        "found": found,
        "mean_mm": float(e.mean()),
        "sd_mm": float(e.std(ddof=1)) if len(e) > 1 else 0.0,
        "median_mm": float(np.median(e)),
        "p95_abs_mm": float(np.percentile(np.abs(e), 95)),
        "max_abs_mm": float(np.abs(e).max()),
    }


def _cells(s: dict, p95: bool = True) -> list[str]:
    """found, mean ± sd, and p95 / largest (or the largest alone) of a summary."""
    if s["mean_mm"] is None:
        return [f"{100 * s['found']:.0f} %", "—", "—"]
    size = f"{s['p95_abs_mm']:.4f} / {s['max_abs_mm']:.4f}" if p95 else f"{s['max_abs_mm']:.4f}"
    return [f"{100 * s['found']:.0f} %", f"{s['mean_mm']:+.4f} ± {s['sd_mm']:.4f}", size]


def _head(names: list, columns: tuple) -> list[str]:
    """A table's header and separator lines: the blur length, then each column for each configuration."""
    cols = [f"`{n}` {col}" for n in names for col in columns]
    return ["| blur (px) | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]


def report(res: dict) -> str:
    """Markdown: per blur length and configuration, the pairs found and the errors of c0-c1
    and c0-c2; then the robot path's."""
    c = res["conf"]
    names = list(res["summary"])
    lines = [
        f"# Distance c0-c1 ({res['true_mm']:g} mm) under motion blur along it: {c['pairs']} poses per blur length",
        "",
        (
            f"Each pose ({c['distance'][0]:g}-{c['distance'][1]:g} mm, tilt up to {c['tilt']:g}°, roll in [0, {c['roll']:g})°, "
            f"α {c['alpha']:g}) rendered at every blur length, the blur along the image direction of c0 -> c1 in each view. "
            "Error = the triangulated distance c0-c1 (or c0-c2) minus the marker's, over the pairs a configuration found: mean ± "
            "standard deviation, and the 95th percentile and the largest of its size."
        ),
        "",
        *_head(names, ("found", "c0-c1 error, mean ± sd (mm)", "c0-c1 size, p95 / largest (mm)", "c0-c2 size, p95 / largest (mm)")),
    ]
    for k, L in enumerate(c["lengths"]):
        cells = []
        for n in names:
            cells += _cells(res["summary"][n][k]) + _cells(res["summary_c0_c2"][n][k])[2:]
        lines.append(f"| {L:g} | " + " | ".join(cells) + " |")
    for part in ("path", "tight"):
        if not res.get(part):
            continue
        what = (
            f"**The robot path**: {c['path_poses']} poses {c['path_step']:g} mm apart along c0 -> c1 at {c['path_distance']:g} mm, "
            "facing the left camera, each pair blurred in both views along the left image's direction of the travel."
            if part == "path"
            else f"**The robot path on a tight plate**: the same poses and blur, the plate {c['tight_margin']:g} mm beyond the rings' "
            f"outer edges on a dark ground (reflectance {c['tight_background']:g}), and the trackers given that plate."
        )
        lines += [
            "",
            what
            + (
                " c0-c1 and c0-c2: mean ± sd and the largest size of the error, and the share of the c0-c1 errors with their "
                "mean's sign; displacement: the largest error of the distance between consecutive poses (mm)."
            ),
            "",
            *_head(names, ("found", "c0-c1 (mm)", "largest", "same sign", "c0-c2 (mm)", "largest", "displacement, largest")),
        ]
        for k, L in enumerate(c["lengths"]):
            cells = []
            for n in names:
                row = res[part][n][k]
                a, b, d = _cells(row["c0_c1"], False), _cells(row["c0_c2"], False), row["displacement"]
                same = "—" if row["same_sign_c0_c1"] is None else f"{100 * row['same_sign_c0_c1']:.0f} %"
                cells += [a[0], a[1], a[2], same, b[1], b[2], "—" if d["max_abs_mm"] is None else f"{d['max_abs_mm']:.4f}"]
            lines.append(f"| {L:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> Path:
    """The mean error of c0-c1 (± one standard deviation) against the blur length: the
    random poses, and beside them the robot path (c0-c1 and c0-c2) where it ran."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    parts = [("random poses, blur along c0 -> c1 in each view", res["summary"], None)]
    if res.get("path"):
        parts.append(("robot path, blur along the left view's travel in both", None, res["path"]))
    if res.get("tight"):
        parts.append((f"the same path, a {res['conf']['tight_margin']:g} mm plate on a dark ground", None, res["tight"]))
    fig, axes = plt.subplots(1, len(parts), figsize=(6.5 * len(parts), 4), squeeze=False, sharey=True)
    for ax, (title, summary, path_rows) in zip(axes[0], parts):
        for i, n in enumerate(res["summary"]):
            series = (
                [("c0-c1", summary[n])]
                if summary
                else [("c0-c1", [r["c0_c1"] for r in path_rows[n]]), ("c0-c2", [r["c0_c2"] for r in path_rows[n]])]
            )
            for what, rows in series:
                ok = [r for r in rows if r["mean_mm"] is not None]
                x = np.array([r["length_px"] for r in ok])
                m, s = np.array([r["mean_mm"] for r in ok]), np.array([r["sd_mm"] for r in ok])
                ax.errorbar(
                    x, m, yerr=s, marker="o", ms=4, capsize=3, color=f"C{i}", ls="-" if what == "c0-c1" else "--", label=f"{n}, {what}"
                )
        ax.axhline(0, color="0.5", lw=0.8)
        for lim in (-0.02, 0.02):
            ax.axhline(lim, color="0.7", lw=0.8, ls=":")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("motion blur (px)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("error of the distance (mm)")
    # One legend for all panels, below them: per panel, nine configurations' entries hid the curves.
    handles = [Line2D([], [], color=f"C{i}", marker="o", ms=4, label=n) for i, n in enumerate(res["summary"])]
    if len(parts) > 1:
        handles += [Line2D([], [], color="0.3", ls=ls, label=what) for ls, what in (("-", "c0-c1"), ("--", "c0-c2 (the path)"))]
    rows = -(-len(handles) // 6)
    fig.legend(handles=handles, loc="lower center", ncol=min(6, len(handles)), frameon=False, fontsize=8)
    fig.tight_layout(rect=(0, 0.06 * rows + 0.02, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
