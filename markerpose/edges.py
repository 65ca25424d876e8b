"""Sub-pixel ring edges: ray profiles, edge positions and robust ellipse fits, in batches.

Every function here works on a batch of K ellipses at once — the rings of one view, or
of both views of a stereo pair — held in arrays padded to the largest ring, with masks
saying which rays, samples and points are real. Each ellipse of a batch gets exactly what
it would get alone. Why batches: a ring's refinement is a few hundred small array
operations (medians, percentiles, 3 x 3 solves); done ring by ring, a tracked frame's six
rings spend their time in the per-call overhead of those operations, not in arithmetic.

The method (see :func:`markerpose.classical.refine_ring` for its use):

- :func:`edge_points` samples rays from each ellipse's centre across its edge, fits the
  plateau levels (ink, paper) as planes over the ring, and locates the edge on each ray
  by the area method (the integral of the normalised profile);
- :func:`fit_robust` fits an ellipse to the edge points (direct least squares,
  :func:`fit_ellipses`) after a least-median-of-squares screen and with iterative
  outlier rejection;
- :func:`refine_edges` iterates the two until the ellipses stop moving.
"""

from __future__ import annotations

import numpy as np

from .jit import compiled

# --- masked statistics (numpy's median / linear percentile over the masked-in entries) ----------


def masked_median(x: np.ndarray, mask: np.ndarray, empty: float = 0.0) -> np.ndarray:
    """Median of each row's masked-in entries (last axis); ``empty`` for none."""
    return _masked_stat(x, mask, -1.0, empty)


def masked_percentile(x: np.ndarray, mask: np.ndarray, q: float, empty: float = 0.0) -> np.ndarray:
    """``np.percentile(row[mask], q)`` (linear) of each row (last axis); ``empty`` for none."""
    return _masked_stat(x, mask, float(q), empty)


def _masked_stat(x: np.ndarray, mask: np.ndarray, q: float, empty: float) -> np.ndarray:
    x2 = np.ascontiguousarray(x, np.float64).reshape(-1, x.shape[-1])
    out = np.empty(len(x2))
    _row_stats(x2, np.ascontiguousarray(mask, bool).reshape(x2.shape), q, float(empty), out)
    return out.reshape(x.shape[:-1])


@compiled
def _row_stats(x, mask, q, empty, out):  # pragma: no cover - compiled
    """Per row of ``x``, :func:`sorted_stat` of the masked-in entries; ``empty`` for none."""
    buf = np.empty(x.shape[1])
    for k in range(x.shape[0]):
        n = 0
        for i in range(x.shape[1]):
            if mask[k, i]:
                buf[n] = x[k, i]
                n += 1
        out[k] = sorted_stat(buf, n, q) if n else empty


@compiled
def sorted_stat(buf, n, q):  # pragma: no cover - compiled
    """The median (q < 0) or the linear q-th percentile of buf[:n] (n > 0), as numpy
    computes them from the sorted values (found by selection, reordering buf)."""
    if q < 0:
        return _median(buf, n)
    pos = (n - 1) * (q / 100.0)
    lo = int(np.floor(pos))
    t = pos - lo
    a = _select(buf, n, lo)  # then buf[lo + 1:n] holds the larger values
    b = buf[lo + 1 : n].min() if lo + 1 < n else a
    d = b - a
    return b - d * (1 - t) if t >= 0.5 else a + d * t  # numpy's lerp


# --- per-ray kernels (compiled) ------------------------------------------------------------------
# A tracked frame samples tens of thousands of profile points; in numpy each step of the
# profile analysis is a pass over all of them with its own temporaries, and the passes,
# not the arithmetic, are the cost. Numba runs each ray's analysis in one loop. The
# arithmetic is numpy's, operation for operation, so the edge points are the same to
# rounding.


@compiled
def _sample_rays(img, rows, cx, cy, ux, uy, lam, S, m, v, v_in, v_out):  # pragma: no cover - compiled
    """For the rows k of ``rows``: bilinear samples v[k, i, s] of ``img`` at cen[k] + u[k, i] lam[k, s] (coordinates
    clipped to the image, as :func:`bilinear`); each ray's mean of its first and of its
    last m[k] real samples (v_in, v_out) as numpy's cumulative sums give them."""
    h, w = img.shape
    xmax, ymax = w - 1.000001, h - 1.000001
    Sm = v.shape[2]
    xs, ys = np.empty(Sm), np.empty(Sm)
    for k in rows:
        Sk, mk = S[k], m[k]
        for i in range(v.shape[1]):
            # Coordinates first (a loop the compiler vectorises), then the gathers.
            ax, ay, bx, by = cx[k], cy[k], ux[k, i], uy[k, i]
            for s in range(Sm):
                xs[s] = min(max(ax + bx * lam[k, s], 0.0), xmax)
                ys[s] = min(max(ay + by * lam[k, s], 0.0), ymax)
            for s in range(Sm):
                x, y = xs[s], ys[s]
                x0, y0 = int(x), int(y)
                fx, fy = x - x0, y - y0
                v00, v01 = float(img[y0, x0]), float(img[y0, x0 + 1])
                v10, v11 = float(img[y0 + 1, x0]), float(img[y0 + 1, x0 + 1])
                top = v00 + fx * (v01 - v00)
                bot = v10 + fx * (v11 - v10)
                v[k, i, s] = top + fy * (bot - top)
            acc = 0.0
            at_m = at_sm = 0.0
            for s in range(Sk):
                if s == mk:
                    at_m = acc
                if s == Sk - mk:
                    at_sm = acc
                acc += v[k, i, s]
            v_in[k, i] = at_m / mk
            v_out[k, i] = (acc - at_sm) / mk


@compiled
def _ray_crossings(v, v_out, dd, lam, dl, S, r, e, found, width):  # pragma: no cover - compiled
    """Per ray of the profiles ``v`` normalised as f = (v - v_out) / dd (1 inside, 0
    outside): the 50 % crossing nearest the window centre (lambda, into ``e``), whether
    there is one, and the 10-90 % width of the transition around it (px)."""
    K, N, Sm = v.shape
    f = np.empty(Sm)
    for k in range(K):
        Sk = S[k]
        mid = (Sk - 1) / 2
        for i in range(N):
            vo, d = v_out[k, i], dd[k, i]
            for s in range(Sk):  # the normalised profile, once (a loop the compiler vectorises)
                f[s] = (v[k, i, s] - vo) / d
            # The crossing nearest the middle: a sample >= 0.5 followed by one below.
            j, best = 0, np.inf
            for s in range(Sk - 1):
                if f[s] >= 0.5 and not f[s + 1] >= 0.5 and abs(s - mid) < best:
                    j, best = s, abs(s - mid)
            found[k, i] = best < np.inf
            f0, f1 = f[j], f[j + 1]
            den = f0 - f1
            e[k, i] = lam[k, j] + dl[k] * (f0 - 0.5) / (den if den != 0 else 1.0)
            # Only the run of in-between samples around the crossing counts: in dark
            # images noise puts isolated plateau samples in (0.1, 0.9). Padding samples
            # count as plateau, which ends a run at a ring's last sample.
            before = -1
            for s in range(j, -1, -1):
                if f[s] <= 0.1 or f[s] >= 0.9:
                    before = s
                    break
            after = Sm
            for s in range(j + 1, Sm):
                if s >= Sk or f[s] <= 0.1 or f[s] >= 0.9:
                    after = s
                    break
            span_j = (j if before == j else after) - before
            span_j1 = after - (j + 1 if after == j + 1 else before)
            run = max(span_j, span_j1) - 1
            width[k, i] = max(run, 0) * dl[k] * r[k, i]


@compiled
def _ray_integrals(v, v_out, dd, lam, dl, S, xs, out):  # pragma: no cover - compiled
    """Per ray, the integral from lam[k, 0] to each x of xs[q] (lambda) of the
    piecewise-linear normalised profile f = (v - v_out) / dd, into out[q]."""
    K, N, Sm = v.shape
    f = np.empty(Sm)
    for k in range(K):
        Sk, l0, step = S[k], lam[k, 0], dl[k]
        for i in range(N):
            vo, d = v_out[k, i], dd[k, i]
            for s in range(Sk):
                f[s] = (v[k, i, s] - vo) / d
            for q in range(xs.shape[0]):
                x = xs[q, k, i]
                pos = min(max((x - l0) / step, 0.0), Sk - 1 - 1e-9)
                j = int(pos)
                t = pos - j
                acc = 0.0  # the integral from lam[k, 0] to lam[k, j]
                for s in range(j):
                    acc += 0.5 * (f[s + 1] + f[s]) * step
                f0 = f[j]
                f1 = f[min(j + 1, Sk - 1)]
                out[q, k, i] = acc + step * (t * f0 + 0.5 * t * t * (f1 - f0))


@compiled
def _scatter(P, w, mask, m, s, mu):  # pragma: no cover - compiled
    """Per row k: the mean m[k] and RMS radius s[k] of the masked-in points, and the
    weighted moments mu[k, (a, b)] = sum w x^a y^b (a + b <= 4, in the order of
    ``_MOMENTS``) of the points centred and scaled by them."""
    for k in range(P.shape[0]):
        n, mx, my = 0, 0.0, 0.0
        for i in range(P.shape[1]):
            if mask[k, i]:
                n += 1
                mx += P[k, i, 0]
                my += P[k, i, 1]
        n1 = max(n, 1)
        mx, my = mx / n1, my / n1
        ss = 0.0
        for i in range(P.shape[1]):
            if mask[k, i]:
                ss += (P[k, i, 0] - mx) ** 2 + (P[k, i, 1] - my) ** 2
        sk = np.sqrt(ss / n1)
        m[k, 0], m[k, 1], s[k] = mx, my, sk
        sc = sk if sk > 0 else 1.0
        mu[k] = 0.0
        for i in range(P.shape[1]):
            if mask[k, i]:
                x, y, wi = (P[k, i, 0] - mx) / sc, (P[k, i, 1] - my) / sc, w[k, i]
                x2, y2 = x * x, y * y
                mu[k, 0] += wi
                mu[k, 1] += wi * x
                mu[k, 2] += wi * y
                mu[k, 3] += wi * x2
                mu[k, 4] += wi * x * y
                mu[k, 5] += wi * y2
                mu[k, 6] += wi * x2 * x
                mu[k, 7] += wi * x2 * y
                mu[k, 8] += wi * x * y2
                mu[k, 9] += wi * y2 * y
                mu[k, 10] += wi * x2 * x2
                mu[k, 11] += wi * x2 * x * y
                mu[k, 12] += wi * x2 * y2
                mu[k, 13] += wi * x * y2 * y
                mu[k, 14] += wi * y2 * y2


# (a, b) of the moments _scatter returns; the scatter matrices of the conic's monomials
# [x^2, xy, y^2] (D1) and [x, y, 1] (D2) are sums of these.
_MOMENTS = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3), (4, 0), (3, 1), (2, 2), (1, 3), (0, 4)]
_D1 = [(2, 0), (1, 1), (0, 2)]
_D2 = [(1, 0), (0, 1), (0, 0)]


def _scatter_index(rows: list, cols: list) -> np.ndarray:
    return np.array([[_MOMENTS.index((a + c, b + d)) for c, d in cols] for a, b in rows])


_S1, _S2, _S3 = _scatter_index(_D1, _D1), _scatter_index(_D1, _D2), _scatter_index(_D2, _D2)


