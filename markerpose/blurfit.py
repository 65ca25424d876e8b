"""Sub-pixel ring ellipses under motion blur: a fit of a blurred-ring image model.

Why: under linear motion blur longer than the ring's black band, edge profiles along
the motion never reach the ink or paper level inside the band, so edge-based fits
(:func:`markerpose.classical.refine_ring`) locate the edges across the motion well but
those along it poorly; a neighbouring ring's blur reaches into the profile as well.
Here the marker's rings are fitted together to every pixel their blur reaches: the
image is modelled as

    I(x) = (p0 + g . x) + (a + b . x) * sum over the rings of R_k(x),

where R_k is a ring (outer ellipse minus the white disk inside it) convolved with a
box of length L along the motion direction theta and a Gaussian of sigma px (optics and
pixel area), and the two planes are the paper level and the rings' contrast (solved
linearly for any geometry). Each ring's outer ellipse (centre and shape) and white
disk's offset, and the shared theta, L and sigma, are fitted by robust
Levenberg-Marquardt, started from the edge fit and from the best (theta, L) on a
coarse grid.

The box-blurred indicator of an ellipse is exact and cheap: along the line through a
pixel in the motion direction the ellipse occupies a chord [s1, s2] (a quadratic's
roots), and the blurred value is the chord's overlap with [-L/2, L/2] over L, smoothed
by sigma in closed form. Across the motion, sigma is applied by a three-point
Gauss-Hermite rule, each of its lines itself smoothed across near the ellipse's tangents
(where a bare line's chord opens as a square root and the fit's cost would have cusps).

The fit samples the image sparsely, each sample the mean of the pixel block around it, so
that every pixel's noise counts at a fraction of the model's cost. Its last iterations
model each sample as what it is, the block's mean (a 2 x 2-point rule over the block,
:func:`block_offset`); the model of the block's centre alone, with its Gaussian widened,
misfits sharp edges by what depends on where the samples fall on them.
"""

from __future__ import annotations

import math

import numpy as np

from .geometry import minor_semi_axis
from .jit import compiled

_SQ2PI = np.sqrt(2 * np.pi)
_SQ2 = np.sqrt(2.0)
# Gauss-Hermite rule for a unit normal: nodes and weights.
_GH_T = np.array([-np.sqrt(3.0), 0.0, np.sqrt(3.0)])
_GH_W = np.array([1 / 6, 2 / 3, 1 / 6])


def _smooth_sqrt_table(lo=-6.0, hi=12.05, step=0.05):
    """F(a) = E[sqrt(max(a + z, 0))] and F'(a), z ~ N(0, 1), on a grid of a: with a + z = t^2,
    F = 2 int_0^inf t^2 phi(t^2 - a) dt and F' = int_0^inf phi(t^2 - a) dt."""
    a = np.arange(lo, hi + step / 2, step)
    t, dt = np.linspace(0.0, np.sqrt(hi + 12.0), 4001, retstep=True)
    phi = np.exp(-0.5 * (t[None, :] ** 2 - a[:, None]) ** 2) / np.sqrt(2 * np.pi)
    trap = np.full(len(t), dt)
    trap[[0, -1]] = dt / 2  # the trapezoid rule's weights
    return float(a[0]), step, (phi * (2 * t * t)) @ trap, phi @ trap


_SQ_LO, _SQ_STEP, _SQ_F, _SQ_FP = _smooth_sqrt_table()

default_conf: dict = {
    "margin": 4.0,  # pixels used: within the blurred ring's reach plus this, px
    "grid_angles": 8,  # coarse search: motion directions over 180° ...
    "grid_lengths": (6.0, 14.0, 26.0),  # ... and blur lengths, px
    "grid_stride": 4,  # ... on every grid_stride-th pixel in x and y, or ...
    "grid_stride_frac": 0.2,  # ... every this fraction of the smallest minor semi-axis, if more
    #                           (large rings: the search's choice is as clear on fewer pixels)
    "grid_search": "axes",  # "axes": every direction at the middle length, then every length
    #                        at the best direction; "full": every (direction, length) pair
    "stride": 3,  # the fit uses every stride-th pixel in x and y, each the mean of the
    #               block of this size around it (odd: one more when even), so that every
    #               pixel's noise is averaged in at a ninth of the model evaluations ...
    "max_pixels": 20_000,  # ... or a sparser grid where that would give more pixels: the
    #                        marker's rings give fewer even at the nearest working distance,
    #                        a large ring-like decoy many more (seconds of fitting)
    "block_fit": True,  # ... fitted by a model of the blocks' means (block_offset), started
    #                     where a fit of the model at the blocks' centres settled (False:
    #                     that fit alone, whose result then depends on its start at sharp
    #                     edges) ...
    "jac_once_length": 10.0,  # ... its derivatives those of its first evaluation (its centres
    #                           move by hundredths of a pixel) where the blur is at least this
    #                           long, px (inf: at every iterate; shorter blur leaves sharper
    #                           edges, whose derivatives change faster) ...
    "jac_move": 0.01,  # ... but anew at a trial step that moves a centre farther than this, px
    "block_start_tol": 0.01,  # ... which stops at this centre step, px, or ...
    "block_start_ftol": 1e-3,  # ... this relative cost change
    "max_iter": 30,  # Levenberg-Marquardt iterations at most
    "xtol": 1e-4,  # convergence: relative parameter change ...
    "ftol": 1e-4,  # ... or relative cost change ...
    "center_tol": 0.002,  # ... or no centre moved more than this, px ...
    "center_predict": True,  # ... or would move more than this in the steps still to come,
    #                          extrapolated from the last two as a geometric series (the steps
    #                          shrink by a steady factor near the optimum: the step that
    #                          would only confirm the tolerance is saved)
    "max_move": 0.0,  # give up once a centre is this far from its start, px (0: never)
    "loss_scale": 3.0,  # robust loss: residuals beyond this many noise sigmas count less
    "tangent_smooth": 0.5,  # near the ellipses' tangents along the motion, each of the three
    #                         lines across is smoothed across by this fraction of sigma (the
    #                         lines spread by the rest of its variance): a bare line's chord
    #                         opens as a square root where it meets the tangent, which put
    #                         cusps into the cost wherever a sample's line crossed one (the
    #                         steps zigzag, fits from nearby starts settle apart); 0: bare lines
    "min_length": 0.0,  # give up when the coarse search's best blur length is under this, px
    #                     (seeds where no edge fitted: without blur, they missed the rings)
}


PLATE_SLACK_PX = 3.0  # beyond the motion's reach, the optics' blur and a block mean's half width, px

_JCOLS = {"c": slice(0, 2), "Q": slice(2, 5), "theta": 5, "L": 6, "sigma": 7}  # a disk's derivative columns


def blurred_disk(x, y, c, Q, theta, L, sigma, jac=False, box=1, smooth=None):
    """The indicator of the ellipse (p - c)^T Q (p - c) <= 1 convolved with a box of length
    ``L`` along ``theta`` (radians) and a Gaussian of ``sigma`` px (exact along the motion,
    a three-point rule across, each line smoothed near the tangents by ``smooth`` x sigma,
    None: ``default_conf["tangent_smooth"]``), at the points (x, y); with an odd ``box`` > 1,
    its mean over the ``box`` x ``box`` pixels centred on each point (:func:`block_offset`).

    Returns the values (N,), and with ``jac`` also their derivatives: a dict with ``c``
    (N, 2), ``Q`` (N, 3) for (Q11, Q12, Q22), ``theta``, ``L`` and ``sigma`` (N,).
    A chord end p on the ellipse moves with any parameter as ds = -dq / (2 u^T Q p),
    q(s) = (d + s u)^T Q (d + s u) - 1 being the quadratic whose roots are the ends.
    """
    x, y = np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64)
    val = np.zeros(len(x))
    J = np.zeros((len(x), 8) if jac else (1, 8))
    _add_disks(x, y, [(c, Q, 1.0, (0, -1, 5), (1.0, 1.0, 1.0))], theta, L, sigma, jac, val, J, block_offset(box), _tangent_smooth(smooth))
    if not jac:
        return val
    return val, {k: J[:, col] for k, col in _JCOLS.items()}


