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
}


def check_conf(conf: dict) -> dict:
    """``conf`` with its values checked (``ValueError`` naming the key)."""
    if int(conf["pairs"]) < 1:
        raise ValueError(f"pairs must be >= 1, got {conf['pairs']!r}")
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
    trackers = {name: build(name, rig, marker) for name in names}
    true = float(np.linalg.norm(marker.points3d[1] - marker.points3d[0]))
    lengths = [float(v) for v in c["lengths"]]
    errors = {name: {L: [] for L in lengths} for name in names}  # mm, None where no pose
    poses = _poses(c)
    with tqdm(total=len(poses) * len(lengths), desc="blur-distance", unit="pair", disable=not progress) as bar:
        for n, T in enumerate(poses):
            angles = along_c0_c1(rig, marker, T)
            for L in lengths:
                imaging = tuple(Imaging(alpha=c["alpha"], motion_blur=L, motion_angle=a) for a in angles)
                frame = render_stereo(rig, T, marker, imaging, seed=c["seed"] + 1 + n)
                for name, tr in trackers.items():
                    est = tr.estimate(*frame.images)
                    errors[name][L].append(None if est is None else float(np.linalg.norm(est.points3d[1] - est.points3d[0]) - true))
                bar.update()
    res = {
        "conf": {**c, "lengths": lengths},
        "true_mm": true,
        "summary": {name: [_summary(L, errors[name][L]) for L in lengths] for name in names},
        "errors": {name: {str(L): v for L, v in e.items()} for name, e in errors.items()},
    }
    if out is not None:
        write_json(out / "results.json", res)
        (out / "report.md").write_text(report(res))
        plot(res, out / "blur-distance.png")
    return res


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


def report(res: dict) -> str:
    """Markdown: per blur length and configuration, the pairs found and the error of c0-c1."""
    c = res["conf"]
    names = list(res["summary"])
    lines = [
        f"# Distance c0-c1 ({res['true_mm']:g} mm) under motion blur along it: {c['pairs']} poses per blur length",
        "",
        (
            f"Each pose ({c['distance'][0]:g}-{c['distance'][1]:g} mm, tilt up to {c['tilt']:g}°, roll in [0, {c['roll']:g})°, "
            f"α {c['alpha']:g}) rendered at every blur length, the blur along the image direction of c0 -> c1 in each view. "
            "Error = the triangulated distance c0-c1 minus the marker's, over the pairs a configuration found: mean ± standard "
            "deviation, and the 95th percentile and the largest of its size."
        ),
        "",
        "| blur (px) | "
        + " | ".join(f"`{n}` found | `{n}` error, mean ± sd (mm) | `{n}` error size, p95 / largest (mm)" for n in names)
        + " |",
        "|---|" + "---|---|---|" * len(names),
    ]
    for k, L in enumerate(c["lengths"]):
        cells = []
        for n in names:
            s = res["summary"][n][k]
            if s["mean_mm"] is None:
                cells += [f"{100 * s['found']:.0f} %", "—", "—"]
            else:
                cells += [
                    f"{100 * s['found']:.0f} %",
                    f"{s['mean_mm']:+.4f} ± {s['sd_mm']:.4f}",
                    f"{s['p95_abs_mm']:.4f} / {s['max_abs_mm']:.4f}",
                ]
        lines.append(f"| {L:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> Path:
    """The mean error of c0-c1 (± one standard deviation) against the blur length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for n, rows in res["summary"].items():
        ok = [r for r in rows if r["mean_mm"] is not None]
        x = np.array([r["length_px"] for r in ok])
        m, s = np.array([r["mean_mm"] for r in ok]), np.array([r["sd_mm"] for r in ok])
        ax.errorbar(x, m, yerr=s, marker="o", ms=4, capsize=3, label=n)
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xlabel("motion blur along c0 -> c1 (px)")
    ax.set_ylabel("error of the distance c0-c1 (mm)")
    ax.grid(alpha=0.3)
    ax.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


__all__ = ["along_c0_c1", "check_conf", "default_conf", "main", "plot", "report"]