@compiled
def _select(a, n, kth):  # pragma: no cover - compiled
    """The kth smallest of a[:n], in place (Wirth's selection: afterwards a[:kth] holds
    the smaller ones, a[kth + 1:n] the larger)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = a[kth]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if j < kth:
            lo = i
        if kth < i:
            hi = j
    return a[kth]


@compiled
def _lmeds(X, off, mask, cnt, idx, min_px, keep):  # pragma: no cover - compiled
    """:func:`lmeds_inliers` per ring k (X[k]: the model's five terms (5, N), one row per
    term): each 5-point subset idx[k, s] of its first cnt[k] points fitted exactly (skipped
    when |det| <= 1e-6), the subset with the smallest median absolute residual kept (the
    first of equals), and keep[k] set to the points within max(2.5 robust sigmas, min_px)
    of its model; keep[k] = mask[k] when no subset is regular.

    A subset's median is only computed when it can beat the best so far: while fewer
    than half the residuals lie below the best median, its median cannot be smaller."""
    K, _, N = X.shape
    S = idx.shape[1]
    A, b = np.empty((5, 5)), np.empty((5, 1))
    best = np.empty(5)
    buf = np.empty(N)
    for k in range(K):
        n = cnt[k]
        best_med = np.inf
        found = False
        for s in range(S):
            for r in range(5):
                q = idx[k, s, r]
                for j in range(5):
                    A[r, j] = X[k, j, q]
                b[r, 0] = off[k, q]
            coef, det, _ = _lu_solve_det(A, b)
            if not abs(det) > 1e-6:
                continue
            c0, c1, c2, c3, c4 = coef[0, 0], coef[1, 0], coef[2, 0], coef[3, 0], coef[4, 0]
            for i in range(n):  # the residuals (a loop over contiguous rows: vectorised)
                buf[i] = abs(off[k, i] - ((((c0 * X[k, 0, i] + c1 * X[k, 1, i]) + c2 * X[k, 2, i]) + c3 * X[k, 3, i]) + c4 * X[k, 4, i]))
            below = 0
            for i in range(n):
                below += buf[i] < best_med
            if found and below < (n + 1) // 2:  # the (n - 1) // 2-th smallest is >= best
                continue
            med = _median(buf, n)
            if not found or med < best_med:
                best_med = med
                for j in range(5):
                    best[j] = coef[j, 0]
            found = True
        if not found:
            for i in range(N):
                keep[k, i] = mask[k, i]
            continue
        sigma = 1.4826 * (1 + 5.0 / max(n - 5, 1)) * best_med
        thr = max(2.5 * sigma, min_px)
        for i in range(N):
            pred = (((best[0] * X[k, 0, i] + best[1] * X[k, 1, i]) + best[2] * X[k, 2, i]) + best[3] * X[k, 3, i]) + best[4] * X[k, 4, i]
            keep[k, i] = mask[k, i] and abs(off[k, i] - pred) <= thr


# --- ray profiles --------------------------------------------------------------------------------


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` (float or 8-bit) at float coordinates (any shape); also a
    validity mask.

    Done in float64 numpy, not ``cv2.remap``, whose fixed-point weights quantise positions
    to 1/32 px.
    """
    h, w = img.shape
    valid = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    return _bilinear_inside(img, np.clip(x, 0, w - 1.000001), np.clip(y, 0, h - 1.000001)), valid


