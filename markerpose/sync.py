"""Unsynchronised cameras: the right view exposed at another time than the left.

Two USB or industrial cameras without a trigger cable expose their views up to a frame
apart. A marker moving at 100 mm/s moves 3.3 mm in 33 ms, and a pair taken apart
triangulates to a pose that is wrong by millimetres, mostly in depth (the disparity
changes) and across the epipolar lines.

**Compensation** (:func:`right_at_left_time`, used by ``MarkerPose.track(left, right,
times=(t_left, t_right))``): the pose is wanted at the left view's time. Each right-view
ring centre is read at ``t_left`` off its own path in the image: the parabola through its
positions in the last two pairs' right views and this one (a line with one pair before),
each at its capture time; the pair is then verified and solved as a synchronised one. It
needs no pose (a pose's bias under the delay does not enter), only the pairs before: the
first pair after the marker was found is not compensated. Exact for a steady image
acceleration.

**Estimating the delay** (:func:`estimate_delay`, ``markerpose sync``): over a recording of
the marker moving, each pair's right view is taken a trial delay after its left; the delay
that makes the pairs most consistent (the least RMS reprojection error of the rigid fits,
which sees both the epipolar error and the change of the marker's shape) is found by a
one-dimensional search, and its standard error from the curvature of the residuals at the
minimum. Each right-view centre is read at its left view's time off the parabola through
its positions in that pair and its two nearest neighbours (at a run's end, both on one
side), each at its own trial time. A delay error moves the pose mostly in depth (about z / baseline times the
marker's motion within the error): a longer recording measures it better.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np

# While the delay is unknown, a pair exposed apart is off its epipolar lines and misfits the
# rigid marker by the motion within the delay: a recording whose delay is to be estimated is
# tracked with these looser limits (stage settings), which the estimate does not depend on
# (it compares the pairs' consistency, not the limits).
LOOSE = {"verify": {"epipolar_tol": 20.0}, "track": {"max_residual_px": 20.0}}


def check_times(times) -> tuple[float, float]:
    """(t_left, t_right) as floats, or ``ValueError`` (two finite numbers, seconds)."""
    try:
        t_left, t_right = (float(v) for v in times)
    except (TypeError, ValueError):
        raise ValueError(f"times must be (t_left, t_right) in seconds, got {times!r}") from None
    if not (np.isfinite(t_left) and np.isfinite(t_right)):
        raise ValueError(f"times must be finite, got {times!r}")
    return t_left, t_right


class Motion(NamedTuple):
    """What a tracker knows when a pair comes: the pair's capture times (t_left, t_right),
    and the right view's ring centres as measured in the last one or two pairs (each (3, 2))
    with their right views' times, oldest first."""

    times: tuple
    right_prev: tuple
    t_right_prev: tuple


def motion(right_prev: list, t_right_prev: list, times: tuple | None) -> Motion | None:
    """The :class:`Motion` of a pair at ``times`` after the pairs whose right-view centres
    ``right_prev`` were seen at ``t_right_prev`` (oldest first; the last two are used);
    None without times or a previous pair."""
    if times is None or not right_prev or not t_right_prev or any(t is None for t in t_right_prev[-2:]):
        return None
    if not times[1] > t_right_prev[-1]:
        return None
    keep = slice(-2, None) if len(right_prev) >= 2 and t_right_prev[-1] > t_right_prev[-2] else slice(-1, None)
    return Motion(times, tuple(np.asarray(c, np.float64) for c in right_prev[keep]), tuple(float(t) for t in t_right_prev[keep]))


def right_at_left_time(det_r, m: Motion):
    """The right view's Detection ``det_r`` moved to the left view's time: each centre's
    path through its last positions and this one (a line through two, a parabola through
    three), read at ``t_left`` (see the module's docstring)."""
    t_left, t_right = m.times
    if t_right == t_left:
        return det_r
    c = np.asarray(det_r.centers, np.float64)
    at = _lagrange((*m.t_right_prev, t_right), (*m.right_prev, c), t_left)
    shift = at - c
    ellipses = det_r.ellipses
    if ellipses is not None:  # the rings' outlines move with their centres (the plate check compares them)
        ellipses = [None if e is None else ((e[0][0] + d[0], e[0][1] + d[1]), e[1], e[2]) for e, d in zip(ellipses, shift)]
    return replace(det_r, centers=at, ellipses=ellipses)


