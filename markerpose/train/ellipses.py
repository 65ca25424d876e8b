"""Training and evaluation of stage 2 (EllipSegNet).

Each sample is a patch cut exactly as the pipeline cuts it (:func:`~markerpose.ellipses.extract_patch`)
from a full-resolution rendering of the window around a simulated stage-1 point (the true
centre plus a stage-1-like error), with its target: the anti-aliased coverage of the
central ring's outer disk (the filled Ø20 mm disk, inner white disk included), computed
by supersampling each patch pixel through the lens model onto the marker plane. The
window is either the paper's fixed 120 px or an adaptive one (1.2-2.8 ring diameters),
so one network serves both patch modes.

Metrics: IoU of the thresholded mask, and the full-resolution error of the centre from
the mask against the true centre of the imaged outer ellipse (what the method estimates)
and against the projection of the ring's 3D centre (they differ by the perspective bias).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import ellipses as es
from ..camera import Camera
from ..marker import Marker
from ..synth import Imaging, clutter_background, look_at_pose, render_view, sensor_readout
from .augment import photometric
from .data import cached as data_cache
from .data import draw as draw_value
from .data import render_many
from .loop import export as export_checkpoint
from .loop import fit, to_onnx
from .scenes import FULL_SIZES, loguniform, occluders, random_imaging

default_conf = {
    "lr": 1e-4,  # Adam (the paper's)
    "schedule": "constant",  # or "cosine"
    "epochs": 10,
    "batch_size": 32,
    "train_size": 11010,  # the paper's number of patches
    "val_size": 400,
    "seed": 0,
    "workers": 2,
    "device": None,
    "init": None,  # checkpoint whose weights start the run (fine-tuning); None: random
}

TEST_SETS = {
    "standard": (2001, 600, {"alpha": (0.25, 1.0), "blur": (0.0, 9.0), "p_occlude": 0.0}),
    "dark_0.0625": (2002, 300, {"alpha": 0.0625, "blur": (0.0, 9.0), "p_occlude": 0.0}),
    "blur_25": (2003, 300, {"alpha": (0.25, 1.0), "blur": 25.0, "p_occlude": 0.0}),
}


@dataclass
class PatchSample:
    """One stage-2 sample: ``image`` (120, 120) uint8, ``target`` (120, 120) float32 coverage,
    ``frame`` [x0, y0, scale] of the patch, ``center`` (2,) true imaged-ellipse centre and
    ``center3d`` (2,) projected 3D centre, both in full-resolution pixels, and the
    conditions (ring_px, tilt, distance, alpha, blur)."""

    image: np.ndarray
    target: np.ndarray
    frame: np.ndarray
    center: np.ndarray
    center3d: np.ndarray
    conditions: np.ndarray  # ring_px, tilt, distance, alpha, blur


def _coverage(camera: Camera, T: np.ndarray, disk_center, radius: float, frame: np.ndarray, n: int = 4) -> np.ndarray:
    """(120, 120) fraction of each patch pixel inside the imaged disk, n x n supersampled.

    Pixel centres are undistorted exactly; the sub-pixel samples follow the local Jacobian
    of that map (its curvature over one pixel is negligible), as the renderer does.
    """
    g = np.arange(es.PATCH, dtype=np.float64)
    X, Y = np.meshgrid(g, g)
    full = es.patch_to_image(np.column_stack([X.ravel(), Y.ravel()]), frame)
    xn = camera.undistort_points(full, ideal_pixels=False).reshape(es.PATCH, es.PATCH, 2)
    J_u, J_v = np.gradient(xn, axis=1), np.gradient(xn, axis=0)
    off = (np.arange(n) + 0.5) / n - 0.5
    du, dv = (o.ravel() for o in np.meshgrid(off, off))
    sx = xn[..., :1] + J_u[..., :1] * du + J_v[..., :1] * dv  # (120, 120, n*n)
    sy = xn[..., 1:] + J_u[..., 1:] * du + J_v[..., 1:] * dv
    Hinv = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    w = Hinv[2, 0] * sx + Hinv[2, 1] * sy + Hinv[2, 2]
    mx = (Hinv[0, 0] * sx + Hinv[0, 1] * sy + Hinv[0, 2]) / w
    my = (Hinv[1, 0] * sx + Hinv[1, 1] * sy + Hinv[1, 2]) / w
    inside = (mx - disk_center[0]) ** 2 + (my - disk_center[1]) ** 2 <= radius**2
    return inside.mean(axis=2).astype(np.float32)


def sample(rng: np.random.Generator, marker: Marker | None = None, conf: dict | None = None) -> PatchSample:
    """One random patch around a ring of the marker, as the pipeline would cut it."""
    conf = conf or {}
    marker = marker or Marker()

    def draw(key, default):
        return draw_value(rng, conf, key, default)

    W, H = FULL_SIZES[int(rng.integers(len(FULL_SIZES)))]
    f = rng.uniform(0.75, 1.5) * 2500 * W / 1280
    dist = np.array([rng.uniform(-0.25, 0.05), rng.uniform(-0.05, 0.15), 0, 0, 0])
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    full_cam = Camera(K, dist, (W, H))

    ring_px = draw("ring_px", lambda: loguniform(rng, 40, 200))
    z = f * marker.outer_diameter / ring_px
    tilt = draw("tilt", lambda: rng.uniform(0, 60) if rng.uniform() < 0.9 else rng.uniform(60, 65))
    T = look_at_pose([0, 0, z], tilt, rng.uniform(0, 360), rng.uniform(0, 360))
    i = int(rng.integers(3))
    # Where the ring lands: anywhere, near the border 15% of the time.
    u, v = rng.uniform(0.1 * W, 0.9 * W), rng.uniform(0.1 * H, 0.9 * H)
    if rng.uniform() < 0.15:  # at the border: windows (and rings) that cross it
        m = rng.uniform(0, 0.4 * ring_px)
        u, v = [(m, v), (W - 1 - m, v), (u, m), (u, H - 1 - m)][int(rng.integers(4))]
    ray = np.linalg.solve(K, [u, v, 1.0])
    T[:3, 3] = ray * z - T[:3, :3] @ marker.points3d[i]
    true = full_cam.project((T[:3, :3] @ marker.points3d[i] + T[:3, 3])[None])[0]

    # A stage-1-like error: a few px, sometimes up to a fifth of a ring.
    err = rng.normal(0, 2.0, 2) if rng.uniform() < 0.85 else rng.uniform(-0.2, 0.2, 2) * ring_px
    rough = true + np.clip(err, -0.25 * ring_px, 0.25 * ring_px)
    if rng.uniform() < 0.3:
        side = es.PATCH  # the paper's fixed window
    else:
        d_est = ring_px * rng.uniform(0.85, 1.18)
        side = int(np.clip(round(rng.uniform(1.2, 2.8) * d_est), 48, 480))

    # Render the part of the image the window covers (and the one-pixel neighbours the
    # crop's replication may need), then cut the patch exactly as the pipeline does.
    x0 = int(np.floor(rough[0] + 0.5)) - side // 2
    y0 = int(np.floor(rough[1] + 0.5)) - side // 2
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + side, W), min(y0 + side, H)
    if cx1 - cx0 < 2 or cy1 - cy0 < 2:  # the window left the image: re-draw
        return sample(rng, marker, conf)
    Kc = K.copy()
    Kc[0, 2] -= cx0
    Kc[1, 2] -= cy0
    crop_cam = Camera(Kc, dist, (cx1 - cx0, cy1 - cy0))

    alpha = draw("alpha", lambda: rng.uniform(0.25, 1.0) if rng.uniform() < 0.5 else loguniform(rng, 0.03, 0.25))
    blur = draw("blur", lambda: 0.0 if rng.uniform() < 0.45 else rng.uniform(1, 30))
    imaging = random_imaging(rng, alpha, blur, psf=(0.3, 2.0), vignetting=0.0)
    bg = clutter_background((cx1 - cx0, cy1 - cy0), rng, scale=1.0)
    dn, truth = render_view(crop_cam, T, marker, imaging, background=bg, seed=rng)
    if rng.uniform() < conf.get("p_occlude", 0.2):
        h, w = dn.shape
        near = truth.centers[int(rng.integers(3))]
        cover, refl = occluders((h, w), rng, near, ring_px)
        dn = dn * (1 - cover) + refl * float(alpha * imaging.exposure * 255.0) * cover
    img = sensor_readout(dn, Imaging(full_well=imaging.full_well, read_noise=imaging.read_noise), rng)
    patch, frame = es.extract_patch(img, rough - [cx0, cy0], side)
    frame[:2] += [cx0, cy0]
    if rng.uniform() < conf.get("p_photometric", 0.5):
        patch = photometric(patch, rng, {"p_resample": 0.0, "p_vignetting": 0.0})
    target = _coverage(full_cam, T, marker.centers2d[i], marker.outer_radius, frame)
    center = truth.outer_centers[i] + [cx0, cy0]
    center3d = truth.centers[i] + [cx0, cy0]
    return PatchSample(patch, target, frame, center, center3d, np.array([ring_px, tilt, z, alpha, blur]))


def _render_chunk(args):
    seed, chunk, n, conf = args
    rng = np.random.default_rng([seed, chunk])
    return [sample(rng, conf=conf) for _ in range(n)]


def generate(n: int, seed: int, conf: dict | None = None, workers: int = 2, desc: str = "render") -> dict:
    """Render ``n`` stage-2 samples into arrays (see :class:`PatchSample`)."""
    out = render_many(_render_chunk, n, seed, conf, workers, desc, "patch")
    return {
        "image": np.stack([s.image for s in out]),
        "target": np.stack([np.rint(s.target * 255) for s in out]).astype(np.uint8),  # 1/255 steps
        "frame": np.stack([s.frame for s in out]),
        "center": np.stack([s.center for s in out]),
        "center3d": np.stack([s.center3d for s in out]),
        "conditions": np.stack([s.conditions for s in out]),
    }


def cached(path: Path, *, n: int, seed: int, conf: dict | None = None, workers: int = 2, desc: str = "render") -> dict:
    """Load a rendered stage-2 set from ``path`` (.npz) or render and save it."""
    key = {"n": n, "seed": seed, "conf": conf, "kind": "ellipses"}
    return data_cache(path, key, lambda: generate(n, seed, conf, workers, desc))


# --- evaluation --------------------------------------------------------------------------
def predict(net, images: np.ndarray, batch: int = 64, device="cpu") -> np.ndarray:
    """(N, 120, 120) uint8 → (N, 120, 120) float32 probabilities. ``net``: a torch module,
    or a :class:`markerpose.nets.Runner` (ONNX Runtime or torch)."""
    from ..nets import Runner

    out = []
    if isinstance(net, Runner):
        for k in range(0, len(images), batch):
            out.append(es.sigmoid(net(images[k : k + batch].astype(np.float32)[:, None] / 255.0)[0][:, 0]))
        return np.concatenate(out)
    import torch

    net.eval()
    with torch.inference_mode():
        for k in range(0, len(images), batch):
            x = torch.from_numpy(images[k : k + batch].astype(np.float32) / 255.0)[:, None].to(device)
            out.append(torch.sigmoid(net(x))[:, 0].float().cpu().numpy())
    return np.concatenate(out)


def score(probs: np.ndarray, data: dict, fits=es.FITS, detail: bool = False) -> dict:
    """IoU and centre errors (full-resolution px; a missing centre counts as inf).

    With ``detail`` each fit also carries the per-patch errors (``errors``, ``errors_3d``).
    """
    target = data["target"].astype(np.float32) / 255.0
    pm, tm = probs > 0.5, target > 0.5
    inter, union = (pm & tm).sum(axis=(1, 2)), (pm | tm).sum(axis=(1, 2))
    res = {"n": len(probs), "iou_mean": float(np.mean(inter / np.maximum(union, 1)))}
    for method in fits:
        e_true, e_3d = np.full(len(probs), np.inf), np.full(len(probs), np.inf)
        for k in range(len(probs)):
            found = es.mask_center(probs[k], method)
            if found is None:
                continue
            c = es.patch_to_image(found[0], data["frame"][k])
            e_true[k] = np.linalg.norm(c - data["center"][k])
            e_3d[k] = np.linalg.norm(c - data["center3d"][k])
        res[method] = {
            "median_px": float(np.median(e_true)),
            "p95_px": float(np.percentile(e_true, 95, method="higher")),
            "found": float(np.isfinite(e_true).mean()),
            "median_px_vs_3d": float(np.median(e_3d)),
            "p95_px_vs_3d": float(np.percentile(e_3d, 95, method="higher")),
        }
        if detail:
            res[method].update(errors=e_true, errors_3d=e_3d)
    return res


def by_condition(data: dict, res: dict, fits=("ellipse", "subpixel")) -> list[dict]:
    """Median errors binned by tilt and by apparent ring size, with the perspective bias
    (|imaged-ellipse centre − projected 3D centre|) of the same patches."""
    cond = data["conditions"]
    bias = np.linalg.norm(data["center"] - data["center3d"], axis=1)
    rows = []
    bins = [("tilt", 1, (0, 20, 40, 66)), ("ring_px", 0, (40, 70, 110, 201))]
    for name, col, edges in bins:
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (cond[:, col] >= lo) & (cond[:, col] < hi)
            if not sel.any():
                continue
            row = {
                "bin": f"{name} {lo}-{hi}",
                "n": int(sel.sum()),
                "bias_median": float(np.median(bias[sel])),
                "bias_max": float(bias[sel].max()),
            }
            for f in fits:
                row[f"{f}_median"] = float(np.median(res[f]["errors"][sel]))
                row[f"{f}_median_3d"] = float(np.median(res[f]["errors_3d"][sel]))
            rows.append(row)
    return rows


# --- training ----------------------------------------------------------------------------
def _flip_batch(im, tg, rng):
    """Flips and 90° turns of whole patches (exact: the patch centre stays put)."""
    k = int(rng.integers(4))
    im, tg = np.rot90(im, k, axes=(1, 2)), np.rot90(tg, k, axes=(1, 2))
    if rng.uniform() < 0.5:
        im, tg = im[:, :, ::-1], tg[:, :, ::-1]
    return np.ascontiguousarray(im), np.ascontiguousarray(tg)


def main(conf: dict | None = None, out_dir: str | Path = "runs/ellipses", resume: bool = False, data_dir: str | Path = "runs/data") -> Path:
    """Train EllipSegNet; returns the best checkpoint (lowest median centre error)."""
    import torch

    c = {**default_conf, **(conf or {})}
    data_dir = Path(data_dir)
    c["device"] = dev = c["device"] or ("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(c["seed"])
    train = cached(
        data_dir / f"es_train_{c['seed']}_{c['train_size']}.npz",
        n=c["train_size"],
        seed=c["seed"],
        workers=c["workers"],
        desc="render train",
    )
    val = cached(data_dir / f"es_val_{c['val_size']}.npz", n=c["val_size"], seed=1, workers=c["workers"], desc="render val")
    net = es.build_network().to(dev)
    bce = torch.nn.BCEWithLogitsLoss()
    n, bs = len(train["image"]), c["batch_size"]

    def batches(rng):
        idx = rng.permutation(n)
        for k in range(0, n - bs + 1, bs):
            j = np.sort(idx[k : k + bs])
            im, tg = _flip_batch(train["image"][j], train["target"][j], rng)
            yield im, tg

    def loss_fn(net, im, tg):
        x = torch.from_numpy(im.astype(np.float32) / 255.0)[:, None].to(dev)
        y = torch.from_numpy(tg.astype(np.float32) / 255.0)[:, None].to(dev)
        loss = bce(net(x), y)
        return loss, {"bce": loss.item()}

    def describe(m):
        return f"IoU {m['iou_mean']:.4f}  centre median {m['ellipse']['median_px']:.3f} px (fitEllipse), {m['subpixel']['median_px']:.3f} px (sub-pixel)  bce {m['bce']:.4f}"

    return fit(
        net,
        batches,
        n // bs,
        loss_fn,
        lambda net: score(predict(net, val["image"], device=dev), val, fits=("ellipse", "subpixel")),
        lambda m: -m["subpixel"]["median_px"] - m["subpixel"]["p95_px"] / 3,
        c,
        Path(out_dir),
        resume,
        describe,
    )


def export(checkpoint: str | Path, dest: str | Path) -> Path:
    """The inference part of an EllipSegNet checkpoint (``dest``), and its ONNX copy beside it."""
    dest = export_checkpoint(checkpoint, dest, "ellipses")
    to_onnx(dest)
    return dest


def evaluate(weights: str | Path | None = None, data_dir: str | Path = "runs/data", sets: list | None = None, workers: int = 2) -> dict:
    """Metrics of an EllipSegNet checkpoint on the held-out patch sets (rendered once, cached)."""
    model = es.EllipseNet(weights)
    res = {}
    for name in sets or TEST_SETS:
        seed, n, conf = TEST_SETS[name]
        data = cached(Path(data_dir) / f"es_test_{name}.npz", n=n, seed=seed, conf=conf, workers=workers, desc=f"render {name}")
        t0 = time.perf_counter()
        probs = predict(model.runner, data["image"])
        seconds = (time.perf_counter() - t0) / n
        r = score(probs, data, detail=True)
        r["by_condition"] = by_condition(data, r)
        for f in es.FITS:
            r[f].pop("errors")
            r[f].pop("errors_3d")
        res[name] = {**r, "seconds_per_patch": seconds}
    return res


__all__ = ["TEST_SETS", "by_condition", "cached", "default_conf", "evaluate", "export", "generate", "main", "predict", "sample", "score"]