def _bilinear_inside(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:func:`bilinear` of coordinates known to lie in [0, w - 1.000001] x [0, h - 1.000001]."""
    w = img.shape[1]
    x0 = x.astype(np.intp)  # truncation is the floor: coordinates >= 0
    y0 = y.astype(np.intp)
    fx, fy = x - x0, y - y0
    flat = img.ravel()
    i00 = y0 * w + x0
    v00, v01, v10, v11 = (flat[i] for i in (i00, i00 + 1, i00 + w, i00 + w + 1))
    if not np.issubdtype(img.dtype, np.floating):  # an 8-bit image sampled as it is, without a float copy
        v00, v01, v10, v11 = (v.astype(np.float64) for v in (v00, v01, v10, v11))
    top = v00 + fx * (v01 - v00)
    bot = v10 + fx * (v11 - v10)
    return top + fy * (bot - top)


def crossings(v: np.ndarray, v_out: np.ndarray, dd: np.ndarray, lam: np.ndarray, dl: np.ndarray, S: np.ndarray, r: np.ndarray):
    """Per ray of (K, N, Smax) profiles ``v`` normalised as f = (v - v_out) / dd (ring k has
    S[k] real samples at ``lam[k]``, step dl[k]; r (K, N) px per unit lambda): the 50 %
    crossing nearest the window centre (lambda), its validity, and the 10-90 % width of
    the transition around it (px)."""
    K, N, _ = v.shape
    e, found, width = np.empty((K, N)), np.empty((K, N), bool), np.empty((K, N))
    _ray_crossings(v, v_out, dd, lam, dl, S, r, e, found, width)
    return e, found, width


def integral(v: np.ndarray, v_out: np.ndarray, dd: np.ndarray, lam: np.ndarray, dl: np.ndarray, S: np.ndarray, xs: tuple) -> list:
    """Per ray, the integral from lam[k, 0] to x of the piecewise-linear normalised profile
    (as :func:`crossings`), for each x (K, N) of ``xs``."""
    out = np.empty((len(xs), *v.shape[:2]))
    _ray_integrals(v, v_out, dd, lam, dl, S, np.stack(xs), out)
    return list(out)


def plane_levels(
    xy: np.ndarray, values: np.ndarray, use: np.ndarray, center: np.ndarray, scale: np.ndarray, floor: np.ndarray
) -> np.ndarray:
    """Per row k, fit ``values ≈ a + g . (xy - center)`` on the rays ``use``; evaluate at all.

    Robust: rays farther than max(3 MAD, ``floor``) from the median, then from the fit, are
    left out (a dark occluder across a few rays must not tilt the plane). The gradient is
    ridge-regularised (weight ~ (0.15 scale)^2 per ray), so directions the used rays do not
    span — e.g. only two opposite sectors are clean under motion blur — fall back to a
    constant level instead of an extrapolated slope.

    Args: xy (K, N, 2), values / use (K, N), center (K, 2), scale / floor (K,).
    """
    out = np.empty(values.shape)
    _plane_rows(
        np.ascontiguousarray(xy, np.float64),
        np.ascontiguousarray(values, np.float64),
        np.ascontiguousarray(use, bool),
        np.ascontiguousarray(center, np.float64),
        (0.15 * np.asarray(scale, np.float64)) ** 2,
        np.ascontiguousarray(floor, np.float64),
        out,
    )
    return out


@compiled
def _median(buf, n):  # pragma: no cover - compiled
    """numpy's median of buf[:n] (n > 0), reordering it."""
    lo = _select(buf, n, (n - 1) // 2)
    return 0.5 * (lo + (buf[n // 2 : n].min() if n % 2 == 0 else lo))


@compiled
def _plane_normal_equations(xy, values, use, center, res, lim, k, M, rhs):  # pragma: no cover - compiled
    """Row ``k``'s plane normal equations (into ``M`` (3, 3), upper triangle, and ``rhs``
    (3,)) over its used samples whose residual ``res`` is within ``lim``; returns their number."""
    N = values.shape[1]
    M[:] = 0.0
    rhs[:] = 0.0
    cnt = 0
    for i in range(N):
        if use[k, i] and abs(res[i]) <= lim:
            cnt += 1
            a1, a2 = xy[k, i, 0] - center[k, 0], xy[k, i, 1] - center[k, 1]
            v = values[k, i]
            M[0, 0] += 1.0
            M[0, 1] += a1
            M[0, 2] += a2
            M[1, 1] += a1 * a1
            M[1, 2] += a1 * a2
            M[2, 2] += a2 * a2
            rhs[0] += v
            rhs[1] += a1 * v
            rhs[2] += a2 * v
    return cnt


@compiled
def _eliminate3(M, rhs):  # pragma: no cover - compiled
    """Forward elimination with partial pivoting of the system M x = rhs (3 x 3), in
    place (M upper triangular after it); False, stopping there, when M is singular."""
    for col in range(3):
        piv = col
        for row in range(col + 1, 3):
            if abs(M[row, col]) > abs(M[piv, col]):
                piv = row
        if M[piv, col] == 0.0:
            return False
        if piv != col:
            for j in range(3):
                M[col, j], M[piv, j] = M[piv, j], M[col, j]
            rhs[col], rhs[piv] = rhs[piv], rhs[col]
        for row in range(col + 1, 3):
            f = M[row, col] / M[col, col]
            for j in range(col, 3):
                M[row, j] -= f * M[col, j]
            rhs[row] -= f * rhs[col]
    return True


@compiled
def _plane_rows(xy, values, use, center, pen, floor, out):  # pragma: no cover - compiled
    """:func:`plane_levels` row by row: the robust selection, the ridge-regularised
    normal equations (3 x 3, solved by elimination with partial pivoting; a singular
    system keeps the previous coefficients)."""
    K, N = values.shape
    buf, res = np.empty(N), np.empty(N)
    M, rhs = np.empty((3, 3)), np.empty(3)
    for k in range(K):
        n = 0
        for i in range(N):
            if use[k, i]:
                buf[n] = values[k, i]
                n += 1
        c0 = _median(buf, n) if n else 0.0
        c1 = c2 = 0.0
        for i in range(N):
            res[i] = values[k, i] - c0
        for _ in range(2):
            n = 0
            for i in range(N):
                if use[k, i]:
                    buf[n] = abs(res[i])
                    n += 1
            lim = max(3 * (1.4826 * (_median(buf, n) if n else 0.0)), floor[k])
            cnt = _plane_normal_equations(xy, values, use, center, res, lim, k, M, rhs)
            if cnt < 6:
                break
            M[1, 1] += cnt * pen[k]
            M[2, 2] += cnt * pen[k]
            M[1, 0], M[2, 0], M[2, 1] = M[0, 1], M[0, 2], M[1, 2]
            if _eliminate3(M, rhs):
                x2 = rhs[2] / M[2, 2]
                x1 = (rhs[1] - M[1, 2] * x2) / M[1, 1]
                c0 = (rhs[0] - M[0, 1] * x1 - M[0, 2] * x2) / M[0, 0]
                c1, c2 = x1, x2
            for i in range(N):
                res[i] = values[k, i] - (c0 + c1 * (xy[k, i, 0] - center[k, 0]) + c2 * (xy[k, i, 1] - center[k, 1]))
        for i in range(N):
            out[k, i] = c0 + c1 * (xy[k, i, 0] - center[k, 0]) + c2 * (xy[k, i, 1] - center[k, 1])


@compiled
def _ray_frame(L, cen, n, S, half, hw, u, r, lam, dl, xy, ok):  # pragma: no cover - compiled
    """The rays of K ellipses (L = Q^(-1/2)): ray i of n[k] from the centre at angle
    2 pi i / n[k] on the unit circle, u[k, :, i] its edge point at lambda 1 relative to
    the centre, r its length (px per unit lambda), xy the edge point itself; the window's
    lambda = 1 + linspace(-half[k], half[k], S[k]) (as numpy computes it: window tests compare
    run lengths times this step against fractions of the window), its padding repeating
    the last sample, and its step dl; ``ok``: a real ray whose window (a segment) lies in
    its image (height, width ``hw[k]``)."""
    K, N = r.shape
    Sm = lam.shape[1]
    for k in range(K):
        hk = half[k]
        step = (2 * hk) / (S[k] - 1)
        for s in range(Sm):
            lam[k, s] = 1.0 + (hk if s >= S[k] - 1 else min(s, S[k] - 1) * step + (-hk))
        dl[k] = lam[k, 1] - lam[k, 0]
        lo, hi = lam[k, 0], lam[k, Sm - 1]
        for i in range(N):
            ray = i < n[k]
            t = 2 * np.pi * i / n[k] if ray else 0.0
            ct, st = np.cos(t), np.sin(t)
            ux = L[k, 0, 0] * ct + L[k, 0, 1] * st
            uy = L[k, 1, 0] * ct + L[k, 1, 1] * st
            u[k, 0, i], u[k, 1, i] = ux, uy
            r[k, i] = np.hypot(ux, uy)
            xy[k, i, 0], xy[k, i, 1] = cen[k, 0] + ux, cen[k, 1] + uy
            x0, x1 = cen[k, 0] + ux * lo, cen[k, 0] + ux * hi
            y0, y1 = cen[k, 1] + uy * lo, cen[k, 1] + uy * hi
            ok[k, i] = ray and min(x0, x1) >= 0 and min(y0, y1) >= 0 and max(x0, x1) <= hw[k, 1] - 1 and max(y0, y1) <= hw[k, 0] - 1


@compiled
def _normalisers(v_in, v_out, dark):  # pragma: no cover - compiled
    """Per ray, the contrast of its levels (positive for the expected polarity: the inner
    side darker when ``dark``) and the divisor that normalises its profile to 1 inside,
    0 outside (the levels' difference, kept away from zero)."""
    K, N = v_in.shape
    contrast, dd = np.empty((K, N)), np.empty((K, N))
    for k in range(K):
        for i in range(N):
            diff = v_in[k, i] - v_out[k, i]  # > 0 when the inner side is brighter
            contrast[k, i] = -diff if dark else diff
            dd[k, i] = diff if abs(diff) > 1e-9 else 1e-9
    return contrast, dd


@compiled
def _first_look(v, v_in, v_out, lam, dl, S, r, ok, floor, dark, w1090, sane, width):  # pragma: no cover - compiled
    """The profiles normalised by their own ends: each ray's 10-90 % width, whether it is
    sane (a crossing, contrast above the floor) and each ring's 75th percentile of the
    sane rays' widths."""
    K, N, _ = v.shape
    contrast, dd = _normalisers(v_in, v_out, dark)
    e, found = np.empty((K, N)), np.empty((K, N), np.bool_)
    _ray_crossings(v, v_out, dd, lam, dl, S, r, e, found, w1090)
    for k in range(K):
        for i in range(N):
            sane[k, i] = ok[k, i] and found[k, i] and contrast[k, i] > floor[k]
    _row_stats(w1090, sane, 75.0, 0.0, width)


@compiled
def _neighbours(xy, r, width, half, kk, co, Qo, b_o, n, min_free, ok, far, n_use):  # pragma: no cover - compiled
    """Rays whose window a blurred neighbour (outer ellipse co[p], Qo[p] of ring kk[p])
    may reach, and their opposite rays, out of ``far``; where enough rays stay
    (``min_free`` of them), only those count (``ok``, ``n_use``)."""
    K, N = r.shape
    for p in range(len(kk)):
        k = kk[p]
        for i in range(N):
            # A blurred neighbour darkens this profile's outer plateau when its edge is
            # closer than the window plus the blur's reach (~0.65 of the 10-90 % width) to ours.
            reach = half[k] * r[k, i] + 0.65 * width[k] + 1.0
            dx, dy = xy[k, i, 0] - co[p, 0], xy[k, i, 1] - co[p, 1]
            lam_o = np.sqrt(dx * (Qo[p, 0, 0] * dx + Qo[p, 0, 1] * dy) + dy * (Qo[p, 1, 0] * dx + Qo[p, 1, 1] * dy))
            if not (lam_o - 1.0) * b_o[p] > reach:  # lower bound on the distance to its edge, px
                far[k, i] = False
    has = np.zeros(K, np.bool_)
    for p in range(len(kk)):
        has[kk[p]] = True
    _symmetric_drop(far, has, n, min_free, ok, n_use)


@compiled
def _plate_rays(xy, r, width, half, lines, plated, n, min_free, ok, far, keep, n_use, reached):  # pragma: no cover - compiled
    """Rays of the rings ``plated`` whose window the plate's blurred edge (its sides
    ``lines[k]``, distances positive inside) may reach, and their opposite rays, out of
    ``keep``: what lies beyond the plate bleeds in as a neighbour does. Where enough rays
    stay with those ``far`` from the neighbours (``min_free`` of them), ``n_use`` counts
    them; elsewhere ``keep`` is all True. ``reached[k]``: the plate's edge reached some of
    ring k's rays (left out or, too many to leave out, kept)."""
    K, N = r.shape
    for k in range(K):
        if not plated[k]:
            continue
        for i in range(N):
            reach = half[k] * r[k, i] + 0.65 * width[k] + 1.0
            for j in range(4):
                if not lines[k, j, 0] * xy[k, i, 0] + lines[k, j, 1] * xy[k, i, 1] + lines[k, j, 2] > reach:
                    keep[k, i] = False
    for k in range(K):
        for i in range(N):
            keep[k, i] = keep[k, i] and far[k, i]
    both = keep.copy()
    _symmetric_drop(both, plated, n, min_free, ok.copy(), n_use)
    for k in range(K):
        hit = False
        for i in range(N):
            hit = hit or not keep[k, i]
            keep[k, i] = both[k, i] or not plated[k]
        reached[k] = plated[k] and hit


@compiled
def _symmetric_drop(far, has, n, min_free, ok, n_use):  # pragma: no cover - compiled
    """:func:`_neighbours`' last step: each dropped ray's opposite out of ``far`` too; for
    the rings ``has`` where enough rays stay (``min_free`` of them), only those count
    (``ok``, ``n_use``), elsewhere ``far`` is all True."""
    K, N = far.shape
    row = np.empty(N, np.bool_)
    for k in range(K):
        # Drop the opposite rays too: the blurred edge is centrally symmetric about the
        # centre (not an ellipse under motion blur), so a symmetric point set keeps the
        # fitted centre unbiased where a one-sided gap would not.
        nk = n[k]
        row[:] = far[k]
        n_far = 0
        for i in range(N):
            opp = (i - nk // 2) % nk if i < nk else 0
            far[k, i] = row[i] and row[opp]
            n_far += far[k, i] and i < nk
        if has[k] and n_far >= min_free * nk:
            n_use[k] = n_far
            for i in range(N):
                ok[k, i] = ok[k, i] and far[k, i]
        else:
            far[k] = True  # better contaminated rays than none


@compiled
def _compact(cen, u, e, W, ok, P, Wc, cnt):  # pragma: no cover - compiled
    """Edge points cen + u e and their weights, the valid ones first (in ray order), then
    the others; cnt[k] valid in row k."""
    K, N = e.shape
    for k in range(K):
        j = 0
        for rnd in range(2):
            for i in range(N):
                if ok[k, i] == (rnd == 0):
                    P[k, j, 0] = cen[k, 0] + u[k, 0, i] * e[k, i]
                    P[k, j, 1] = cen[k, 1] + u[k, 1, i] * e[k, i]
                    Wc[k, j] = W[k, i]
                    j += 1
            if rnd == 0:
                cnt[k] = j


@compiled
def _ray_levels(v_in, v_out, xy, cen, pen, clean, n, level_tol, ok, planes):  # pragma: no cover - compiled
    """The plateau levels of each ring with enough clean rays (``planes[k]``: at least
    six, and a tenth of its rays) replaced, in place, by planes fitted on those rays
    (:func:`plane_levels`; floor a tenth of the levels' difference); rays whose two ends
    depart from the planes unequally are dropped from ``ok``."""
    K, N = v_in.shape
    med_in, med_out = np.empty(K), np.empty(K)
    _row_stats(v_in, clean, -1.0, 0.0, med_in)
    _row_stats(v_out, clean, -1.0, 0.0, med_out)
    fl, fin, fout = np.empty(1), np.empty((1, N)), np.empty((1, N))
    for k in range(K):
        cnt = 0
        for i in range(N):
            cnt += clean[k, i]
        planes[k] = cnt >= max(6.0, 0.1 * n[k])
        if not planes[k]:
            continue
        fl[0] = 0.1 * abs(med_in[k] - med_out[k])
        _plane_rows(xy[k : k + 1], v_in[k : k + 1], clean[k : k + 1], cen[k : k + 1], pen[k : k + 1], fl, fin)
        _plane_rows(xy[k : k + 1], v_out[k : k + 1], clean[k : k + 1], cen[k : k + 1], pen[k : k + 1], fl, fout)
        for i in range(N):
            # Blur moves both ends of a profile toward the middle by about the same amount;
            # something dark or bright next to the ring (an occluder, clutter, a neighbour)
            # moves one end only. Such rays are dropped.
            if abs((v_in[k, i] - fin[0, i]) + (v_out[k, i] - fout[0, i])) > level_tol * abs(fin[0, i] - fout[0, i]):
                ok[k, i] = False
            v_in[k, i], v_out[k, i] = fin[0, i], fout[0, i]


@compiled
def _ray_edges(
    v, v_in, v_out, lam, dl, S, r, ok, floor, dark, half, area, aw0, aw1, weights, e, W, w1090, width
):  # pragma: no cover - compiled
    """Each ray's edge (lambda, into ``e``) from its profile normalised by the plateau
    levels, its fit weight (``W``), its 10-90 % width (``w1090``) and each ring's 75th
    percentile of those widths over the valid rays (``width``); rays without a clear
    edge well inside the window are dropped from ``ok``."""
    K, N, _ = v.shape
    contrast, dd = _normalisers(v_in, v_out, dark)
    med = np.empty(K)
    _row_stats(contrast, ok, -1.0, 0.0, med)
    for k in range(K):
        lim = max(0.3 * med[k], floor[k])  # NaN first: a NaN median drops the ring's rays, as numpy's maximum did
        for i in range(N):
            ok[k, i] = ok[k, i] and contrast[k, i] > lim
    found = np.empty((K, N), np.bool_)
    _ray_crossings(v, v_out, dd, lam, dl, S, r, e, found, w1090)
    for k in range(K):
        for i in range(N):
            ok[k, i] = ok[k, i] and found[k, i]
    if area:
        # Integral of the normalised profile over [e - h, e + h] is the edge position minus
        # (e - h) for any symmetric blur, and exact for area-sampled pixels. The window
        # grows with the blur (a high quantile: motion blur widens one direction only).
        _row_stats(w1090, ok, 75.0, 0.0, width)
        xs, at = np.empty((2, K, N)), np.empty((2, K, N))
        for k in range(K):
            for i in range(N):
                h = (aw0 * width[k] + aw1) / r[k, i]
                xs[0, k, i] = min(e[k, i] + h, 1.0 + half[k])
                xs[1, k, i] = max(e[k, i] - h, lam[k, 0])
        _ray_integrals(v, v_out, dd, lam, dl, S, xs, at)
        for k in range(K):
            for i in range(N):
                e[k, i] = xs[1, k, i] + at[0, k, i] - at[1, k, i]
    # The edge must lie well inside the window.
    for k in range(K):
        lo, hi = 1.0 - half[k] + 0.15 * 2 * half[k], 1.0 + half[k] - 0.15 * 2 * half[k]
        for i in range(N):
            ok[k, i] = ok[k, i] and e[k, i] > lo and e[k, i] < hi
            # Edge position noise ~ noise x transition width / contrast: under motion blur
            # the rays along the motion are smeared and uncertain, those across it sharp.
            # (The ellipse fit does not depend on the weights' overall scale.)
            W[k, i] = (abs(contrast[k, i]) / max(w1090[k, i], 1.0)) ** 2 if weights else 1.0
    _row_stats(w1090, ok, 75.0, 0.0, width)


def _circular_smooth(v: np.ndarray, k: int) -> np.ndarray:
    ker = np.ones(k) / k
    return np.convolve(np.r_[v[-k:], v, v[:k]], ker, "same")[k:-k]


def edge_points(
    grays: list,
    view: np.ndarray,
    cen: np.ndarray,
    Q: np.ndarray,
    half,
    dark_inside: bool,
    c: dict,
    floor: np.ndarray,
    others: list,
    plates: list | None = None,
):
    """Sub-pixel edge points along rays of K ellipses (x - cen)^T Q (x - cen) = 1.

    Rays run from the centre through the ellipse (radial lines are images of the circle's
    radii under an affine map, so each ray crosses the edge once); each is sampled over
    ``lambda in [1 - half, 1 + half]`` (lambda = 1 on the ellipse).

    Plateau levels (ink, paper) are fitted as planes over the ring from the rays that
    reach them — those whose transition is narrow compared with the window and which do
    not look toward a neighbour. Under motion blur the rays along the motion never reach
    a plateau inside the window; levels taken from their own ends would put the 50 %
    level wherever the window happens to be, so the estimate would not move toward the edge.

    Args:
        grays: the images; ellipse k is in ``grays[view[k]]``.
        cen, Q: (K, 2), (K, 2, 2) the current ellipses.
        half: half-window in units of the ellipse: one for all, or (K,) one per ellipse.
        dark_inside: polarity (True for the outer edge of a ring).
        c: the classical detector's settings.
        floor: (K,) smallest inner/outer level difference, grey levels.
        others: per ellipse, a list of (centre, Q) outer ellipses of neighbouring rings:
            rays whose window ends within a blur width of them are dropped (their light
            bleeds into the profile).
        plates: per ellipse, None or the plate's outline as four lines (4, 3): (a, b, c)
            with a x + b y + c the distance inside the plate, px (:func:`plate_lines`):
            rays whose window ends within a blur width of the plate's edge are dropped
            too (what lies beyond the plate bleeds in as a neighbour does); None: none.
    Returns:
        (P (K, M, 2) edge points, valid first: mask (K, M), number of rays not dropped
        for a neighbour (K,), fit weights (K, M), the 75th percentile of the 10-90 % edge
        widths of the valid points in px (K,), the covariance of the edges' shared shift
        (K, 2, 2), :func:`_shared_covs`, whether the plate's blurred edge reached the
        ring's rays (K,): left out, or kept where too many to leave out), and the widths'
        25th percentile over their 75th (K,): motion blur widens the edges along the
        motion only, and the edges across it stay sharp (a low ratio); defocus widens them
        all alike (near 1).
    """
    # Three compiled steps (the rays, the levels, the edges) with the images' sampling and
    # the rare smoothing between them: a pass runs for every fit of every frame, and the
    # many small array steps between kernels cost as much as the kernels did.
    K = len(cen)
    half = _per_ellipse(half, K)
    cen = np.ascontiguousarray(cen, np.float64)
    view = np.asarray(view, np.intp)
    hw = np.array([g.shape[:2] for g in grays], np.float64)[view]
    u, r, xy, lam, dl, ok, n, S, m, a, b, v, v_in, v_out, ux, uy = _ray_setup(
        np.ascontiguousarray(Q, np.float64).reshape(K, 2, 2),
        cen,
        half,
        hw,
        float(c["edge_spacing"]),
        int(c["min_rays"]),
        int(c["max_rays"]),
        float(c["edge_step"]),
        float(c["level_samples"]),
    )
    cx, cy = cen[:, 0].copy(), cen[:, 1].copy()
    for g in np.unique(view):
        _sample_rays(np.ascontiguousarray(grays[g]), np.nonzero(view == g)[0], cx, cy, ux, uy, lam, S, m, v, v_in, v_out)
    floor = np.ascontiguousarray(np.broadcast_to(np.asarray(floor, np.float64), (K,)))
    kk, co, Qo = _neighbour_arrays(others)
    plated, lines = _plate_arrays(plates, K)
    w1090, width, far, n_use, keep, reached, clean, local_in, local_out, pen, planes = _levels_pass(
        v, v_in, v_out, lam, dl, S, r, ok, floor, bool(dark_inside), half, xy, cen, a, b, n, kk, co, Qo, plated, lines,
        float(c["min_free_frac"]), float(c["level_tol"]),
    )  # fmt: skip
    for k in np.nonzero(~planes)[0]:  # too few clean rays: the local levels smoothed along the ellipse
        w = max(1, round(c["level_smooth"] * n[k]))
        if w > 1:
            v_in[k, : n[k]] = _circular_smooth(v_in[k, : n[k]], w)
            v_out[k, : n[k]] = _circular_smooth(v_out[k, : n[k]], w)
    aw = c["area_window"]
    return _edges_pass(
        v, v_in, v_out, lam, dl, S, r, ok, floor, bool(dark_inside), half, xy, cen, u, n_use, keep, reached, clean,
        local_in, local_out, pen, planes, c["edge_method"] == "area", float(aw[0]), float(aw[1]), bool(c["edge_weights"]),
    )  # fmt: skip


@compiled
def _ray_setup(Q, cen, half, hw, spacing, min_rays, max_rays, step, level_samples):  # pragma: no cover - compiled
    """The rays of K ellipses Q (K, 2, 2) about ``cen`` (K, 2): even numbers of rays n (K,)
    about ``spacing`` px apart along the perimeter, samples per ray S (K,) about ``step``
    px apart over the window ``half``, samples per plateau level m (K,) (``level_samples``
    of them), the semi-axes a, b (K,); the rays' frame (:func:`_ray_frame`: u (K, 2, N),
    r (K, N), xy (K, N, 2), lam (K, Sm), dl (K,), ok (K, N); ``hw`` (K, 2) each ellipse's
    image's height and width); the samples' arrays to fill (v (K, N, Sm), v_in, v_out
    (K, N)) and the directions' coordinates ux, uy (K, N)."""
    K = Q.shape[0]
    L, eig = np.empty((K, 2, 2)), np.empty((K, 2))
    _spd2_rows(Q, True, L, eig)  # Q^-1/2
    a, b = np.empty(K), np.empty(K)
    n, S, m = np.empty(K, np.int64), np.empty(K, np.int64), np.empty(K, np.intp)
    for k in range(K):
        a[k], b[k] = 1 / np.sqrt(eig[k, 0]), 1 / np.sqrt(eig[k, 1])
        perim = np.pi * (3 * (a[k] + b[k]) - np.sqrt((3 * a[k] + b[k]) * (a[k] + 3 * b[k])))
        rays = np.round(perim / spacing / 2)
        n[k] = 2 * int(min(max(rays, min_rays // 2), max_rays // 2)) if np.isfinite(rays) else 2 * (min_rays // 2)
        samples = np.ceil(2 * half[k] * a[k] / step)
        S[k] = int(min(max(samples, 8.0), 200.0)) + 1 if np.isfinite(samples) else 9
        m[k] = int(max(2.0, np.round(level_samples * S[k])))
    N, Sm = max(n.max(), 1), S.max()
    u, r, xy = np.empty((K, 2, N)), np.empty((K, N)), np.empty((K, N, 2))
    lam, dl, ok = np.empty((K, Sm)), np.empty(K), np.empty((K, N), np.bool_)
    _ray_frame(L, cen, n, S, half, hw, u, r, lam, dl, xy, ok)
    ux, uy = u[:, 0].copy(), u[:, 1].copy()
    v, v_in, v_out = np.empty((K, N, Sm)), np.empty((K, N)), np.empty((K, N))
    return u, r, xy, lam, dl, ok, n, S, m, a, b, v, v_in, v_out, ux, uy


def _neighbour_arrays(others: list) -> tuple:
    """The neighbours' outer ellipses of :func:`edge_points`' ``others`` as arrays: (ring
    (P,), centre (P, 2), Q (P, 2, 2)) per pair of a ring and a neighbour."""
    pairs = [(k, co, Qo) for k, oth in enumerate(others) for co, Qo in oth]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2))
    return (
        np.array([p[0] for p in pairs], np.int64),
        np.array([p[1] for p in pairs], np.float64),
        np.array([p[2] for p in pairs], np.float64),
    )


def _plate_arrays(plates: list | None, K: int) -> tuple:
    """Which of the K rings have their plate's sides (K,), and those sides (K, 4, 3)."""
    plated, lines = np.zeros(K, bool), np.zeros((K, 4, 3))
    for k, p in enumerate(plates or []):
        if p is not None:
            plated[k], lines[k] = True, p
    return plated, lines


@compiled
def _levels_pass(
    v, v_in, v_out, lam, dl, S, r, ok, floor, dark, half, xy, cen, a, b, n, kk, co, Qo, plated, lines, min_free, level_tol
):  # pragma: no cover - compiled
    """:func:`edge_points`' plateau levels, in place in v_in, v_out. First the profiles
    normalised by their own ends (:func:`_first_look`: each ray's 10-90 % width w1090 and
    the rings' blur width); the rays that a blurred neighbour (ring kk[p]'s neighbour
    co[p], Qo[p]) may reach (:func:`_neighbours`, decided with that first-look width) and
    the plate's edge (the rings ``plated``, their sides ``lines``: :func:`_plate_rays`; it
    leaves the levels and the fit, not the edges' width, which the blurred-ring fit's gate
    reads); then planes fitted on the clean rays, the transition well inside the window
    (:func:`_ray_levels`, ridge ``pen``), where enough are clean (``planes``; elsewhere
    the caller smooths the local levels). Returns (w1090, width, far, n_use, keep, reached,
    clean, the local levels v_in and v_out before the planes, pen, planes)."""
    K, N = r.shape
    w1090, sane, width = np.empty((K, N)), np.empty((K, N), np.bool_), np.empty(K)
    _first_look(v, v_in, v_out, lam, dl, S, r, ok, floor, dark, w1090, sane, width)
    far = np.ones((K, N), np.bool_)
    n_use = n.copy()
    if len(kk):
        eig, root = np.empty((len(kk), 2)), np.empty((len(kk), 2, 2))
        _spd2_rows(Qo, False, root, eig)
        b_o = 1 / np.sqrt(eig[:, 1])
        _neighbours(xy, r, width, half, kk, co, Qo, b_o, n, min_free, ok, far, n_use)
    keep, reached = np.ones((K, N), np.bool_), np.zeros(K, np.bool_)
    if plated.any():
        _plate_rays(xy, r, width, half, lines, plated, n, min_free, ok, far, keep, n_use, reached)
    clean = np.empty((K, N), np.bool_)
    for k in range(K):
        for i in range(N):
            clean[k, i] = sane[k, i] and far[k, i] and w1090[k, i] < 1.2 * half[k] * r[k, i] and keep[k, i]
    local_in, local_out = v_in.copy(), v_out.copy()
    pen = (0.15 * np.sqrt(a * b)) ** 2
    planes = np.empty(K, np.bool_)
    _ray_levels(v_in, v_out, xy, cen, pen, clean, n, level_tol, ok, planes)
    return w1090, width, far, n_use, keep, reached, clean, local_in, local_out, pen, planes


@compiled
def _edges_pass(
    v, v_in, v_out, lam, dl, S, r, ok, floor, dark, half, xy, cen, u, n_use, keep, reached, clean,
    local_in, local_out, pen, planes, area, aw0, aw1, weights,
):  # pragma: no cover - compiled  # fmt: skip
    """:func:`edge_points`' edges from the plateau levels: each ray's edge, weight and
    width (:func:`_ray_edges`), the widths' evenness, the rays the plate's edge reaches
    left out (``keep``), the covariance of the edges' shared shift (:func:`_shared_covs`:
    the planes' gradient errors move every edge of the ring together, each by the level
    error over the contrast times the edge locator's reach: the integral's half window,
    for the mid-level crossing the 10-90 % width over 1.6; zero where the levels are not
    planes), the points compacted (:func:`_compact`). Returns :func:`edge_points`' tuple."""
    K, N = r.shape
    e, W, w1090, width = np.empty((K, N)), np.empty((K, N)), np.empty((K, N)), np.empty(K)
    _ray_edges(v, v_in, v_out, lam, dl, S, r, ok, floor, dark, half, area, aw0, aw1, weights, e, W, w1090, width)
    low = np.empty(K)
    _row_stats(w1090, ok, 25.0, 0.0, low)  # the 25th percentile, over the rays the 75th is over
    even = np.ones(K)
    for k in range(K):
        if width[k] > 0:
            even[k] = low[k] / width[k]
    use = np.empty((K, N), np.bool_)
    for k in range(K):
        for i in range(N):
            ok[k, i] = ok[k, i] and keep[k, i]
            use[k, i] = clean[k, i] and planes[k]
    reach = (aw0 * width + aw1) if area else width / 1.6
    shared = np.zeros((K, 2, 2))
    _shared_covs(xy, cen, use, ok, local_in, local_out, v_in, v_out, reach, pen, shared)
    P, Wc, cnt = np.empty((K, N, 2)), np.empty((K, N)), np.empty(K, np.int64)
    _compact(cen, u, e, W, ok, P, Wc, cnt)  # valid points first, in ray order
    mask = np.empty((K, N), np.bool_)
    for k in range(K):
        for i in range(N):
            mask[k, i] = i < cnt[k]
    return P, mask, n_use, Wc, width, shared, reached, even


@compiled
def _shared_covs(xy, cen, use, ok, lin, lout, fin, fout, reach, pen, out):  # pragma: no cover - compiled
    """The covariance of ``g`` in the edges' shared shift g . (x - c), px, per ring (the plateau
    planes' gradient errors move every edge of the ring together, each by the level error
    over the contrast times the edge locator's ``reach``): the plane fit's covariance V = A^-1 X^T X A^-1
    (A = X^T X + the ridge on the gradient), its residual variance s2 and the contrast
    (the median level difference of its rays in the image), ``out[k]`` = s2 (reach / contrast)^2
    V's gradient block; left zero where fewer than 6 clean rays or no contrast."""
    K, N = use.shape
    buf = np.empty(N)
    for k in range(K):
        XtX = np.zeros((3, 3))
        m, ss, nb = 0, 0.0, 0
        for i in range(N):
            if ok[k, i]:
                buf[nb] = abs(fin[k, i] - fout[k, i])
                nb += 1
            if not use[k, i]:
                continue
            m += 1
            x = (1.0, xy[k, i, 0] - cen[k, 0], xy[k, i, 1] - cen[k, 1])
            for p in range(3):
                for q in range(3):
                    XtX[p, q] += x[p] * x[q]
            ss += (lin[k, i] - fin[k, i]) ** 2 + (lout[k, i] - fout[k, i]) ** 2
        if m < 6 or nb == 0:
            continue
        contrast = _median(buf, nb)
        if not contrast > 0:
            continue
        A = XtX.copy()
        A[1, 1] += m * pen[k]
        A[2, 2] += m * pen[k]
        Ai = np.linalg.inv(A)
        V = Ai @ XtX @ Ai
        s2 = ss / max(m - 3, 1)
        f = s2 * (reach[k] / contrast) ** 2
        for p in range(2):
            for q in range(2):
                out[k, p, q] = f * V[p + 1, q + 1]


def _per_ellipse(half, K: int) -> np.ndarray:
    """(K,) float64 half-windows from one for all or one per ellipse (a writable copy: the
    kernels are compiled for writable arrays)."""
    return np.array(np.broadcast_to(np.asarray(half, np.float64), (K,)))


def plate_lines(corners: np.ndarray) -> np.ndarray:
    """The four lines (4, 3) of a convex quadrilateral's sides, ``corners`` (4, 2) in order:
    (a, b, c) with a x + b y + c the signed distance from the side, positive inside."""
    P = np.asarray(corners, np.float64).reshape(4, 2)
    mid = P.mean(0)
    out = np.empty((4, 3))
    for j in range(4):
        d = P[(j + 1) % 4] - P[j]
        nrm = np.array([-d[1], d[0]]) / max(np.hypot(d[0], d[1]), 1e-12)
        if nrm @ (mid - P[j]) < 0:
            nrm = -nrm
        out[j] = nrm[0], nrm[1], -nrm @ P[j]
    return out


# --- ellipse fits ---------------------------------------------------------------------------------


def fit_ellipses(P: np.ndarray, mask: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Direct least-squares ellipse fits (Fitzgibbon; Halir-Flusser's stable form), batched.

    Args:
        P: (K, N, 2) points; mask (K, N) which count (at least 6 per fit).
        weights: optional (K, N) non-negative weights of the points' algebraic residuals.
    Returns:
        (centres (K, 2), Q (K, 2, 2), valid (K,)) with (x - c)^T Q (x - c) = 1 where valid.
    """
    K, N = mask.shape
    m, s, mu = np.empty((K, 2)), np.empty(K), np.empty((K, len(_MOMENTS)))
    w = np.ones((K, N)) if weights is None else np.ascontiguousarray(weights, np.float64)
    mask = np.ascontiguousarray(mask)
    _scatter(np.ascontiguousarray(P, np.float64), w, mask, m, s, mu)
    valid = (mask.sum(1) >= 6) & (s > 0)
    M, T = np.empty((K, 3, 3)), np.empty((K, 3, 3))
    _reduced_scatter(mu, _S1, _S2, _S3, valid, M, T)
    # The 3 x 3 eigenproblems compiled, where their eigenvalues are real; numpy takes the
    # rest (a fit that is no ellipse), whose eigenvectors' real parts it returns.
    V, rest = np.zeros((K, 3, 3)), np.zeros(K, bool)
    _eigvecs_rows(M, valid, V, rest)
    for k in np.nonzero(rest)[0]:
        try:
            V[k] = np.real(np.linalg.eig(M[k])[1])
        except np.linalg.LinAlgError:
            valid[k] = False
    cen, Q = np.empty((K, 2)), np.empty((K, 2, 2))
    _ellipse_from_conic(V, T, m, s, valid, cen, Q)
    return cen, Q, valid


@compiled
def _eigvecs_rows(M, valid, V, rest):  # pragma: no cover - compiled
    """V[k] <- the eigenvectors of M[k] for each valid k whose eigenvalues are real
    (:func:`_real_eigvecs`); rest[k] set where they are not (V[k] untouched)."""
    for k in range(M.shape[0]):
        if valid[k] and not _real_eigvecs(M[k], V[k]):
            rest[k] = True


@compiled
def _lu_solve_det(A, B):  # pragma: no cover - compiled
    """(X with A X = B, det A, whether A is regular) for a small square A by Gaussian
    elimination with partial pivoting, as LAPACK's gesv and numpy's det; an exactly zero
    pivot makes A singular (det 0, X unfinished)."""
    n = A.shape[0]
    A, X = A.copy(), B.copy()
    det = 1.0
    for j in range(n):
        p = j
        for i in range(j + 1, n):
            if abs(A[i, j]) > abs(A[p, j]):
                p = i
        if A[p, j] == 0.0:
            return X, 0.0, False
        if p != j:
            det = -det
            for c in range(n):
                A[j, c], A[p, c] = A[p, c], A[j, c]
            for c in range(X.shape[1]):
                X[j, c], X[p, c] = X[p, c], X[j, c]
        det *= A[j, j]
        for i in range(j + 1, n):
            f = A[i, j] / A[j, j]
            for c in range(j, n):
                A[i, c] -= f * A[j, c]
            for c in range(X.shape[1]):
                X[i, c] -= f * X[j, c]
    for j in range(n - 1, -1, -1):
        for c in range(X.shape[1]):
            acc = X[j, c]
            for i in range(j + 1, n):
                acc -= A[j, i] * X[i, c]
            X[j, c] = acc / A[j, j]
    return X, det, True


@compiled
def _lu_solve(A, B):  # pragma: no cover - compiled
    """X with A X = B for a small square A (:func:`_lu_solve_det`) and whether A was
    regular (an exactly zero pivot: not)."""
    X, _, regular = _lu_solve_det(A, B)
    return X, regular


@compiled
def _reduced_scatter(mu, S1i, S2i, S3i, valid, M, T):  # pragma: no cover - compiled
    """Per fit k, from the moments mu[k]: T[k] = -S3^-1 S2^T and the reduced scatter
    matrix M[k] = C1^-1 (S1 + S2 T) (Halir-Flusser) whose eigenvector is the conic's
    quadratic part; valid[k] is cleared where S3 is singular (M[k] then the identity)."""
    S1, S2, S3 = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    for k in range(mu.shape[0]):
        M[k] = 0.0
        T[k] = 0.0
        for a in range(3):
            M[k, a, a] = 1.0
        if not valid[k]:
            continue
        for a in range(3):
            for b in range(3):
                S1[a, b], S2[a, b], S3[a, b] = mu[k, S1i[a, b]], mu[k, S2i[a, b]], mu[k, S3i[a, b]]
        Tk, ok = _lu_solve(S3, -S2.T.copy())
        if not ok:
            valid[k] = False
            continue
        T[k] = Tk
        R = S1 + S2 @ Tk
        for b in range(3):
            M[k, 0, b], M[k, 1, b], M[k, 2, b] = R[2, b] / 2, -R[1, b], R[0, b] / 2


@compiled
def _ellipse_from_conic(V, T, m, s, valid, cen, Q):  # pragma: no cover - compiled
    """Per fit k: the eigenvector of V[k] that is an ellipse (4 a c - b^2 > 0, the first
    such) completed by T[k] to the conic, its centre and form Q (x - c)^T Q (x - c) = 1,
    mapped back from the points' normalisation (m[k], s[k]); valid[k] cleared where none
    is an ellipse or the conic is degenerate (cen, Q then 0 and the identity)."""
    for k in range(V.shape[0]):
        cen[k] = 0.0
        Q[k, 0, 0], Q[k, 0, 1], Q[k, 1, 0], Q[k, 1, 1] = 1.0, 0.0, 0.0, 1.0
        if not valid[k]:
            continue
        j = -1
        for e in range(3):
            if 4 * V[k, 0, e] * V[k, 2, e] - V[k, 1, e] ** 2 > 0:
                j = e
                break
        if j < 0:
            valid[k] = False
            continue
        A, B, C = V[k, 0, j], V[k, 1, j], V[k, 2, j]
        D = T[k, 0, 0] * A + T[k, 0, 1] * B + T[k, 0, 2] * C
        E = T[k, 1, 0] * A + T[k, 1, 1] * B + T[k, 1, 2] * C
        F = T[k, 2, 0] * A + T[k, 2, 1] * B + T[k, 2, 2] * C
        A2 = np.array([[A, B / 2], [B / 2, C]])
        b2 = np.array([[-D / 2], [-E / 2]])
        uc, ok = _lu_solve(A2, b2)
        if not ok:
            valid[k] = False
            continue
        fc = F + (D / 2) * uc[0, 0] + (E / 2) * uc[1, 0]
        if fc == 0:
            valid[k] = False
            continue
        q00, q01, q11 = A / -fc, (B / 2) / -fc, C / -fc
        if not (np.isfinite(q00) and np.isfinite(q01) and np.isfinite(q11)) or not (q00 > 0 and q00 * q11 - q01 * q01 > 0):
            valid[k] = False
            continue
        sk = s[k]
        cen[k, 0], cen[k, 1] = m[k, 0] + sk * uc[0, 0], m[k, 1] + sk * uc[1, 0]
        s2 = sk * sk
        Q[k, 0, 0], Q[k, 0, 1], Q[k, 1, 0], Q[k, 1, 1] = q00 / s2, q01 / s2, q01 / s2, q11 / s2


_SUBSETS: dict = {}  # (n, count) → the fixed random 5-point subsets of n points


def _subsets(n: int, count: int) -> np.ndarray:
    """(count, 5) random 5-point subsets of ``n`` points from a fixed seed, drawn once per
    (n, count): the same subsets every call, without drawing them again."""
    key = (n, count)
    if key not in _SUBSETS:
        rng = np.random.default_rng(0)
        _SUBSETS[key] = np.stack([rng.choice(n, 5, replace=False) for _ in range(count)])
        _SUBSETS[key].flags.writeable = False
    return _SUBSETS[key]


def _radial_offsets(P: np.ndarray, cen: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point, its angle on the ellipse (cen, Q) seen as a unit circle, and its radial
    offset from the ellipse, px (K, N each)."""
    K, N = P.shape[:2]
    t, off = np.empty((K, N)), np.empty((K, N))
    _offsets(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(cen, np.float64), _spd2(Q, 0.5)[0], t, off)
    return t, off


@compiled
def _offsets(P, cen, R, t, off):  # pragma: no cover - compiled
    """:func:`_radial_offsets` with R = Q^(1/2), the map to the unit-circle frame."""
    K, N, _ = P.shape
    for k in range(K):
        for i in range(N):
            dx, dy = P[k, i, 0] - cen[k, 0], P[k, i, 1] - cen[k, 1]
            qx, qy = R[k, 0, 0] * dx + R[k, 0, 1] * dy, R[k, 1, 0] * dx + R[k, 1, 1] * dy
            lam = np.hypot(qx, qy)
            t[k, i] = np.arctan2(qy, qx)
            off[k, i] = (lam - 1.0) * np.hypot(dx, dy) / max(lam, 1e-9)


@compiled
def _reject(res, kl, mask, k_sigma, min_px, new, same):  # pragma: no cover - compiled
    """Per row, the points of ``mask`` within max(k_sigma robust sigmas, min_px) of the
    curve (radial residuals ``res``; the sigma from the median absolute deviation over
    the current points ``kl``) into ``new``; ``same[k]``: whether that changed nothing."""
    K, N = res.shape
    med, sig = np.empty(K), np.empty(K)
    dev = np.empty((K, N))
    _row_stats(res, kl, -1.0, 0.0, med)
    for k in range(K):
        for i in range(N):
            dev[k, i] = abs(res[k, i] - med[k])
    _row_stats(dev, kl, -1.0, 0.0, sig)
    for k in range(K):
        lim = max(k_sigma * (1.4826 * sig[k]), min_px)
        same[k] = True
        for i in range(N):
            new[k, i] = mask[k, i] and abs(res[k, i]) <= lim
            same[k] = same[k] and new[k, i] == kl[k, i]


@compiled
def _harmonics(t, X):  # pragma: no cover - compiled
    """X[k, :, i] = (1, cos t, sin t, cos 2t, sin 2t) of t[k, i]: the linearised model's terms."""
    K, N = t.shape
    for k in range(K):
        for i in range(N):
            a = t[k, i]
            X[k, 0, i] = 1.0
            X[k, 1, i] = np.cos(a)
            X[k, 2, i] = np.sin(a)
            X[k, 3, i] = np.cos(2 * a)
            X[k, 4, i] = np.sin(2 * a)


def lmeds_inliers(P: np.ndarray, mask: np.ndarray, cen: np.ndarray, Q: np.ndarray, c: dict, n_subsets: int = 40) -> np.ndarray:
    """Inliers (K, N) of edge points by least-median-of-squares on a linearised ellipse model.

    Near the current ellipse (cen, Q), a slightly different ellipse moves the edge along
    each ray by ``a0 + a1 cos t + b1 sin t + a2 cos 2t + b2 sin 2t`` (size, centre, shape).
    Fitting this 5-parameter model to the radial offsets on random 5-point subsets and
    keeping the one with the smallest median residual tolerates a contiguous spoilt sector
    (an occluder across the edge) that a least-squares fit would bend toward and so hide.
    The subsets come from a fixed seed: the result is deterministic. ``P``'s valid points
    come first in each row (as :func:`edge_points` returns them).
    """
    t, off = _radial_offsets(P, cen, Q)
    X = np.empty((len(t), 5, t.shape[1]))
    _harmonics(t, X)
    cnt = mask.sum(1)
    idx = np.stack([_subsets(int(n), n_subsets) for n in cnt])  # (K, S, 5)
    keep = np.empty(mask.shape, bool)
    _lmeds(X, np.ascontiguousarray(off), np.ascontiguousarray(mask), cnt, idx, float(c["outlier_min_px"]), keep)
    return keep


def fit_robust(
    P: np.ndarray,
    mask: np.ndarray,
    c: dict,
    frame: tuple | None = None,
    weights: np.ndarray | None = None,
    screen: np.ndarray | None = None,
):
    """Ellipse fits with iterative rejection of points far from the fitted curve (after a
    least-median-of-squares screen around ``frame`` = (cen (K, 2), Q (K, 2, 2)) for fits of
    at least 12 points, of the ellipses ``screen`` (K,) only where given); ``weights``
    (K, N) weigh the points in the fit. ``P``'s valid points come first in each row (as
    :func:`edge_points` returns them).

    Returns (centres (K, 2), Q (K, 2, 2), fitted (K,), keep (K, N)).

    Each ring in one compiled pass (:func:`_robust_rows`); a ring whose reduced scatter
    matrix has complex eigenvalues (numba's eig refuses those) is fitted by the same steps
    in numpy (:func:`_fit_robust_numpy`), whose batched eig returns them and whose fit
    takes their eigenvectors' real parts.
    """
    K, N = mask.shape
    P = np.ascontiguousarray(P, np.float64)
    mask = np.ascontiguousarray(mask, bool)
    W = np.ones((K, N)) if weights is None else np.ascontiguousarray(weights, np.float64)
    cnt = mask.sum(1)
    screen = np.zeros(K, bool) if frame is None else (cnt >= 12) & (True if screen is None else np.asarray(screen, bool))
    n_sub = 40
    idx = np.zeros((K, n_sub, 5), np.int64)
    for k in np.nonzero(screen)[0]:
        idx[k] = _subsets(int(cnt[k]), n_sub)
    fcen = np.zeros((K, 2)) if frame is None else np.ascontiguousarray(frame[0], np.float64)
    fR = np.tile(np.eye(2), (K, 1, 1)) if frame is None else _spd2(frame[1], 0.5)[0]
    cen, Q, fitted, keep, fallback = np.empty((K, 2)), np.empty((K, 2, 2)), np.empty(K, bool), np.empty((K, N), bool), np.empty(K, bool)
    _robust_rows(
        P, mask, W, screen, fcen, fR, idx, float(c["outlier_k"]), float(c["outlier_min_px"]), _S1, _S2, _S3, cen, Q, fitted, keep, fallback
    )
    if fallback.any():
        f = np.nonzero(fallback)[0]
        sub = None if frame is None else (frame[0][f], frame[1][f])
        cen[f], Q[f], fitted[f], keep[f] = _fit_robust_numpy(P[f], mask[f], c, sub, W[f])
    return cen, Q, fitted, keep


@compiled
def _real_eigvecs(M, V):  # pragma: no cover - compiled
    """V <- the eigenvectors (columns) of the real square matrix M; False, V untouched,
    when an eigenvalue is complex or the eigenproblem fails. Typed the same whatever eig
    returns: numba's eig raises on complex eigenvalues of a real matrix under numpy < 2.5
    and returns complex arrays for every real matrix under numpy >= 2.5 (as numpy does);
    np.imag / np.real take either."""
    try:
        w, Vk = np.linalg.eig(M)
    except Exception:
        return False
    wi = np.imag(w)
    for i in range(wi.shape[0]):
        if wi[i] != 0.0:
            return False
    V[:, :] = np.real(Vk)
    return True


@compiled
def _robust_rows(
    P, mask, W, screen, fcen, fR, idx, k_sigma, min_px, S1i, S2i, S3i, cen, Q, fitted, keep, fallback
):  # pragma: no cover - compiled
    """:func:`fit_robust` ring by ring: the least-median screen where ``screen[k]`` (radial
    offsets from the frame ellipse fcen[k], fR[k] = Q^(1/2)), then up to three weighted
    direct fits, each followed by the outlier rejection, stopping when the points kept do
    not change. ``fallback[k]``: the eigenproblem was refused (complex eigenvalues)."""
    K, N, _ = P.shape
    t, off, X = np.empty((1, N)), np.empty((1, N)), np.empty((1, 5, N))
    m, s, mu = np.empty((1, 2)), np.empty(1), np.empty((1, 15))
    M, T, V = np.empty((1, 3, 3)), np.empty((1, 3, 3)), np.empty((1, 3, 3))
    valid = np.empty(1, np.bool_)
    ci, Qi, R, eig = np.empty((1, 2)), np.empty((1, 2, 2)), np.empty((1, 2, 2)), np.empty((1, 2))
    new, same, cnt = np.empty((1, N), np.bool_), np.empty(1, np.bool_), np.empty(1, np.int64)
    for k in range(K):
        fallback[k] = False
        fitted[k] = False
        cen[k] = 0.0
        Q[k, 0, 0], Q[k, 0, 1], Q[k, 1, 0], Q[k, 1, 1] = 1.0, 0.0, 0.0, 1.0
        for i in range(N):
            keep[k, i] = mask[k, i]
        if screen[k]:
            n = 0
            for i in range(N):
                n += mask[k, i]
            cnt[0] = n
            _offsets(P[k : k + 1], fcen[k : k + 1], fR[k : k + 1], t, off)
            _harmonics(t, X)
            _lmeds(X, off, mask[k : k + 1], cnt, idx[k : k + 1], min_px, keep[k : k + 1])
        for _ in range(3):
            n = 0
            for i in range(N):
                n += keep[k, i]
            if n < 6:
                fitted[k] = False
                break
            _scatter(P[k : k + 1], W[k : k + 1], keep[k : k + 1], m, s, mu)
            valid[0] = s[0] > 0
            _reduced_scatter(mu, S1i, S2i, S3i, valid, M, T)
            if not _real_eigvecs(M[0], V[0]):  # complex eigenvalues: numpy's path takes their real parts
                fallback[k] = True
                break
            _ellipse_from_conic(V, T, m, s, valid, ci, Qi)
            fitted[k] = valid[0]
            if not valid[0]:
                break
            cen[k], Q[k] = ci[0], Qi[0]
            _spd2_rows(Qi, False, R, eig)
            _offsets(P[k : k + 1], ci, R, t, off)  # off: the radial residuals, px
            _reject(off, keep[k : k + 1], mask[k : k + 1], k_sigma, min_px, new, same)
            for i in range(N):
                keep[k, i] = new[0, i]
            if same[0]:
                break


def _fit_robust_numpy(P: np.ndarray, mask: np.ndarray, c: dict, frame: tuple | None = None, weights: np.ndarray | None = None):
    """:func:`fit_robust` in numpy, batched (the fallback for rings numba's eig refuses)."""
    K = len(mask)
    keep = mask.copy()
    if frame is not None:
        big = mask.sum(1) >= 12
        if big.any():
            keep[big] = lmeds_inliers(P[big], mask[big], frame[0][big], frame[1][big], c)
    cen, Q = np.zeros((K, 2)), np.tile(np.eye(2), (K, 1, 1))
    fitted = np.zeros(K, bool)
    live = np.ones(K, bool)
    for _ in range(3):
        few = live & (keep.sum(1) < 6)
        fitted[few] = False
        live &= ~few
        if not live.any():
            break
        ci, Qi, ok = fit_ellipses(P[live], keep[live], None if weights is None else weights[live])
        li = np.nonzero(live)[0]
        fitted[li] = ok
        live[li[~ok]] = False
        li, ci, Qi = li[ok], ci[ok], Qi[ok]
        cen[li], Q[li] = ci, Qi
        _, res = _radial_offsets(P[li], ci, Qi)  # radial residual, px
        new, same = np.empty(res.shape, bool), np.empty(len(li), bool)
        _reject(res, keep[li], mask[li], float(c["outlier_k"]), float(c["outlier_min_px"]), new, same)
        keep[li] = new
        live[li[same]] = False
    return cen, Q, fitted, keep


def _semi_axes(Q: np.ndarray) -> np.ndarray:
    return np.sqrt(1 / _spd2(Q, 0.5)[1])


def _spd2(Q: np.ndarray, power: float) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric positive definite 2 x 2 matrices Q (K, 2, 2): Q^power (power 0.5 or
    -0.5) and the eigenvalues, ascending (K, 2), in closed form."""
    Q = np.ascontiguousarray(Q, np.float64).reshape(-1, 2, 2)
    out, eig = np.empty(Q.shape), np.empty((len(Q), 2))
    _spd2_rows(Q, power < 0, out, eig)
    return out, eig


@compiled
def _spd2_rows(Q, inverse, out, eig):  # pragma: no cover - compiled
    """:func:`_spd2` per row: sqrt(Q) = (Q + sqrt(det Q) I) / sqrt(tr Q + 2 sqrt(det Q)),
    inverted for the power -0.5; the smaller eigenvalue as det / the larger (no
    cancellation)."""
    for k in range(Q.shape[0]):
        a, b, c = Q[k, 0, 0], 0.5 * (Q[k, 0, 1] + Q[k, 1, 0]), Q[k, 1, 1]
        det = a * c - b * b
        hi = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
        eig[k, 0], eig[k, 1] = det / hi, hi
        s = np.sqrt(det)
        t = np.sqrt(a + c + 2 * s)
        r00, r01, r11 = (a + s) / t, b / t, (c + s) / t
        if inverse:  # the inverse of a 2 x 2 matrix whose determinant is sqrt(det Q)
            r00, r01, r11 = r11 / s, -r01 / s, r00 / s
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 0], out[k, 1, 1] = r00, r01, r01, r11


def _fit_passes(
    grays: list,
    view: np.ndarray,
    cen: np.ndarray,
    Q: np.ndarray,
    half: np.ndarray,
    dark_inside: bool,
    c: dict,
    floor: np.ndarray,
    others: list,
    plates: list | None = None,
) -> tuple:
    """The passes of edge sampling and robust fit of :func:`refine_edges`, each on the
    ellipses still moving; cen (K, 2) and Q (K, 2, 2) are updated in place. Returns (per
    ellipse (edge points (M, 2), weights (M,)) of its last fit or None, edge widths (K,),
    the covariances of the edges' shared shift (K, 2, 2), whether the plate's edge reached
    the last fit's rays (K,), the widths' evenness (K,): :func:`edge_points`)."""
    K = len(cen)
    active = np.ones(K, bool)
    last_fit: list = [None] * K  # per ellipse (its points, weights, which it kept) of its last fit
    width, even = np.zeros(K), np.ones(K)
    reached = np.zeros(K, bool)
    shared = np.zeros((K, 2, 2))
    last = np.full(K, np.inf)  # each ellipse's move in the pass before (inf: no fit taken yet)
    # The least-median screen is for a spoilt sector (an occluder): after a pass whose fit
    # rejected (almost) no point (conf["rescreen_frac"]), the next pass's rays see the same
    # clean edge.
    # A seed known to be close (a tracker's prediction, refine_first_tol > 0) rarely meets
    # one: its first fit goes without the screen, and only where that fit rejected points
    # (a sector spoilt) does a screened pass follow.
    close = c["refine_first_tol"] > 0 and not c["close_seed_screen"]
    screen = np.full(K, not close)
    tol = c["refine_tol"]
    sparse = c["first_pass_spacing"] if not c["refine_first_tol"] else 0.0
    # Rings the blurred-ring fit refits stop early: there each pass at best halves the
    # error, and the model fit starts from wherever they leave the ellipse. Edges wider than
    # c["wide_edge_width"] of the minor semi-axis stop after c["wide_edge_passes"] full
    # passes; motion blur's (c["motion_edges"]: (passes, widths' evenness at most, long
    # blur's px and fraction of the minor semi-axis)), wide or long and uneven around the
    # ring, after its fewer passes: the model is motion blur's, and its fit there settles
    # where it would from a closer start, while on evenly wide edges (defocus) it misfits,
    # and a closer start matters. With motion_edges' last entry, the coarse pass's fit of
    # such edges is kept as their first pass (other wide edges discard it: the full passes
    # start from the seed).
    wide_passes, wide_width = c.get("wide_edge_passes", 0), c.get("wide_edge_width", np.inf)
    motion_passes, motion_even, long_px, long_width, motion_coarse = c.get("motion_edges", (0, 0.0, np.inf, np.inf, False))
    limits = (  # _take_fits' settings, typed alike in every call (one compiled version)
        float(c["first_pass_max_width"]), float(c["rescreen_frac"]), float(c["refine_first_tol"]), float(tol),
        bool(c["refine_predict"]), int(wide_passes), float(wide_width), int(motion_passes), float(motion_even), float(long_px),
        float(long_width), bool(motion_coarse),
    )  # fmt: skip
    passes = np.zeros(K, np.intp)
    for it in range(max(1, c["refine_iters"]) + (sparse > 0)):  # a coarse pass does not count
        a = np.nonzero(active)[0]
        if not len(a):
            break
        coarse = it == 0 and sparse > 0  # an ellipse the coarse pass fails gets a full one
        cp = {**c, "edge_spacing": sparse} if coarse else c
        P, M, n_use, W, wd, sh, cr, ev = edge_points(
            grays,
            view[a],
            cen[a],
            Q[a],
            half[a],
            dark_inside,
            cp,
            floor[a],
            [others[k] for k in a],
            None if plates is None else [plates[k] for k in a],
        )
        need = np.maximum(6, c["min_valid_frac"] * n_use)
        go = M.sum(1) >= need
        if not coarse:
            active[a[~go]] = False
        if not go.any():
            if coarse:
                continue
            break
        g = a[go]
        Pg, Wg, Mg = P[go], W[go], M[go]
        cf, Qf, fitted, keep = fit_robust(Pg, Mg, c, (cen[g], Q[g]), Wg, screen[g])
        took = np.empty(len(g), bool)
        _take_fits(
            g, cf, Qf, fitted, keep, Mg, need[go], wd[go], ev[go], cr[go], sh[go], coarse, *limits, cen, Q, active, screen, width,
            even, reached, shared, last, passes, took,
        )  # fmt: skip
        for i in np.nonzero(took)[0]:
            last_fit[g[i]] = (Pg[i], Wg[i], keep[i])
    found = [None if f is None else (f[0][f[2]], f[1][f[2]]) for f in last_fit]
    return found, width, shared, reached, even


@compiled
def _take_fits(
    g, cf, Qf, fitted, keep, M, need, wd, ev, cr, sh, coarse, first_max, rescreen, first_tol, tol, predict, wide_passes,
    wide_width, motion_passes, motion_even, long_px, long_width, motion_coarse, cen, Q, active, screen, width, even,
    reached, shared, last, passes, took,
):  # pragma: no cover - compiled  # fmt: skip
    """:func:`_fit_passes`' step after a pass's fits (ellipses g, fitted cf, Qf, the points
    each kept): which fits the ellipses take (``took``; enough points kept; in the coarse
    pass, only where the edges are narrow, or motion blur's with ``motion_coarse``), each
    one's state updated in place (ellipse, edge widths, shared shift, the least-median
    screen of its next pass, its move) and whether it stops: it moved less than ``tol``
    (after its first fit: ``first_tol``, screened), or its next move, extrapolated
    (``predict``), is under ``tol``; or its wide or motion-blurred edges have had their
    passes. A failed fit stops an ellipse, except in the coarse pass."""
    G = len(g)
    Qs = np.empty((G, 2, 2))
    nk, nm = np.zeros(G, np.int64), np.zeros(G, np.int64)  # points kept, points
    for i in range(G):
        for j in range(keep.shape[1]):
            nk[i] += keep[i, j]
            nm[i] += M[i, j]
        took[i] = fitted[i] and nk[i] >= need[i]
        Qs[i] = Qf[i] if took[i] else Q[g[i]]
    root, eig, root0, eig0 = np.empty((G, 2, 2)), np.empty((G, 2)), np.empty((G, 2, 2)), np.empty((G, 2))
    _spd2_rows(Qs, False, root, eig)
    _spd2_rows(np.ascontiguousarray(Q[g]), False, root0, eig0)
    for i in range(G):
        k = g[i]
        a0, a1 = np.sqrt(1 / eig[i, 0]), np.sqrt(1 / eig[i, 1])
        b0, b1 = np.sqrt(1 / eig0[i, 0]), np.sqrt(1 / eig0[i, 1])
        minor = min(a0, a1)
        wide = wd[i] > wide_width * minor
        motion = ev[i] <= motion_even and (wide or (wd[i] >= long_px and wd[i] >= long_width * minor))
        if coarse:  # wide (blurred) edges need every ray, but for motion blur's the model fit follows
            took[i] = took[i] and (wd[i] < first_max * min(b0, b1) or (motion_coarse and motion))
        elif not took[i]:
            active[k] = False
        if not took[i]:
            continue
        screened = screen[k]
        screen[k] = nm[i] - nk[i] > rescreen * nm[i]
        dx, dy = cf[i, 0] - cen[k, 0], cf[i, 1] - cen[k, 1]
        move = np.sqrt(dx * dx + dy * dy) + max(abs(a0 - b0), abs(a1 - b1))  # the curve's largest displacement
        cen[k], Q[k] = cf[i], Qf[i]
        width[k], even[k], reached[k], shared[k] = wd[i], ev[i], cr[i], sh[i]
        if np.isinf(last[k]):  # the first fit this ellipse took
            done = move < first_tol and (screened or not screen[k])
        else:
            done = move < tol or (predict and move < 10 * tol and move**2 < tol * last[k])
        last[k] = move
        passes[k] += 1
        if done or (wide_passes > 0 and passes[k] >= wide_passes and wide) or (motion_passes > 0 and passes[k] >= motion_passes and motion):
            active[k] = False


def center_covariances(fits: list) -> np.ndarray:
    """(K, 2, 2) covariances of ellipse centres from their fits' residuals: ``fits`` per
    ellipse (edge points (M, 2), weights (M,), centre (2,), Q (2, 2), optionally the
    covariance (2, 2) of a shift g . (x - c) that all its edges share, :func:`_shared_covs`)
    of a weighted least-squares fit of (x - c)^T Q (x - c) = 1. Each point's geometric distance from
    the ellipse is linearised in the five parameters (c, Q); the covariance is the sandwich
    H^-1 B H^-1 (H = J^T W J, B from the weighted residuals: the weights are relative, the
    residuals set the scale, so that the image's noise and the edges' quality at this ring
    show), and its centre block is returned (NaN where fewer than 8 points).

    Neighbouring rays sample overlapping pixels (and share the optics' blur and any misfit
    of the ellipse's shape): their errors are correlated, and the points carry less
    information than their number says. The residuals' own lag-1 correlation rho along the
    ring gives the variance inflation (1 + rho) / (1 - rho) of a first-order sequence. The
    shared shift is carried through the fit on top."""
    K = len(fits)
    out = np.full((K, 2, 2), np.nan)
    if not K:
        return out
    M = max(len(f[0]) for f in fits)
    d, w, S = np.zeros((K, M, 2)), np.zeros((K, M)), np.zeros((K, 2, 2))
    Q = np.stack([np.asarray(f[3], np.float64) for f in fits])
    for k, f in enumerate(fits):
        d[k, : len(f[0])] = np.asarray(f[0], np.float64) - np.asarray(f[2], np.float64)
        w[k, : len(f[0])] = f[1]
        if len(f) > 4:
            S[k] = f[4]
    _center_covs(d, w, Q, S, out)
    return out


@compiled
def _center_covs(d, w, Q, S, out):  # pragma: no cover - compiled
    """:func:`center_covariances`' kernel: ``out[k]`` for ellipse k (left NaN where its fit
    is not determined)."""
    K, M = w.shape
    J = np.empty((M, 5))
    for k in range(K):
        H, B, Jd = np.zeros((5, 5)), np.zeros((5, 5)), np.zeros((5, 2))
        n = 0
        ss, lag, prev = 0.0, 0.0, 0.0
        for m in range(M):
            wm = w[k, m]
            dx, dy = d[k, m, 0], d[k, m, 1]
            gx = Q[k, 0, 0] * dx + Q[k, 0, 1] * dy  # Q (x - c): half the gradient of lambda^2
            gy = Q[k, 1, 0] * dx + Q[k, 1, 1] * dy
            lam = np.sqrt(max(dx * gx + dy * gy, 1e-12))
            px = lam / max(np.sqrt(gx * gx + gy * gy), 1e-12)  # px per unit of lambda, along the normal
            r = (lam - 1.0) * px  # geometric distance from the ellipse, px
            f = px / lam
            J[m, 0], J[m, 1], J[m, 2], J[m, 3], J[m, 4] = -gx * f, -gy * f, 0.5 * dx * dx * f, dx * dy * f, 0.5 * dy * dy * f
            rw = np.sqrt(wm) * r
            if m > 0:
                lag += rw * prev
            prev = rw
            ss += rw * rw
            if wm > 0:
                n += 1
            b = (wm * r) ** 2
            for i in range(5):
                Jd[i, 0] += J[m, i] * wm * dx
                Jd[i, 1] += J[m, i] * wm * dy
                for j in range(i, 5):
                    H[i, j] += J[m, i] * wm * J[m, j]
                    B[i, j] += J[m, i] * b * J[m, j]
        for i in range(5):
            for j in range(i):
                H[i, j], B[i, j] = H[j, i], B[j, i]
        if n < 8 or abs(np.linalg.det(H)) <= 1e-300:
            continue
        rho = min(max(lag / max(ss, 1e-300), 0.0), 0.9)
        Hi = np.linalg.inv(H)
        C = Hi @ B @ Hi * (n / max(n - 5, 1) * (1 + rho) / (1 - rho))
        G = (Hi @ Jd)[:2]  # the shared shift g . (x - c) of every edge, carried through the fit
        out[k] = C[:2, :2] + G @ S[k] @ G.T


def _ideal_fits(found: list, use: list, view: np.ndarray, cameras: list) -> dict:
    """Ellipses k -> (centre, Q, points (M, 2)) in ideal (undistorted) px, fitted to the edge
    points ``found[k]`` = (points (M, 2), weights (M,)) of the ellipses ``use`` once undistorted
    by ``cameras[view[k]]`` (one undistortion per view); the fits that fail are left out."""
    pts: dict = {}
    for g in sorted({view[k] for k in use}):  # one undistortion per view
        mine = [k for k in use if view[k] == g]
        flat = cameras[g].undistort_points(np.concatenate([found[k][0] for k in mine]))
        cuts = np.cumsum([len(found[k][0]) for k in mine])[:-1]
        pts.update(zip(mine, np.split(flat, cuts)))
    pts = [pts[k] for k in use]
    N = max(len(p) for p in pts)
    Pp, Mp, Wp = np.zeros((len(use), N, 2)), np.zeros((len(use), N), bool), np.zeros((len(use), N))
    for i, (k, p) in enumerate(zip(use, pts)):
        Pp[i, : len(p)], Mp[i, : len(p)], Wp[i, : len(p)] = p, True, found[k][1]
    ci, Qi, ok = fit_ellipses(Pp, Mp, Wp)
    return {k: (ci[i], Qi[i], pts[i]) for i, k in enumerate(use) if ok[i]}


def refine_edges(
    grays: list,
    view: np.ndarray,
    cen: np.ndarray,
    Q: np.ndarray,
    half,
    dark_inside: bool,
    c: dict,
    floor: np.ndarray,
    others: list,
    cameras: list | None = None,
    plates: list | None = None,
) -> list:
    """Iterated edge sampling + robust fit of K ellipses (see :func:`edge_points` for the
    arguments: ``half`` one for all or (K,); ``cameras[view[k]]`` undistorts ellipse k's points, or None;
    ``plates`` per ellipse its plate's sides or None).

    Iterates each ellipse until it moves less than c["refine_tol"] px (at least two passes,
    unless the first moved it less than c["refine_first_tol"]): under heavy blur the plateau
    levels are only reached near the true edge, so each pass halves the error at best.

    Returns per ellipse ((centre, Q) in image px, (centre, Q) in ideal px or None, edge
    width px, the centre's covariance (2, 2) in the px of the fit the centre comes from:
    ideal where there is one, :func:`center_covariances`, whether the plate's blurred edge
    reached its rays, the 25th percentile of its edges' widths over their 75th:
    :func:`edge_points`) or None when too few edge points are found.
    """
    K = len(cen)
    cen, Q = np.array(cen, np.float64).reshape(K, 2), np.array(Q, np.float64).reshape(K, 2, 2)
    found, width, shared, reached, even = _fit_passes(grays, view, cen, Q, _per_ellipse(half, K), dark_inside, c, floor, others, plates)
    out: list = [None] * K
    ks = [k for k in range(K) if found[k] is not None]
    ideal: dict = {}
    if cameras is not None and ks:
        # The imaged circle is an ellipse in ideal (undistorted) pixels, not in the raw
        # image: fit there (the centre is mapped back by the caller).
        use = [k for k in ks if cameras[view[k]] is not None]
        if use:
            ideal = _ideal_fits(found, use, view, cameras)
    fits = [(*ideal[k][2:], found[k][1], *ideal[k][:2], shared[k]) if k in ideal else (*found[k], cen[k], Q[k], shared[k]) for k in ks]
    covs = center_covariances(fits)
    for i, k in enumerate(ks):
        out[k] = ((cen[k], Q[k]), ideal[k][:2] if k in ideal else None, float(width[k]), covs[i], bool(reached[k]), float(even[k]))
    return out


_WARM = False


def _warm_profiles(K: int, ii, f2, lam, S, v) -> None:
    """Warm up the ray sampling (uint8 and float32 images) and the edge locators."""
    for img in (np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.float32)):
        _sample_rays(img, ii, np.full(K, 4.0), np.full(K, 4.0), f2, f2, lam, S, np.full(K, 2, np.intp), v, f2.copy(), f2.copy())
    crossings(v, f2, f2, lam, np.full(K, 1 / 3), S, f2)
    integral(v, f2, f2, lam, np.full(K, 1 / 3), S, (f2, f2))


def _warm_fits(K: int, N: int, f2, b2) -> None:
    """Warm up the ellipse fits: direct, robust (LMedS, harmonics, rejection) and their helpers."""
    _scatter(np.zeros((K, N, 2)), f2, b2, np.zeros((K, 2)), np.zeros(K), np.zeros((K, len(_MOMENTS))))
    ring = np.stack([np.cos(np.arange(N)), 2 * np.sin(np.arange(N))], -1)[None]
    fit_ellipses(ring, b2)
    fit_robust(ring, b2, {"outlier_k": 3.0, "outlier_min_px": 0.15}, (np.zeros((K, 2)), np.tile(np.eye(2), (K, 1, 1))), f2)
    _lmeds(np.ones((K, 5, N)), f2, b2, np.full(K, N, np.intp), np.zeros((K, 2, 5), np.intp), 0.15, b2.copy())
    _harmonics(f2, np.empty((K, 5, N)))
    _spd2(np.tile(np.eye(2), (K, 1, 1)), 0.5)
    _radial_offsets(np.ones((K, N, 2)), np.zeros((K, 2)), np.tile(np.eye(2), (K, 1, 1)))
    _reject(f2, b2, b2, 3.0, 0.15, b2.copy(), np.empty(K, bool))
    _center_covs(ring.repeat(K, 0), np.ones((K, N)), np.tile(np.eye(2), (K, 1, 1)), np.zeros((K, 2, 2)), np.empty((K, 2, 2)))


def _warm_rays(K: int, N: int, f2, b2) -> None:
    """Warm up :func:`refine_edges`' kernels (the rays, the levels, the edges and the kernels
    they call, the neighbours' and the plate's included; the fits' bookkeeping) on a drawn
    disk, a coarse pass first."""
    yy, xx = np.mgrid[:40, :40]
    img = np.where((xx - 20.0) ** 2 + (yy - 20.0) ** 2 < 100.0, 40, 200).astype(np.uint8)
    c = {
        "edge_spacing": 4.0, "min_rays": 8, "max_rays": 64, "edge_step": 0.5, "level_samples": 0.2, "min_free_frac": 0.25,
        "level_tol": 0.25, "level_smooth": 0.1, "area_window": (0.5, 0.5), "edge_method": "area", "edge_weights": True,
        "refine_iters": 2, "refine_tol": 0.005, "refine_first_tol": 0.0, "close_seed_screen": False, "refine_predict": True,
        "first_pass_spacing": 6.0, "first_pass_max_width": 0.2, "min_valid_frac": 0.5, "rescreen_frac": 0.03,
        "outlier_k": 3.0, "outlier_min_px": 0.15,
    }  # fmt: skip
    Q = np.eye(2)[None] / 100.0
    refine_edges([img], np.zeros(1, np.intp), np.array([[20.0, 20.0]]), Q, 0.5, True, c, np.ones(1), [[(np.array([45.0, 20.0]), Q[0])]],
                 plates=[plate_lines(np.array([[2.0, 2.0], [38.0, 2.0], [38.0, 38.0], [2.0, 38.0]]))])  # fmt: skip
    masked_median(f2, b2)
    plane_levels(np.zeros((K, N, 2)), f2, b2, np.zeros((K, 2)), np.ones(K), np.ones(K))


def warm_up() -> None:
    """Compile the kernels (or load them from numba's cache) for the argument types the
    pipeline passes, once per process: a stream's first frames must not pay for it."""
    global _WARM
    if _WARM:
        return
    K, N, Sm = 1, 6, 4
    ii, f2, b2 = np.zeros(K, np.intp), np.ones((K, N)), np.ones((K, N), bool)
    lam, S, v = np.linspace(0.5, 1.5, Sm)[None], np.full(K, Sm, np.intp), np.zeros((K, N, Sm))
    _warm_profiles(K, ii, f2, lam, S, v)
    _warm_fits(K, N, f2, b2)
    _warm_rays(K, N, f2, b2)
    _WARM = True


__all__ = [
    "bilinear",
    "edge_points",
    "fit_ellipses",
    "fit_robust",
    "lmeds_inliers",
    "masked_median",
    "masked_percentile",
    "plane_levels",
    "refine_edges",
]