def _neighbours(ok: np.ndarray) -> list:
    """Per pair, the three pairs of its run (itself and its nearest found neighbours: one on
    each side, or two on one side at a run's end; two where the run has two) whose right
    views give its centres' path, or None alone."""
    n, out = len(ok), []
    for k in range(n):
        if not ok[k]:
            out.append(None)
            continue
        lo = hi = k
        while lo > 0 and ok[lo - 1] and k - lo < 2:
            lo -= 1
        while hi < n - 1 and ok[hi + 1] and hi - k < 2:
            hi += 1
        run = list(range(lo, hi + 1))
        if len(run) < 2:
            out.append(None)
            continue
        i = run.index(k)
        start = min(max(i - 1, 0), max(len(run) - 3, 0))
        out.append(run[start : start + 3])
    return out


def _lagrange(ts, cs, t: float) -> np.ndarray:
    """The polynomial through the points (ts[i], cs[i]) read at ``t``."""
    out = np.zeros_like(cs[0])
    for i, (ti, ci) in enumerate(zip(ts, cs)):
        w = 1.0
        for j, tj in enumerate(ts):
            if j != i:
                w *= (t - tj) / (ti - tj)
        out = out + w * ci
    return out


def delay_residuals(rig, marker, times, lefts, rights, paths: list, delay: float, solve_conf: dict) -> np.ndarray:
    """(N,) the RMS reprojection error (px) of each pair's rigid fit when its right view is
    taken ``delay`` seconds after its left: each right-view centre read at the left view's
    time off its path through the pairs ``paths[k]`` (:func:`_neighbours`) of the run."""
    from .results import Detection
    from .stages.solve import solve

    out = np.empty(len(paths))
    for i, (k, idx) in enumerate(paths):
        moved = _lagrange([times[j] + delay for j in idx], [rights[j] for j in idx], times[k])
        out[i] = solve(rig, marker, Detection(lefts[k]), Detection(moved), solve_conf).residual_px
    return out


def estimate_delay(rig, marker, times, lefts, rights, max_delay: float = 0.1, solve_conf: dict | None = None) -> dict:
    """The constant delay (s) of the right view after the left from a recording of the
    marker moving (see the module's docstring).

    Args:
        times: (N,) the left views' times, s.
        lefts, rights: (N, 3, 2) each pair's ring centres (distorted px; NaN where not found).
        max_delay: the search covers [-max_delay, max_delay].
        solve_conf: the solve stage's settings (default: its defaults).
    Returns:
        ``delay_s``, ``sd_s`` (its standard error), ``pairs`` used, ``residual_px`` at the
        delay and at zero (RMS over the pairs), ``speed_px_s`` (the right view's median
        image speed: with little motion the delay cannot be seen).
    """
    from .stages import solve as solve_stage

    conf = {**solve_stage.default_conf, **(solve_conf or {})}
    times = np.asarray(times, np.float64)
    lefts, rights = np.asarray(lefts, np.float64), np.asarray(rights, np.float64)
    ok = np.isfinite(lefts).all(axis=(1, 2)) & np.isfinite(rights).all(axis=(1, 2))
    paths = [(k, idx) for k, idx in enumerate(_neighbours(ok)) if idx is not None]
    if len(paths) < 5:
        raise ValueError(f"the marker was found moving in only {len(paths)} pairs; at least 5 are needed")
    V = np.array([(rights[idx[-1]] - rights[idx[0]]) / (times[idx[-1]] - times[idx[0]]) for _, idx in paths])

    def cost(d: float) -> float:
        return float(np.sum(delay_residuals(rig, marker, times, lefts, rights, paths, d, conf) ** 2))

    # A coarse grid (the cost may have shallow side minima far out), then golden section.
    grid = np.linspace(-max_delay, max_delay, 41)
    costs = [cost(d) for d in grid]
    i = int(np.argmin(costs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    g = (np.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(40):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = cost(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = cost(b)
    d0 = 0.5 * (lo + hi)
    # Standard error from the curvature at the minimum: cost = S0 + c (d - d0)^2, with the
    # residuals' variance per coordinate from S0 (12 coordinates a pair, 6 pose parameters).
    h = max(1e-4, 0.02 * max_delay)
    s0, sp, sm = cost(d0), cost(d0 + h), cost(d0 - h)
    curv = (sp + sm - 2 * s0) / (h * h) / 2
    n = len(paths)
    # The cost sums each pair's mean square over its 6 centres: the sum of squares is 6 x cost,
    # over 12 n coordinates with 6 n + 1 parameters (each pair's pose, the delay).
    sd = float(np.sqrt(s0 / (max(6 * n - 1, 1) * curv))) if curv > 0 else float("inf")
    speed = float(np.median(np.linalg.norm(V, axis=2)))
    return {
        "delay_s": float(d0),
        "sd_s": sd,
        "pairs": n,
        "residual_px": float(np.sqrt(s0 / n)),
        "residual_px_at_zero": float(np.sqrt(cost(0.0) / n)),
        "speed_px_s": speed,
    }


__all__ = ["LOOSE", "Motion", "check_times", "delay_residuals", "estimate_delay", "motion", "right_at_left_time"]