def _tangent_smooth(smooth) -> float:
    """``smooth`` (None: ``default_conf["tangent_smooth"]``) as the kernel takes it, checked."""
    kap = float(default_conf["tangent_smooth"] if smooth is None else smooth)
    if not 0.0 <= kap < 1.0:
        raise ValueError(f"tangent_smooth must be in [0, 1), got {kap}")
    return kap


def block_offset(box: int) -> float:
    """The offset h of the 2 x 2-point rule (+-h, +-h) for the mean of a function over a block
    of ``box`` x ``box`` pixels (odd) centred on a point: h^2 = r (r + 1) / 3, r = box // 2,
    the variance of a pixel's offset along each axis within the block (0 for one pixel).

    A block's mean is the image convolved with that discrete box. Modelled as the point
    model alone (its Gaussian widened to take the box in), the box's flat profile is
    misfitted at sharp edges, by what depends on where the sparse samples fall on them: fits
    of the same rings from nearby starts then settle apart, and the poses depend on where
    stage 1 put its candidates."""
    r = int(box) // 2
    return math.sqrt(r * (r + 1) / 3.0)


def _add_disks(x, y, disks, theta, L, sigma, jac, val, J, h=0.0, smooth=0.0):
    """Add each of ``disks`` = (c, Q, sign, cols, scales), in their order, in one compiled
    call: ``sign`` times :func:`blurred_disk` at (x, y) (lines smoothed near the tangents by
    ``smooth`` x sigma), or with ``h`` > 0 its mean over the
    four points (x +- h, y +- h) (:func:`block_offset`), to ``val`` and, with ``jac``, its
    derivatives to ``J``'s columns ``cols`` = (centre and form (5 from there), a second copy
    of the centre's (-1: none), theta / L / sigma (3 from there)); ``scales`` = (the form's,
    L's, sigma's) divide the form's derivatives and multiply L's and sigma's (a
    reparametrisation)."""
    u0, u1 = math.cos(theta), math.sin(theta)
    L, sigma = max(float(L), 0.05), float(sigma)
    rows = np.empty((len(disks), 14))
    for n, (c, Q, sign, cols, scales) in enumerate(disks):
        q00, q01, q11 = float(Q[0, 0]), float(Q[0, 1]), float(Q[1, 1])
        det = q00 * q11 - q01 * q01
        # Only points within the blurred ellipse's bounding box (its half-widths: the inverse
        # form's diagonal, square-rooted) can be non-zero.
        ext0 = math.sqrt(q11 / det) + abs(u0) * 0.5 * L + 6.0 * sigma + h
        ext1 = math.sqrt(q00 / det) + abs(u1) * 0.5 * L + 6.0 * sigma + h
        rows[n] = (c[0], c[1], q00, q01, q11, ext0, ext1, sign, cols[0], cols[1], cols[2], scales[0], scales[1], scales[2])
    _disks_kernel(x, y, rows, u0, u1, L, sigma, float(h), float(smooth), bool(jac), val, J)


@compiled(fast=True)
def _disks_kernel(x, y, rows, u0, u1, L, sigma, h, kap, jac, val, J):  # pragma: no cover - compiled
    """:func:`_disk_kernel` of each disk's row of :func:`_add_disks`, in order."""
    for n in range(rows.shape[0]):
        r = rows[n]
        _disk_kernel(
            x, y, r[0], r[1], r[2], r[3], r[4], u0, u1, L, sigma, h, kap, r[5], r[6], r[7], jac, val, J,
            int(r[8]), int(r[9]), int(r[10]), r[11], r[12], r[13],
        )  # fmt: skip


