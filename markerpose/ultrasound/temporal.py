"""Temporal calibration: the delay between the ultrasound frames and the tracker.

PLUS's method. The probe is moved up and down over a flat plate (a tank's bottom) a few
times, the image plane kept across it. In the images the plate is a bright line whose
depth follows the probe's height; the tracker sees the probe's position along the same
direction. Two signals of one motion on two clocks: the lag that best aligns them is the
offset to add to the ultrasound times to reach the cameras' clock (``--time-offset``).

- **The line** (:func:`plate_depths`): per image column, the brightest echo's depth
  (sub-pixel, a parabola through its peak), the median over the columns, in mm.
- **The probe** (:func:`probe_heights`): the positions' component along their principal
  direction (the motion up and down, whatever the tracker's axes), of the image's centre at
  the line's depth where the probe calibration is given, else of the marker.
- **The lag** (:func:`estimate_offset`): both signals standardised (zero mean, unit sd,
  the tracker's sign matched to the line's), the tracker's interpolated at the ultrasound
  times plus a trial offset; the offset of least mean squared difference (grid, then a
  parabola through the best three), its standard error from the curvature there.
"""

from __future__ import annotations

import numpy as np


def plate_depths(frames, spacing_y: float, min_contrast: float = 20.0) -> np.ndarray:
    """(N,) the plate line's depth in each frame, mm below the transducer face (NaN where
    no column has an echo ``min_contrast`` grey levels above its own median)."""
    out = np.full(len(frames), np.nan)
    for k, img in enumerate(frames):
        a = np.asarray(img, np.float64)
        if a.ndim != 2 or a.shape[0] < 3:
            raise ValueError(f"frame {k}: expected a 2D grey image, got shape {a.shape}")
        peak = np.argmax(a, axis=0)
        cols = np.arange(a.shape[1])
        strong = a[peak, cols] - np.median(a, axis=0) >= min_contrast
        inner = (peak > 0) & (peak < a.shape[0] - 1) & strong
        if not inner.any():
            continue
        p, c = peak[inner], cols[inner]
        y0, y1, y2 = a[p - 1, c], a[p, c], a[p + 1, c]
        den = y0 - 2 * y1 + y2
        sub = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
        out[k] = float(np.median(p + sub)) * spacing_y
    return out


def probe_heights(poses, point=None) -> np.ndarray:
    """(N,) the position along the positions' principal direction, mm, of ``point`` (3,), mm in
    the marker's frame, under each pose (4 x 4, or None: NaN); without ``point``, the marker's
    origin. With a probe calibration, a point of the image (where the plate line is) follows
    the line itself: a rocking of the probe moves the marker, a lever arm away, and not the line."""
    out = np.full(len(poses), np.nan)
    found = [k for k, T in enumerate(poses) if T is not None]
    if len(found) < 3:
        return out
    p = np.zeros(3) if point is None else np.asarray(point, np.float64)
    X = np.array([np.asarray(poses[k], np.float64)[:3, :3] @ p + np.asarray(poses[k], np.float64)[:3, 3] for k in found])
    X = X - X.mean(0)
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    out[found] = X @ Vt[0]
    return out


def _standard(x: np.ndarray) -> np.ndarray:
    return (x - np.mean(x)) / max(np.std(x), 1e-12)


def estimate_offset(us_times, depths, tracker_times, heights, max_offset: float = 0.5, step: float = 0.001) -> dict:
    """The offset (s) to add to the ultrasound times to reach the tracker's clock: the lag
    that best aligns the line's depths with the probe's heights (see the module's docstring).

    Returns ``offset_s``, ``sd_s``, ``rms`` (the standardised signals' RMS difference at
    the offset: near 0 for a clean calibration, near 1.4 for signals that do not match),
    ``frames`` (the ultrasound frames used), ``amplitude_mm`` (the line's motion, sd).
    """
    tu, d = np.asarray(us_times, np.float64), np.asarray(depths, np.float64)
    tt, h = np.asarray(tracker_times, np.float64), np.asarray(heights, np.float64)
    okt = np.isfinite(tt) & np.isfinite(h)
    tt, h = tt[okt], h[okt]
    oku = np.isfinite(tu) & np.isfinite(d)
    if oku.sum() < 10 or len(tt) < 10:
        raise ValueError(
            f"temporal calibration needs the plate in at least 10 frames and 10 tracked poses, got {int(oku.sum())} and {len(tt)}"
        )
    if np.any(np.diff(tt) <= 0):
        raise ValueError("the tracker's times must increase")
    tu, d = tu[oku], d[oku]
    ds = _standard(d)

    def cost(off: float) -> tuple[float, int]:
        t = tu + off
        inside = (t >= tt[0]) & (t <= tt[-1])
        if inside.sum() < 10:
            return np.inf, 0
        hs = np.interp(t[inside], tt, h)
        a, b = ds[inside], _standard(hs)
        a = (a - a.mean()) / max(a.std(), 1e-12)
        sign = 1.0 if np.mean(a * b) >= 0 else -1.0
        return float(np.mean((a - sign * b) ** 2)), int(inside.sum())

    grid = np.arange(-max_offset, max_offset + step / 2, step)
    costs = np.array([cost(o)[0] for o in grid])
    i = int(np.argmin(costs))
    if not np.isfinite(costs[i]):
        raise ValueError("the ultrasound and tracker times do not overlap")
    off = grid[i]
    if 0 < i < len(grid) - 1 and np.all(np.isfinite(costs[i - 1 : i + 2])):
        c0, c1, c2 = costs[i - 1 : i + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            off = grid[i] + 0.5 * step * (c0 - c2) / den
    c_min, n = cost(off)
    h2 = max(step, 0.005)
    curv = (cost(off + h2)[0] + cost(off - h2)[0] - 2 * c_min) / (h2 * h2) / 2  # mean square = c_min + curv (o - off)^2
    # The mean of n squared standardised differences: its noise per frame is c_min, so the
    # offset's variance is c_min / (n curv) (n - 1 degrees of freedom, one offset).
    sd = float(np.sqrt(c_min / (max(n - 1, 1) * curv))) if curv > 0 else float("inf")
    return {"offset_s": float(off), "sd_s": sd, "rms": float(np.sqrt(c_min)), "frames": n, "amplitude_mm": float(np.std(d))}


__all__ = ["estimate_offset", "plate_depths", "probe_heights"]