@compiled(fast=True)
def _disk_kernel(
    x, y, c0, c1, q00, q01, q11, u0, u1, L, sigma, h, kap, ext0, ext1, sign, jac, val, J, col_cq, col_d, col_m, sq, sl, ss
):  # pragma: no cover - compiled
    """:func:`_add_disks` per point (or, with ``h`` > 0, per each of the four points (+-h,
    +-h) around it, a quarter each): the chord [s1, s2] of the ellipse along the motion
    through the point (shifted across it by each Gauss-Hermite node), its overlap with
    the box [-L/2, L/2] smoothed by sigma (G, the antiderivative of the normal CDF,
    in closed form), and the derivatives through the chord ends.

    The chord's half-length r = sqrt(disc) / A (disc = B^2 - A C, q(s) = A s^2 + 2 B s + C
    the quadratic whose roots are its ends) is taken smoothed across by eps = ``kap``
    sigma: r = sqrt(d_eps) F(disc / d_eps), F the Gaussian mean of a square
    root (:func:`_smooth_sqrt`). Across the motion disc is a concave parabola with slope
    d_eps / eps = 2 sqrt(det Q n^T adj(Q) n) at the tangents, so near them this is the chord
    averaged over lines within eps; away from them F(a) = sqrt(a) (1 - 1 / (8 a^2) ...). The
    derivatives follow s_1,2 = (-B -+ r) / A through B, C, A and d_eps. With ``kap`` 0, bare
    lines: r = sqrt(disc), its derivative clipped at tangent chords."""
    n0, n1 = -u1, u0
    Lh = 0.5 * L
    qu0, qu1 = q00 * u0 + q01 * u1, q01 * u0 + q11 * u1
    A = u0 * qu0 + u1 * qu1
    subs = 4 if h > 0 else 1
    share = 1.0 / subs
    spread = math.sqrt(1.0 - kap * kap)  # the lines' spread: sigma's variance less eps's
    det = q00 * q11 - q01 * q01
    Nn = n0 * n0 * q11 - 2.0 * n0 * n1 * q01 + n1 * n1 * q00  # n^T adj(Q) n
    root = math.sqrt(det * Nn)
    eps = kap * sigma
    deps = 2.0 * eps * root
    sq_deps = math.sqrt(deps)
    smooth = deps > 0.0
    # d_eps's derivatives: Q's three entries (the off-diagonal counted twice), theta, sigma
    e00 = eps * (Nn * q11 + det * n1 * n1) / root
    e01 = eps * (-2.0 * Nn * q01 - 2.0 * det * n0 * n1) / root
    e11 = eps * (Nn * q00 + det * n0 * n0) / root
    eth = eps * det * (-2.0 * (u0 * (q11 * n0 - q01 * n1) + u1 * (q00 * n1 - q01 * n0))) / root
    esg = deps / sigma
    nqu = n0 * qu0 + n1 * qu1  # n^T Q u
    # Points whose every line lies within the ellipse over the box and the Gaussian's reach
    # (1) or misses it there (0), found at the point itself: their lines' origins are within
    # ro of it (the block's offsets, the lines across, their smoothing near the tangents), and
    # a point that far moves the ellipse's norm by at most ro / (minor semi-axis).
    ro = (math.sqrt(2.0) * h + (_GH_T[2] + 6.0 * kap) * sigma + 0.5) * math.sqrt(
        0.5 * (q00 + q11) + math.sqrt(0.25 * (q00 - q11) ** 2 + q01 * q01)
    )
    reach = Lh + 5.0 * sigma + 0.5
    for i in range(len(x)):
        if not (abs(x[i] - c0) < ext0 and abs(y[i] - c1) < ext1):
            continue
        dx, dy = x[i] - c0, y[i] - c1
        B = dx * qu0 + dy * qu1
        C = q00 * dx * dx + 2 * q01 * dx * dy + q11 * dy * dy
        sm = min(max(-B / A, -reach), reach)  # the nearest point to the centre on the segment
        if math.sqrt(max(A * sm * sm + 2.0 * B * sm + C, 0.0)) >= 1.0 + ro:
            continue  # every line misses the ellipse within the reach: no value, no derivative
        qa, qb = A * reach * reach + C, 2.0 * B * reach
        if math.sqrt(max(qa + qb, qa - qb, 0.0)) <= 1.0 - ro:
            val[i] += sign  # every line's chord covers the box and the Gaussian's reach
            continue
        vi = 0.0
        j0 = j1 = j2 = j3 = j4 = j5 = j6 = j7 = 0.0
        for node3 in range(3 * subs):
            node, sub = node3 % 3, node3 // 3
            ox = 0.0 if subs == 1 else (h if sub & 1 else -h)
            oy = 0.0 if subs == 1 else (h if sub & 2 else -h)
            tau, w = _GH_T[node] * spread, _GH_W[node] * share
            off = tau * sigma
            dx = x[i] + ox + off * n0 - c0
            dy = y[i] + oy + off * n1 - c1
            B = dx * qu0 + dy * qu1
            C = q00 * dx * dx + 2 * q01 * dx * dy + q11 * dy * dy - 1.0
            disc = B * B - A * C
            if smooth:
                a = disc / deps
                if not a > _SQ_LO:
                    continue
                F, Fp = _smooth_sqrt(a)
                r = sq_deps * F
                kd = Fp / sq_deps  # dr / d(disc)
                ke = (F - 2.0 * a * Fp) / (2.0 * sq_deps)  # dr / d(d_eps)
            else:
                if not disc > 0:
                    continue
                r = math.sqrt(disc)
                kd = 0.5 / max(r, 0.25 * A)  # tangent chords: the derivative is clipped
                ke = 0.0
            s1, s2 = (-B - r) / A, (-B + r) / A
            G0, P0, p0 = _normal((Lh - s1) / sigma)
            G1, P1, p1 = _normal((-Lh - s1) / sigma)
            G2, P2, p2 = _normal((Lh - s2) / sigma)
            G3, P3, p3 = _normal((-Lh - s2) / sigma)
            v = (G0 - G1 - G2 + G3) * (sigma / L)
            vi += w * v
            if not jac:
                continue
            j6 += w * (-v / L + (P0 + P1 - P2 - P3) / (2 * L))
            if P0 == P1 and P2 == P3 and p0 == 0.0 and p1 == 0.0 and p2 == 0.0 and p3 == 0.0:
                continue  # both chord ends beyond the box on one side each: no other derivative
            # dv = dv/ds1 ds1 + dv/ds2 ds2, ds_1,2 = (-dB -+ dr - s_1,2 dA) / A and
            # dr = kd (2 B dB - A dC - C dA) + ke d(d_eps): per parameter KB dB + KC dC + KA dA + KE d(d_eps).
            dv1, dv2 = -(P0 - P1) / L, (P2 - P3) / L
            cR = (dv2 - dv1) / A
            KB = -(dv1 + dv2) / A + 2.0 * B * kd * cR
            KC = -A * kd * cR
            KA = -(dv1 * s1 + dv2 * s2) / A - C * kd * cR
            KE = ke * cR
            gx, gy = q00 * dx + q01 * dy, q01 * dx + q11 * dy  # Q d
            j0 += w * (-KB * qu0 - 2.0 * KC * gx)
            j1 += w * (-KB * qu1 - 2.0 * KC * gy)
            j2 += w * (KB * u0 * dx + KC * dx * dx + KA * u0 * u0 + KE * e00)
            j3 += w * (KB * (u0 * dy + u1 * dx) + 2.0 * KC * dx * dy + 2.0 * KA * u0 * u1 + KE * e01)
            j4 += w * (KB * u1 * dy + KC * dy * dy + KA * u1 * u1 + KE * e11)
            j5 += w * (KB * (n0 * gx + n1 * gy - off * A) - 2.0 * KC * off * B + 2.0 * KA * nqu + KE * eth)
            j7 += w * ((p0 - p1 - p2 + p3) / L + KB * tau * nqu + 2.0 * KC * tau * (n0 * gx + n1 * gy) + KE * esg)
        val[i] += sign * vi
        if jac:
            _add_disk_row(J, i, sign, j0, j1, j2, j3, j4, j5, j6, j7, col_cq, col_d, col_m, sq, sl, ss)


@compiled(fast=True)
def _smooth_sqrt(a):  # pragma: no cover - compiled
    """(F(a), F'(a)) of :func:`_smooth_sqrt_table`: from a = 12 on (most of a chord's
    lines) its series sqrt(a) (1 - 1 / (8 a^2) - 15 / (128 a^4)), whose next term is below
    1e-7 there; below, the table's cubic Hermite interpolation (F' the interpolant's own
    derivative, so that the fit's derivatives are those of its model)."""
    if a >= 12.0:
        ra, i2 = math.sqrt(a), 1.0 / (a * a)
        return ra * (1.0 - i2 * (0.125 + 0.1171875 * i2)), (0.5 + i2 * (0.1875 + 0.41015625 * i2)) / ra
    u = (a - _SQ_LO) / _SQ_STEP
    k = int(u)
    t = u - k
    f0, f1 = _SQ_F[k], _SQ_F[k + 1]
    m0, m1 = _SQ_FP[k] * _SQ_STEP, _SQ_FP[k + 1] * _SQ_STEP
    t2, t3 = t * t, t * t * t
    F = (2 * t3 - 3 * t2 + 1) * f0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * f1 + (t3 - t2) * m1
    dF = (6 * t2 - 6 * t) * f0 + (3 * t2 - 4 * t + 1) * m0 + (-6 * t2 + 6 * t) * f1 + (3 * t2 - 2 * t) * m1
    return F, dF / _SQ_STEP


@compiled(fast=True)
def _add_disk_row(J, i, sign, j0, j1, j2, j3, j4, j5, j6, j7, col_cq, col_d, col_m, sq, sl, ss):  # pragma: no cover - compiled
    """Add ``sign`` times point ``i``'s derivatives (centre, form, the centre's copy,
    theta / L / sigma) to its row of ``J``, the form's divided by ``sq`` and L's and
    sigma's multiplied by ``sl`` and ``ss`` (the reparametrisation of :func:`_add_disks`)."""
    J[i, col_cq] += sign * j0
    J[i, col_cq + 1] += sign * j1
    J[i, col_cq + 2] += sign * j2 / sq
    J[i, col_cq + 3] += sign * j3 / sq
    J[i, col_cq + 4] += sign * j4 / sq
    if col_d >= 0:
        J[i, col_d] += sign * j0
        J[i, col_d + 1] += sign * j1
    J[i, col_m] += sign * j5
    J[i, col_m + 1] += sign * j6 * sl
    J[i, col_m + 2] += sign * j7 * ss


@compiled(fast=True)
def _normal(t):  # pragma: no cover - compiled
    """(G, Phi, phi) of t: G(t) = t Phi(t) + phi(t), the antiderivative of the normal CDF
    Phi, and its density phi; beyond |t| >= 5 their limits (max(t, 0), step, 0)."""
    if abs(t) >= 5.0:
        return max(t, 0.0), 1.0 if t > 0 else 0.0, 0.0
    e = math.exp(-0.5 * t * t)
    p = e / _SQ2PI
    # The upper tail by Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7), sharing exp with p.
    k = 1.0 / (1.0 + 0.3275911 * abs(t) / _SQ2)
    Q = 0.5 * k * (0.254829592 + k * (-0.284496736 + k * (1.421413741 + k * (-1.453152027 + k * 1.061405429)))) * e
    P = 1.0 - Q if t > 0 else Q
    return t * P + p, P, p


class _Problem:
    """The pixels around the rings, the model's residuals and its Jacobian.

    Parameters p: per ring, centre (2), Q11, Q12, Q22 times scale^2 (3) and the inner
    disk's offset (2); then theta, log L, log sigma shared by all rings.
    """

    def __init__(self, gray, cqs, rho, noise, box=1, plate=None, smooth=None):
        self.cqs = [(np.asarray(c, float), np.asarray(Q, float)) for c, Q in cqs]
        self.plate = None if plate is None else np.asarray(plate, np.float64).reshape(4, 3)
        self.rho, self.gray, self.box = rho, gray, int(box) | 1  # odd: centred on its pixel
        # A block mean's noise: white noise would be box times smaller, but neighbouring
        # pixels' noise is correlated in real images (demosaicing, compression), and a
        # loss scale set too small sends a start that is a pixel off into a poor minimum.
        self.noise = max(float(noise) * 2 / (self.box + 1), 0.5)
        self.scale = float(np.mean([np.sqrt(1 / np.sqrt(np.linalg.det(Q))) for _, Q in self.cqs]))  # ~ sqrt(radius)
        self.k = len(self.cqs)
        self._kept = None  # (parameters, model, derivatives) of the last model with derivatives
        self.block = False  # the model of each sample's block mean (True) or of its centre
        self.freeze = False  # keep the derivatives of the next model computed with them ...
        self.frozen = None  # ... here, and give those instead of computing them again
        self.smooth = _tangent_smooth(smooth)  # the lines' smoothing near the tangents
        self.njev = 0  # model evaluations with derivatives

    def grid(self, reach, stride=1):
        """Per ring (centre, the form of its outer ellipse widened by ``reach`` px), and the
        extent (x0, y0, x1, y1) of the grid of every ``stride``-th pixel that covers them
        inside the image."""
        h, w = self.gray.shape
        boxes, forms = [], []
        for c, Q in self.cqs:
            lam, V = np.linalg.eigh(Q)
            a = 1 / np.sqrt(lam)
            forms.append((c, (V / (a + reach) ** 2) @ V.T))
            R = a[0] + reach
            boxes.append((c[0] - R, c[1] - R, c[0] + R, c[1] + R))
        b = np.array(boxes)
        x0, y0 = int(max(np.floor(b[:, 0].min()), 0)), int(max(np.floor(b[:, 1].min()), 0))
        # The grid on multiples of the stride: the samples (and the blocks whose means they
        # are) do not move with the start, so nearby starts fit the same data.
        x0, y0 = x0 + (-x0) % stride, y0 + (-y0) % stride
        x1, y1 = int(min(np.ceil(b[:, 2].max()), w - 1)), int(min(np.ceil(b[:, 3].max()), h - 1))
        return forms, (x0, y0, x1, y1)

    def pixels(self, reach, stride=1, motion=None):
        """Use the pixels within ``reach`` px of any outer ellipse (inside the image); with
        ``motion`` = (theta, L), only those a blurred ring can reach: within ``reach`` of
        an outer ellipse moved by up to L / 2 along the motion."""
        self._kept = None  # the model kept for the old pixels
        forms, (x0, y0, x1, y1) = self.grid(reach, stride)
        if x1 - x0 < 8 or y1 - y0 < 8:
            return False
        # Per ring the quantities of its test (the chord along the motion; without motion,
        # the pixel inside the widened ellipse), per plate side its margin; the grid's
        # pixels are tested, and their block means taken, in one compiled pass.
        k = len(forms)
        cen, Qxs = np.array([c for c, _ in forms], np.float64), np.array([Qx for _, Qx in forms], np.float64)
        QuA = np.zeros((k, 3))
        half = -1.0  # no motion
        if motion is not None:
            u = np.array([np.cos(motion[0]), np.sin(motion[0])])
            for j, (_, Qx) in enumerate(forms):
                Qu = Qx @ u
                QuA[j] = Qu[0], Qu[1], u @ Qu
            half = 0.5 * motion[1]
        sides = np.zeros((0, 3)) if self.plate is None else self.plate
        # What lies beyond the plate is not the model's paper: a pixel counts only where the
        # blur (along the motion, or any way by up to the longest length searched) cannot
        # bring it in.
        along = np.array(
            [0.5 * motion[1] * abs(a * np.cos(motion[0]) + b * np.sin(motion[0])) if motion is not None else reach for a, b, _ in sides],
            np.float64,
        )
        n_max = ((y1 - y0) // stride + 1) * ((x1 - x0) // stride + 1)
        xi, yi, v = np.empty(n_max, np.int64), np.empty(n_max, np.int64), np.empty(n_max)
        n = _select_pixels(self.gray, x0, y0, x1, y1, stride, cen, Qxs, QuA, half, sides, along + PLATE_SLACK_PX, self.box, xi, yi, v)
        self.x, self.y = xi[:n].astype(np.float64), yi[:n].astype(np.float64)
        self.stride = stride
        self.v = v[:n].copy()  # a fresh buffer: the compiled fast-math sums split their lanes by where an array starts
        ctr = np.mean([c for c, _ in self.cqs], axis=0)
        span = max(x1 - x0, y1 - y0) / 2
        self.xs, self.ys = (self.x - ctr[0]) / span, (self.y - ctr[1]) / span
        self.w = np.ones(len(self.v))
        return len(self.v) >= 50 * self.k

    def start(self):
        p = []
        for c, Q in self.cqs:
            q = Q * self.scale**2
            p += [*c, q[0, 0], q[0, 1], q[1, 1], 0.0, 0.0]
        return np.array(p + [0.0, 0.0, np.log(0.8)])

    def centers(self, p):
        """The rings' centres (k, 2) in the parameters ``p`` (or a step's centre moves)."""
        return p[: 7 * self.k].reshape(-1, 7)[:, :2]

    def unpack(self, p):
        rings = []
        for j in range(self.k):
            q = p[7 * j : 7 * j + 7]
            rings.append((q[0:2], np.array([[q[2], q[3]], [q[3], q[4]]]) / self.scale**2, q[5:7]))
        return rings, p[-3], np.exp(p[-2]), np.exp(p[-1])

    def model(self, p, jac=False):
        """The rings' summed blurred indicator at the pixels (N,) and, with ``jac``, its
        derivatives (N, 7 k + 3). The last one computed with derivatives is kept: the
        optimiser's accepted trial is its next iterate, where the derivatives are needed
        under new robust weights (which only the levels' linear fit depends on)."""
        kept = self._kept
        if kept is not None and np.array_equal(kept[0], p):
            return kept[1], kept[2]
        N, k = len(self.v), self.k
        R = np.zeros(N)
        full = jac and self.frozen is None
        J = np.zeros((N, 7 * k + 3) if full else (1, 7 * k + 3))
        h = block_offset(self.box) if self.block else 0.0
        if not _model_kernel(np.asarray(p, np.float64), k, self.rho**2, self.scale**2, h, self.smooth, self.x, self.y, full, R, J):
            raise ValueError("blur length or sigma out of range (beyond e^±12 px), or an ellipse form not positive definite")
        self.njev += full
        if not jac:
            return R, None
        if self.frozen is not None:
            J = self.frozen
        elif self.freeze:
            self.frozen, self.freeze = J, False
        self._kept = (p.copy(), R, J)
        return R, J

    def evaluate(self, p, jac=False, keep=False):
        """(residuals in noise sigmas, level coefficients, normal equations or None);
        ``keep``: compute the model's derivatives too and keep them (see :meth:`model`).

        With ``jac``, the normal equations (H, g) of the robustly weighted cost at ``p``:
        H = Jr^T W Jr and g = Jr^T W r, Jr the residuals' Jacobian by variable projection
        (Kaufman: Jr = (I - M (M^T W M)^-1 M^T W) Jm, Jm the model's derivatives times the
        rings' contrast). They are formed from Jm without Jr: the projection's cross terms
        collapse to B^T (M^T W M)^-1 B with B = M^T W Jm, and M^T W r = 0 at the levels'
        weighted fit, so g = Jm^T W r."""
        R, J = self.model(p, jac or keep)
        if not jac:
            J = _NO_J
        res, beta = np.empty(len(R)), np.empty(6)
        H, g = np.empty((J.shape[1], J.shape[1])), np.empty(J.shape[1])
        # The levels are a weighted fit (robust weights); one compiled pass each for them,
        # the residuals and the normal equations.
        if not _levels_and_normals(R, J, self.xs, self.ys, self.v, self.w, self.noise, bool(jac), res, beta, H, g):
            raise np.linalg.LinAlgError("the levels' normal equations are singular")
        return res, beta, ((H, g) if jac else None)


_NO_J = np.zeros((1, 1))  # the derivatives' place where none are asked for


@compiled
def _select_pixels(gray, x0, y0, x1, y1, stride, cen, Qxs, QuA, half, sides, limits, box, xi, yi, v):  # pragma: no cover - compiled
    """:meth:`_Problem.pixels`' grid: the pixels (x0 + i stride, y0 + j stride) within
    (x1, y1) that some ring reaches (``half`` < 0: inside its widened ellipse, centre
    ``cen[j]``, form ``Qxs[j]``; else its chord along the motion, ``QuA[j]`` = (Q u, u Q u),
    meets it within ``half``) and every plate side (a, b, c) keeps (a x + b y + c >
    ``limits``), row by row, into ``xi``, ``yi``, and into ``v`` their values: the mean of
    the ``box`` x ``box`` block around each (float32, as OpenCV's box filter of the grid's
    crop gives it, the crop's borders reflected), or the pixel's own where ``box`` is 1.
    Returns their number."""
    h, w = gray.shape
    r = box // 2
    ya, xa = max(y0 - r, 0), max(x0 - r, 0)  # the crop OpenCV's filter would see
    yb, xb = min(y1 + r + 1, h), min(x1 + r + 1, w)
    scale = 1.0 / (box * box)
    n = 0
    for y in range(y0, y1 + 1, stride):
        for x in range(x0, x1 + 1, stride):
            inside = False
            for j in range(len(cen)):
                dx, dy = x - cen[j, 0], y - cen[j, 1]
                C = Qxs[j, 0, 0] * dx * dx + 2 * Qxs[j, 0, 1] * dx * dy + Qxs[j, 1, 1] * dy * dy - 1
                if half < 0:
                    if C <= 0:
                        inside = True
                        break
                    continue
                B = dx * QuA[j, 0] + dy * QuA[j, 1]
                A = QuA[j, 2]
                disc = B * B - A * C
                rt = math.sqrt(max(disc, 0.0))
                if disc > 0 and (-B - rt) / A <= half and (-B + rt) / A >= -half:
                    inside = True
                    break
            if not inside:
                continue
            for m in range(len(sides)):
                if not sides[m, 0] * x + sides[m, 1] * y + sides[m, 2] > limits[m]:
                    inside = False
                    break
            if not inside:
                continue
            xi[n], yi[n] = x, y
            if box > 1:
                acc = 0.0
                for q in range(y - r, y + r + 1):
                    qq = q if q >= ya else 2 * ya - q  # reflected about the crop's first row ...
                    qq = qq if qq < yb else 2 * (yb - 1) - qq  # ... and its last
                    for p in range(x - r, x + r + 1):
                        pp = p if p >= xa else 2 * xa - p
                        pp = pp if pp < xb else 2 * (xb - 1) - pp
                        acc += np.float64(np.float32(gray[qq, pp]))
                v[n] = np.float64(np.float32(acc * scale))
            else:
                v[n] = np.float64(gray[y, x])
            n += 1
    return n


@compiled(fast=True)
def _levels_and_normals(R, J, xs, ys, v, w, noise, jac, res, beta, H, g):  # pragma: no cover - compiled
    """:meth:`_Problem.evaluate`'s algebra: the levels' weighted least squares (the six
    columns M = [1, x, y, R, R x, R y], weights w; a 1e-9 ridge), the residuals (M beta -
    v) / noise into ``res`` and beta into ``beta``; with ``jac`` the normal equations into
    ``H`` and ``g``. False where the levels' matrix is not positive definite."""
    N = len(R)
    A = np.zeros((6, 6))
    b = np.zeros(6)
    m = np.empty(6)
    for i in range(N):
        m[0], m[1], m[2], m[3], m[4], m[5] = 1.0, xs[i], ys[i], R[i], R[i] * xs[i], R[i] * ys[i]
        wi = w[i]
        for a in range(6):
            wa = wi * m[a]
            b[a] += wa * v[i]
            for c in range(a + 1):
                A[a, c] += wa * m[c]
    for a in range(6):
        A[a, a] += 1e-9
        for c in range(a):
            A[c, a] = A[a, c]
    Lc = np.zeros((6, 6))
    if not _cholesky(A, Lc):
        return False
    beta[:] = b
    _cholesky_solve(Lc, beta)
    for i in range(N):
        res[i] = (beta[0] + beta[1] * xs[i] + beta[2] * ys[i] + R[i] * (beta[3] + beta[4] * xs[i] + beta[5] * ys[i]) - v[i]) / noise
    if not jac:
        return True
    # H = J^T W' J - B^T A^-1 B with W' = w wgt^2, B = M^T (w wgt J), wgt the rings' contrast
    # at the pixel in noise sigmas; g = J^T (w wgt res) (variable projection, Kaufman).
    P = J.shape[1]
    H[:] = 0.0
    g[:] = 0.0
    B = np.zeros((6, P))
    for i in range(N):
        wgt = (beta[3] + beta[4] * xs[i] + beta[5] * ys[i]) / noise
        ww = w[i] * wgt
        m[0], m[1], m[2], m[3], m[4], m[5] = 1.0, xs[i], ys[i], R[i], R[i] * xs[i], R[i] * ys[i]
        for a in range(P):
            ja = J[i, a]
            if ja == 0.0:
                continue
            g[a] += ww * res[i] * ja
            t = ww * wgt * ja
            for c in range(a + 1):
                H[a, c] += t * J[i, c]
            t = ww * ja
            for r in range(6):
                B[r, a] += m[r] * t
    X = B.copy()
    for a in range(P):
        col = X[:, a].copy()
        _cholesky_solve(Lc, col)
        X[:, a] = col
    for a in range(P):
        for c in range(a + 1):
            s = 0.0
            for r in range(6):
                s += B[r, a] * X[r, c]
            H[a, c] -= s
            H[c, a] = H[a, c]
    return True


@compiled(fast=True)
def _cholesky(A, L):  # pragma: no cover - compiled
    """L lower-triangular with L L^T = A (n x n); False where A is not positive definite."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0:
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@compiled(fast=True)
def _cholesky_solve(L, x):  # pragma: no cover - compiled
    """x <- A^-1 x for A = L L^T, in place."""
    n = L.shape[0]
    for i in range(n):
        s = x[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


def _robust_lm(prob, p, conf):
    """Robust Levenberg-Marquardt: iteratively reweighted least squares with Cauchy
    weights 1 / (1 + (r / f)^2) (f = conf["loss_scale"] noise sigmas), so that pixels the
    model cannot explain (the plate's edge, clutter, an occluder) stop counting; the
    weights also enter the levels' linear fit. Each iteration takes one damped
    Gauss-Newton step on the weighted cost by the normal equations (few parameters, many
    pixels). Returns (parameters, number of model evaluations, gave up): it gives up, with
    the parameters where it stopped, when a centre went farther than conf["max_move"]
    (a start that missed the rings).

    The loop runs in one compiled call (:func:`_lm_kernel`), outside Python's lock, so that
    a pair's two fits run side by side; it leaves ``prob``'s robust weights, its kept model
    and its frozen derivatives as the model's own evaluations would."""
    frozen = prob.frozen
    out = _lm_kernel(
        prob.x, prob.y, prob.xs, prob.ys, prob.v, prob.w, prob.noise, np.asarray(p, np.float64), prob.k, prob.rho**2,
        prob.scale**2, block_offset(prob.box) if prob.block else 0.0, prob.smooth, float(conf["loss_scale"]) ** 2,
        int(conf["max_iter"]), float(conf["jac_move"]), float(conf["ftol"]), float(conf["xtol"]), float(conf["center_tol"]),
        float(conf["max_move"] or 0.0), frozen is not None, _NO_J if frozen is None else frozen, bool(prob.freeze),
        bool(conf["center_predict"]),
    )  # fmt: skip
    status, p, nfev, njev, gave_up, kept, frozen, has_frozen, freeze = out
    prob.njev += njev
    if status == _BAD_START:
        raise ValueError("the start is outside the model's range")
    if status == _SINGULAR:
        raise np.linalg.LinAlgError("the levels' normal equations are singular")
    prob._kept = kept if kept[0].shape[0] else None
    prob.frozen, prob.freeze = (frozen if has_frozen else None), freeze
    return p, nfev, gave_up


_OK, _BAD_START, _SINGULAR = 0, 1, 2  # :func:`_lm_kernel`'s outcomes


@compiled
def _model_kernel(p, k, rho2, scale2, h, kap, x, y, full, R, J):  # pragma: no cover - compiled
    """The rings' summed blurred indicator at the points (x, y) into the zeroed ``R`` and
    (with ``full``) its derivatives into ``J`` (:meth:`_Problem.model`; its parameters as
    :meth:`_Problem.unpack` reads them): per ring the outer disk minus the white disk (centre
    c + d, form Q / rho^2), the derivatives to the ring's columns (c, Q, d) and the shared
    (theta, log L, log sigma). False where ``p`` is outside the model's range (a blur
    length or sigma beyond e^+-12 px, a form that is not positive definite)."""
    if not (abs(p[-2]) < 12 and abs(p[-1]) < 12):
        return False
    theta, L, sigma = p[-3], math.exp(p[-2]), math.exp(p[-1])
    u0, u1 = math.cos(theta), math.sin(theta)
    Lc = max(L, 0.05)
    rows = np.empty((2 * k, 14))
    for j in range(k):
        q = p[7 * j : 7 * j + 7]
        a00, a01, a11 = q[2] / scale2, q[3] / scale2, q[4] / scale2
        if not (a00 > 0 and a00 * a11 - a01 * a01 > 0):
            return False
        for m in range(2):  # the outer disk, then the white one (centre c + d, form Q / rho^2)
            inner = m == 1
            c0, c1 = (q[0] + q[5], q[1] + q[6]) if inner else (q[0], q[1])
            f = rho2 if inner else 1.0
            q00, q01, q11 = a00 / f, a01 / f, a11 / f
            sign, col_d, sq = (-1.0, 7 * j + 5, rho2 * scale2) if inner else (1.0, -1, scale2)
            det = q00 * q11 - q01 * q01
            ext0 = math.sqrt(q11 / det) + abs(u0) * 0.5 * Lc + 6.0 * sigma + h
            ext1 = math.sqrt(q00 / det) + abs(u1) * 0.5 * Lc + 6.0 * sigma + h
            r = rows[2 * j + m]
            r[0], r[1], r[2], r[3], r[4], r[5], r[6] = c0, c1, q00, q01, q11, ext0, ext1
            r[7], r[8], r[9], r[10], r[11], r[12], r[13] = sign, 7 * j, col_d, 7 * k, sq, L, sigma
    _disks_kernel(x, y, rows, u0, u1, Lc, sigma, h, kap, full, R, J)
    return True


@compiled
def _centre_step(step, k):  # pragma: no cover - compiled
    """The largest |coordinate| of the rings' centre moves in ``step``."""
    m = 0.0
    for j in range(k):
        m = max(m, abs(step[7 * j]), abs(step[7 * j + 1]))
    return m


@compiled
def _lm_kernel(
    x,
    y,
    xs,
    ys,
    v,
    w,
    noise,
    p,
    k,
    rho2,
    scale2,
    h,
    kap,
    f2,
    max_iter,
    jac_move,
    ftol,
    xtol,
    center_tol,
    max_move,
    has_frozen,
    frozen,
    freeze,
    predict,
):  # pragma: no cover - compiled
    """:func:`_robust_lm`'s loop: (outcome, parameters, model evaluations, those with
    derivatives, gave up, the kept model
    (parameters, values, derivatives; empty parameters: none), frozen derivatives, whether
    they hold, whether the next derivatives are to be frozen). The robust weights are
    updated in ``w``. Each step is numpy's solve of the damped normal equations (the same
    LAPACK routine), the costs its dot product, so the iterates are those of the loop in
    numpy."""
    N, P = len(x), 7 * k + 3
    nojac = np.zeros((1, 1))
    no_kept = (np.zeros(0), np.zeros(0), np.zeros((1, 1)))
    start = np.empty((k, 2))
    for j in range(k):
        start[j, 0], start[j, 1] = p[7 * j], p[7 * j + 1]
    beta = np.empty(6)
    H, g = np.empty((P, P)), np.empty(P)
    no_H, no_g = np.empty((1, 1)), np.empty(1)  # the normal equations' place where none are asked for
    # The start's model with its derivatives (the first iteration's), and its residuals.
    R = np.zeros(N)
    J = np.zeros((N, P)) if not has_frozen else np.zeros((1, P))
    njev = 0
    if not _model_kernel(p, k, rho2, scale2, h, kap, x, y, not has_frozen, R, J):
        return _BAD_START, p, 1, njev, False, no_kept, frozen, has_frozen, freeze
    njev += not has_frozen
    if has_frozen:
        J = frozen
    elif freeze:
        frozen, has_frozen, freeze = J, True, False
    kept_p, kept_R, kept_J = p.copy(), R, J
    r = np.empty(N)
    if not _levels_and_normals(R, nojac, xs, ys, v, w, noise, False, r, beta, no_H, no_g):
        return _SINGULAR, p, 1, njev, False, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze
    lam, nfev = 1e-3, 1
    last = np.inf  # the centres' move in the step before
    for _ in range(max_iter):
        for i in range(N):
            w[i] = 1 / (1 + r[i] * r[i] / f2)
        # The iterate's model is the kept one: the start's, or the accepted trial's.
        r = np.empty(N)
        if not _levels_and_normals(kept_R, kept_J, xs, ys, v, w, noise, True, r, beta, H, g):
            return _SINGULAR, p, nfev, njev, False, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze
        E = np.dot(w, r * r)
        D = np.diag(H).copy()
        for a in range(P):
            if D[a] <= 0:
                D[a] = 1.0
        nfev += 1
        while True:
            A = H + lam * np.diag(D)
            ok = np.all(np.isfinite(A)) and np.all(np.isfinite(g))
            step = np.linalg.solve(A, -g) if ok else np.full(P, np.nan)
            trial = p + step
            if has_frozen and _centre_step(step, k) > jac_move:
                has_frozen, freeze = False, True  # derivatives frozen this far away would be stale: anew at the trial
            Et = np.inf
            if np.array_equal(kept_p, trial):
                Rt, valid = kept_R, True
            else:
                Rt = np.zeros(N)
                Jt = np.zeros((N, P)) if not has_frozen else np.zeros((1, P))
                valid = _model_kernel(trial, k, rho2, scale2, h, kap, x, y, not has_frozen, Rt, Jt)
                if valid:
                    njev += not has_frozen
                    if has_frozen:
                        Jt = frozen
                    elif freeze:
                        frozen, has_frozen, freeze = Jt, True, False
                    kept_p, kept_R, kept_J = trial.copy(), Rt, Jt  # accepted, it is the next iterate
            rt = np.empty(N)
            if valid:
                if not _levels_and_normals(Rt, nojac, xs, ys, v, w, noise, False, rt, beta, no_H, no_g):
                    return _SINGULAR, p, nfev, njev, False, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze
                Et = np.dot(w, rt * rt)
            nfev += 1
            if Et < E:
                break
            lam *= 10
            if lam > 1e8:
                return _OK, p, nfev, njev, False, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze
        move = _centre_step(step, k)
        small = E - Et <= ftol * E or move <= center_tol
        if predict and not small and move < last < np.inf:
            q = move / last  # the steps' ratio: what remains is move q / (1 - q)
            small = move * q <= center_tol * (1.0 - q)
        last = move
        if not small:
            small = True
            for a in range(P):
                if not abs(step[a]) <= xtol * (abs(p[a]) + xtol):
                    small = False
                    break
        p, r = trial, rt
        if max_move:
            far = 0.0
            for j in range(k):
                dx, dy = p[7 * j] - start[j, 0], p[7 * j + 1] - start[j, 1]
                far = max(far, math.sqrt(dx * dx + dy * dy))
            if far > max_move:
                return _OK, p, nfev, njev, True, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze
        lam = max(lam / 10, 1e-7)
        if small:
            break
    return _OK, p, nfev, njev, False, (kept_p, kept_R, kept_J), frozen, has_frozen, freeze


def fit_blurred_rings(gray, cqs, rho, noise=2.0, conf=None, plate=None):
    """Outer ellipses of motion-blurred rings by one image-model fit of all of them.

    Args:
        gray: (H, W) grey image, uint8 or float32 (C-contiguous).
        cqs: per ring, (centre (2,), Q (2, 2)) of a starting outer ellipse (e.g. the
            edge fit's); all rings of one marker, so that their blur is modelled.
        rho: inner/outer diameter ratio of the marker's rings.
        noise: the image's noise sigma, grey levels.
        conf: overrides of :data:`default_conf`.
        plate: None, or the plate's sides in the image (4, 3): (a, b, c) with a x + b y + c
            the distance inside the plate, px: pixels that the blur may reach from beyond
            the plate are not used.
    Returns:
        dict with ``cqs`` (list of (centre, Q)), ``theta`` (rad), ``length`` and
        ``sigma`` (px), ``center_covs`` ((k, 2, 2) the centres' covariances, px^2), ``rms`` (residual RMS in noise sigmas of the block means), ``contrast`` (ring
        level minus paper level at the marker's middle, grey levels), ``nfev`` and
        ``njev`` (the model's evaluations, and those with derivatives), and
        ``gave_up``: True when a centre went farther than ``max_move`` from its start and
        the fit stopped there (its ellipses are where it stopped, not a fit); or None when
        too few pixels are usable or the fit fails.
    """
    c = dict(default_conf)
    if conf:
        c.update(conf)
    if c["grid_search"] not in ("axes", "full"):
        raise ValueError(f"grid_search must be 'axes' or 'full', got {c['grid_search']!r}")
    prob = _Problem(gray, cqs, rho, noise, box=c["stride"], plate=plate, smooth=c["tangent_smooth"])
    base = prob.start()
    # Coarse search over the motion (direction, length) with the start ellipses, on a
    # sparse pixel grid.
    minor = min(minor_semi_axis(Q) for _, Q in prob.cqs)
    grid_stride = max(int(c["grid_stride"]), int(c["grid_stride_frac"] * minor))
    if not prob.pixels(0.5 * max(c["grid_lengths"]) + c["margin"], stride=grid_stride):
        return None
    p0 = _coarse_motion(prob, base, c)
    if np.exp(p0[-2]) < c["min_length"]:
        return None
    if not _fit_pixels(prob, (p0[-3], 1.3 * np.exp(p0[-2])), c):
        return None
    try:
        block = c["block_fit"] and prob.box > 1
        first = {**c, "center_tol": c["block_start_tol"], "ftol": c["block_start_ftol"]} if block else c
        p, nfev, gave_up = _robust_lm(prob, p0, first)
        if block and not gave_up:
            # The fit of the blocks' centres (the cheaper model) gives the start of the fit
            # of their means, which costs four times as much per iteration.
            prob.block, prob._kept = True, None
            prob.freeze = bool(np.exp(p[-2]) >= c["jac_once_length"])
            p, more, gave_up = _robust_lm(prob, p, c)
            nfev += more
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.all(np.isfinite(p)):
        return None
    return _fit_result(prob, p, nfev, gave_up)


def _coarse_motion(prob, base, c):
    """The start parameters ``base`` with the (theta, log L) of least cost on the coarse
    grid of motion directions and lengths (conf["grid_search"]), on the current pixels.
    The lines are bare (no smoothing near the tangents): a coarse choice, cheaper, does."""

    def costed(cands):
        """(cost, parameters) of each (theta, L) of ``cands``, costed in one compiled call;
        the model's errors raised as its own evaluation raises them, at the first."""
        th = np.array([t for t, _ in cands], np.float64)
        logL = np.array([np.log(L) for _, L in cands], np.float64)
        costs, status = _motion_costs(
            prob.x, prob.y, prob.xs, prob.ys, prob.v, prob.w, prob.noise, base, prob.k, prob.rho**2, prob.scale**2, th, logL
        )
        if status == _BAD_START:
            raise ValueError("blur length or sigma out of range")
        if status == _SINGULAR:
            raise np.linalg.LinAlgError("the levels' normal equations are singular")
        out = []
        for t, lL, cost in zip(th, logL, costs):
            p = base.copy()
            p[-3], p[-2] = t, lL
            out.append((float(cost), p))
        return out

    def cost(t):
        return t[0]

    angles, lengths = np.arange(c["grid_angles"]) * np.pi / c["grid_angles"], c["grid_lengths"]
    prob._kept = None
    if c["grid_search"] == "full":
        return min(costed([(th, L) for th in angles for L in lengths]), key=cost)[1]
    # The direction shows at any length near the true one; the length then at that direction.
    middle = sorted(lengths)[len(lengths) // 2]
    best = min(costed([(th, middle) for th in angles]), key=cost)
    return min([best] + costed([(best[1][-3], L) for L in lengths if L != middle]), key=cost)[1]


@compiled
def _motion_costs(x, y, xs, ys, v, w, noise, base, k, rho2, scale2, thetas, log_lengths):  # pragma: no cover - compiled
    """The residuals' sum of squares of the model (bare lines, the samples' centres) at
    ``base`` with each (theta, log L) of ``thetas``, ``log_lengths``, and the outcome: the
    costs stop at the first (theta, L) where the model is out of range or the levels' fit is
    singular (:func:`_lm_kernel`'s outcomes)."""
    N, P = len(x), 7 * k + 3
    out = np.full(len(thetas), np.nan)
    p = base.copy()
    nojac, no_H, no_g, beta = np.zeros((1, 1)), np.empty((1, 1)), np.empty(1), np.empty(6)
    for n in range(len(thetas)):
        p[-3], p[-2] = thetas[n], log_lengths[n]
        R, r = np.zeros(N), np.empty(N)
        if not _model_kernel(p, k, rho2, scale2, 0.0, 0.0, x, y, False, R, np.zeros((1, P))):
            return out, _BAD_START
        if not _levels_and_normals(R, nojac, xs, ys, v, w, noise, False, r, beta, no_H, no_g):
            return out, _SINGULAR
        out[n] = np.dot(r, r)
    return out, _OK


def _fit_pixels(prob, motion, c):
    """Select the fit's pixels, those a ring blurred by ``motion`` = (theta, L) can reach,
    on a grid sparse enough for conf["max_pixels"]; False when too few are usable."""
    if not prob.pixels(c["margin"], stride=c["stride"], motion=motion):
        return False
    if len(prob.v) > c["max_pixels"]:
        stride = int(np.ceil(c["stride"] * np.sqrt(len(prob.v) / c["max_pixels"])))
        if not prob.pixels(c["margin"], stride=stride, motion=motion):
            return False
    return True


# The blurred-ring model's misfit that its residuals do not show (its blur and optics only
# approximate the image's, the more so the longer the blur): the centres scatter more than
# s^2 H^-1 says, by this many px per axis and px of blur length (added in variance).
# Measured by ``markerpose eval uncertainty`` on blurred pairs of a seed of their own (its
# report gives the excess).
MODEL_PX_PER_BLUR_PX = 0.001


def _center_covs(prob, p, r, normals) -> np.ndarray:
    """(k, 2, 2) covariances of the rings' centres, px^2: s^2 H^-1 of the robustly weighted
    normal equations ``normals`` = (H, g) at ``p`` (None: NaN), ``r`` the residuals there in
    noise sigmas (s^2 their weighted variance, so the image's own residuals set the scale),
    plus (:data:`MODEL_PX_PER_BLUR_PX` x the fitted blur length) squared per axis, NaN where
    H is singular."""
    if normals is None:
        return np.full((prob.k, 2, 2), np.nan)
    try:
        s2 = float(prob.w @ (r * r)) / max(float(prob.w.sum()) - len(p) - 6, 1.0)  # the levels' six coefficients are fitted too
        cov = s2 * _correlation_inflation(prob, np.sqrt(prob.w) * r) * np.linalg.inv(normals[0])
    except np.linalg.LinAlgError:
        return np.full((prob.k, 2, 2), np.nan)
    idx = [np.array([7 * j, 7 * j + 1]) for j in range(prob.k)]
    L = float(prob.unpack(p)[2])
    return np.stack([cov[np.ix_(i, i)] for i in idx]) + (MODEL_PX_PER_BLUR_PX * L) ** 2 * np.eye(2)


def _correlation_inflation(prob, r) -> float:
    """The variance inflation of a fit to residuals ``r`` (one per sample of ``prob``'s grid)
    correlated with their neighbours: where the model misfits (its blur and optics only
    approximate the image's), the misfit spans several samples, and the samples carry
    less information than their number says. For a field correlated as a first-order
    process along each axis (lag-one correlations rho_x, rho_y of the residuals on the
    grid), the inflation is prod (1 + rho) / (1 - rho)."""
    st = float(getattr(prob, "stride", 1))
    return _lag_inflation(prob.x, prob.y, st, np.ascontiguousarray(r, np.float64))


@compiled
def _lag_inflation(x, y, stride, r):  # pragma: no cover - compiled
    """:func:`_correlation_inflation`'s kernel: the samples (x, y) placed on their grid of
    ``stride`` px, and for each axis the lag-one correlation of ``r`` over the neighbouring
    pairs where both are finite (an axis with fewer than ten such pairs is left out),
    clipped to [0, 0.9]."""
    x0, y0 = x.min(), y.min()
    ix, iy = np.empty(len(x), np.intp), np.empty(len(x), np.intp)
    for i in range(len(x)):
        ix[i], iy[i] = round((x[i] - x0) / stride), round((y[i] - y0) / stride)
    grid = np.full((iy.max() + 1, ix.max() + 1), np.nan)
    for i in range(len(x)):
        grid[iy[i], ix[i]] = r[i]
    ny, nx = grid.shape
    f = 1.0
    for axis in range(2):
        sab, saa, sbb, n = 0.0, 0.0, 0.0, 0
        for j in range(ny - axis):
            for i in range(nx - 1 + axis):
                a, b = grid[j + axis, i + 1 - axis], grid[j, i]
                if np.isfinite(a) and np.isfinite(b):
                    sab += a * b
                    saa += a * a
                    sbb += b * b
                    n += 1
        if n < 10:
            continue
        rho = min(max(sab / max(math.sqrt(saa * sbb), 1e-300), 0.0), 0.9)
        f *= (1 + rho) / (1 - rho)
    return f


def _fit_result(prob, p, nfev, gave_up):
    """The result dict of :func:`fit_blurred_rings` for the fitted parameters ``p``."""
    try:
        r, beta, normals = prob.evaluate(p, jac=True)
    except (np.linalg.LinAlgError, ValueError):  # no covariances; the residuals as the model gives them (or its error)
        (r, beta, _), normals = prob.evaluate(p), None
    covs = _center_covs(prob, p, r, normals)
    rings, theta, L, sigma = prob.unpack(p)
    return {
        "cqs": [(cen.copy(), Q) for cen, Q, _ in rings],
        "center_covs": covs,
        "theta": float(theta % np.pi),
        "length": float(L),
        "sigma": float(sigma),
        "rms": float(np.sqrt(np.mean(r * r))),
        "contrast": float(beta[3]),
        "nfev": nfev,
        "njev": prob.njev,
        "gave_up": gave_up,
    }


_WARM = False


def warm_up() -> None:
    """Compile the model's kernel (or load it from numba's cache) once per process."""
    global _WARM
    if not _WARM:
        blurred_disk(np.zeros(2), np.zeros(2), np.zeros(2), np.eye(2), 0.0, 2.0, 0.8, jac=True)
        blurred_disk(np.zeros(2), np.zeros(2), np.zeros(2), np.eye(2), 0.0, 2.0, 0.8)
        one = np.empty(16, np.int64)
        for dtype in (np.uint8, np.float32):  # a frame's gray, or an image given as float32
            rings = (np.zeros((1, 2)), np.eye(2)[None], np.zeros((1, 3)), -1.0, np.zeros((0, 3)), np.zeros(0))
            _select_pixels(np.zeros((4, 4), dtype), 0, 0, 3, 3, 1, *rings, 3, one, one.copy(), np.empty(16))
        z = np.zeros(8)
        for J in (np.zeros((8, 3)), _NO_J):
            _levels_and_normals(
                z, J, z, z, z, z + 1, 1.0, J is not _NO_J, np.empty(8), np.empty(6), np.empty((J.shape[1],) * 2), np.empty(J.shape[1])
            )
        p = np.array([0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, np.log(0.8)])
        for full in (True, False):
            _model_kernel(p, 1, 0.25, 1.0, 0.0, 0.5, z, z, full, np.zeros(8), np.zeros((8, 10) if full else (1, 10)))
        _lm_kernel(z, z, z, z, z, z + 1, 1.0, p, 1, 0.25, 1.0, 0.0, 0.5, 9.0, 1, 0.01, 1e-4, 1e-4, 0.002, 0.0, False, _NO_J, False, True)
        _motion_costs(z, z, z, z, z, z + 1, 1.0, p, 1, 0.25, 1.0, np.zeros(1), np.zeros(1))
        _lag_inflation(z, z, 1.0, z)
        _WARM = True
