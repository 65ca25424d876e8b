"""Track: on a video stream, the previous frames are the prior.

From the last three poses a constant-acceleration model predicts the marker's pose in the
new frame (:func:`predict`); the rings' outer ellipses under that pose
(:func:`~markerpose.geometry.ring_ellipses`) seed the sub-pixel edge fit in both views
directly — no stage 1, no EllipSegNet. The result passes the usual verification
(every centre edge-fitted, epipolar distances, plate check, the marker's shape) and a
quality gate on the reprojection error. Otherwise the marker is first sought around the
prediction by the correlation of its drawn appearance (:func:`shift`, ``shift_margin``),
and the predicted rings, moved to where that puts them, are fitted and gated as above;
failing that, the frame is detected cold, first with stage 1 looking only around where
the marker was predicted (``near_margin``), then in the whole images.

While the marker is lost, a pair that has not changed since the last cold detection that
found nothing (:func:`changed`: no block of either view moved beyond its noise) is not
detected again: a still scene costs a comparison, not a detection, and the marker coming
into view is a change. A cold detection still runs every ``lost_refresh`` frames.
"""

from __future__ import annotations

import cv2
import numpy as np

from .. import settings
from ..geometry import ring_ellipses
from ..settings import number
from ..sync import motion

default_conf = {
    "max_residual_px": 0.5,  # quality gate: RMS reprojection error of the six centres, px
    "one_pass_move": 0.15,  # px: a ring's edge fit from its predicted ellipse stops after
    #                         one pass when that pass moved it less than this (a still or
    #                         slow marker: the prediction was close), else it iterates to
    #                         convergence as a cold detection's does
    "shift_margin": 0.5,  # when the prior fails: the marker's drawn appearance is first sought
    #                       by correlation this many predicted plate extents around the
    #                       prediction in each view (:func:`shift`), and the prior's rings,
    #                       moved there, fitted as a tracked frame's are (0: no search)
    "shift_min_score": 0.4,  # ... the least normalised correlation that counts as found
    "jump_ratio": 3.0,  # a pose found after the prior failed that moved the marker's rings more
    #                     than this many times their move in the frame before it is a jump (the
    #                     marker put down elsewhere, a cut): the next prior takes the marker as
    #                     standing there, not as moving by that step again (0: always a velocity)
    "near_margin": 0.5,  # when the prior fails: stage 1 first looks only this many predicted
    #                      marker extents beyond the predicted marker in each view (0: the
    #                      whole images at once), then in the whole images
    "lost_change": 6.0,  # while lost: a block mean that moved more than this many times the
    #                      blocks' noise (and a grey level) since the last cold detection is
    #                      a change, and the pair is detected cold (0: every lost pair is)
    "lost_block": 8,  # ... px, the side of those blocks
    "lost_refresh": 30,  # ... frames: a cold detection at least this often even without change
}
RULES = {
    "max_residual_px": number(0, above=True),
    "one_pass_move": number(0),
    "shift_margin": number(0),
    "shift_min_score": number(-1, 1),
    "jump_ratio": number(0),
    "near_margin": number(0),
    "lost_change": number(0),
    "lost_block": number(1, integer=True),
    "lost_refresh": number(1, integer=True),
}

MARGIN_PX = 2.0  # predicted rings must lie this far inside both images
# Frames between estimates of the images' noise (the edge fit's contrast floor) while
# there is a prior; renewed too when the marker is found again after it was lost.
NOISE_EVERY = 30


def predict(history: list) -> np.ndarray:
    """The next T_left_marker (4, 4) from the last one, two or three: the last pose, then
    constant velocity (the last frame-to-frame motion applied once more), then constant
    acceleration (that motion changed once more as it last changed). A hand's motion turns
    within a few frames: under constant velocity the prediction overshoots each turn by
    the motion's change per frame, and the edge fit then needs more passes."""
    if len(history) < 2:
        return history[-1]
    last = history[-1]
    step = last @ np.linalg.inv(history[-2])
    if len(history) >= 3:
        step = (step @ np.linalg.inv(history[-2] @ np.linalg.inv(history[-3]))) @ step
    return step @ last


def _fill_ellipse(img: np.ndarray, centre, axes, angle: float, scale: float, value: int) -> None:
    """Fill an ellipse (``centre`` and full ``axes`` in full-resolution px, ``angle``) into
    ``img`` drawn at 1/``scale``, to 1/16 px (OpenCV's fixed point)."""
    cv2.ellipse(
        img,
        (round(centre[0] / scale * 16), round(centre[1] / scale * 16)),
        (max(1, round(axes[0] / scale * 8)), max(1, round(axes[1] / scale * 8))),
        angle,
        0,
        360,
        value,
        -1,
        cv2.LINE_8,
        4,
    )


def appearance(camera, T: np.ndarray, marker, scale: float, origin: np.ndarray, rings: list | None = None) -> tuple:
    """The marker at pose ``T`` (camera frame) as the view would see it, drawn at 1/``scale``
    of its pixels from ``origin`` (x, y, full-resolution px): (image, mask), float32 over
    the plate's bounding box; the plate white (1), the rings' black bands (0), and the
    mask 1 on the plate, 0 off it (what lies there is not the marker's: a masked
    correlation ignores it). ``rings``: the rings' outer ellipses under ``T`` if known
    (:func:`~markerpose.geometry.ring_ellipses`)."""

    def px(points3d):
        cam = points3d @ T[:3, :3].T + T[:3, 3]
        return (camera.project(cam) - origin) / scale

    corners = px(marker.plate_corners3d)
    size = np.ceil(corners.max(0)).astype(int) + 1
    plate = np.zeros((size[1], size[0]), np.uint8)
    cv2.fillConvexPoly(plate, np.round(corners * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    ink = np.zeros_like(plate)
    for radius, value in ((marker.outer_radius, 1), (marker.inner_radius, 0)):  # the band: outer disk minus the hole
        ellipses = rings if rings is not None and radius == marker.outer_radius else ring_ellipses(camera, T, marker.points3d, radius)
        for centre, axes, angle in ellipses:
            _fill_ellipse(ink, np.subtract(centre, origin), axes, angle, scale, value)
    return (plate & (1 - ink)).astype(np.float32), plate.astype(np.float32)


def _peak(corr: np.ndarray) -> tuple[np.ndarray, float]:
    """The best place (x, y) of a correlation map, sub-pixel by a parabola through the peak
    and its neighbours along each axis, and its value."""
    _, best, _, (bx, by) = cv2.minMaxLoc(corr)
    peak = []
    for c, line in ((bx, corr[by, :]), (by, corr[:, bx])):
        den = line[c - 1] - 2 * line[c] + line[c + 1] if 0 < c < len(line) - 1 else 0.0
        peak.append(c + (0.5 * (line[c - 1] - line[c + 1]) / den if den < 0 else 0.0))
    return np.array(peak), float(best)


def _ring(axes: tuple, angle: float, rho: float, scale: float, pad: float) -> np.ndarray:
    """One ring (outer ellipse ``axes`` full-resolution px, ``angle``; hole ``rho`` of it) drawn
    black on white at 1/``scale``, centred in a square ``pad`` times its outer radius across."""
    half = int(np.ceil(max(axes) / 2 / scale * pad))
    out = np.ones((2 * half + 1, 2 * half + 1), np.uint8)
    for f, value in ((1.0, 0), (rho, 1)):
        _fill_ellipse(out, (half * scale, half * scale), (axes[0] * f, axes[1] * f), angle, scale, value)
    return out.astype(np.float32)


def shift(
    gray: np.ndarray,
    camera,
    T: np.ndarray,
    marker,
    margin: float,
    rings: list | None = None,
    cell_px: float = 8.0,
    ring_cells: int = 3,
    min_ring: float = 0.3,
) -> tuple | None:
    """Where the rings of the marker that the prior puts at pose ``T`` (camera frame) lie in
    ``gray``. The marker's drawn appearance (:func:`appearance`) is correlated with the
    image around the prediction, both at a whole-pixel scale where a ring spans
    ~``cell_px`` pixels, within ``margin`` of the predicted plate's extent beyond it on
    each side; then each ring alone within ``ring_cells`` of where that puts it (the
    marker turned since the prior moves the rings apart; a ring whose own correlation
    stays under ``min_ring``, or peaks on the edge of that range, keeps the marker's
    move). The peaks are sub-pixel by a parabola: within about a third of a search pixel
    (a few image pixels), which the edge fit then captures. The whole predicted plate must
    lie in the image (else stage 1 looks there). Returns ((3, 2) displacements
    px from the predicted ring centres, the marker's normalised correlation in [-1, 1]),
    or None where the predicted plate leaves the image or the window leaves no room to
    search. ``rings``: as in :func:`appearance`."""
    rings = ring_ellipses(camera, T, marker.points3d, marker.outer_radius) if rings is None else rings
    s = max(1, round(min(min(axes) for _, axes, _ in rings) / cell_px))
    corners = camera.project(marker.plate_corners3d @ T[:3, :3].T + T[:3, 3])
    lo, hi = corners.min(0), corners.max(0)
    H, W = gray.shape
    if lo[0] < 0 or lo[1] < 0 or hi[0] > W - 1 or hi[1] > H - 1:
        return None
    grow = margin * float((hi - lo).max())
    x0, y0 = (np.maximum(lo - grow, 0) // s).astype(int) * s
    nx, ny = (np.minimum(hi + grow, (W - 1, H - 1)) + 1 - (x0, y0)).astype(int) // s
    # Pixel i of the window averages image pixels i*s ... i*s + s - 1: its centre is there.
    origin = np.array([x0, y0], np.float64) + (s - 1) / 2
    template, plate = appearance(camera, T, marker, s, origin, rings)
    tx, ty = np.maximum(np.floor((lo - origin) / s), 0).astype(int)
    tmpl, mask = template[ty:, tx:], plate[ty:, tx:]
    if nx <= tmpl.shape[1] + 2 or ny <= tmpl.shape[0] + 2:
        return None
    window = cv2.resize(gray[y0 : y0 + ny * s, x0 : x0 + nx * s], (nx, ny), interpolation=cv2.INTER_AREA).astype(np.float32)
    # Only the plate's pixels count, on both sides (a flat patch under it has no correlation).
    corr = cv2.matchTemplate(window, tmpl, cv2.TM_CCOEFF_NORMED, mask=mask)
    peak, best = _peak(np.nan_to_num(corr, nan=-1.0, posinf=-1.0, neginf=-1.0))
    d = peak - (tx, ty)  # the marker's move, window px
    moves = np.tile(d * s, (len(rings), 1))
    rho = marker.inner_radius / marker.outer_radius
    for k, (centre, axes, angle) in enumerate(rings):
        move = _ring_move(window, centre, axes, angle, rho, s, origin, d, ring_cells, min_ring)
        if move is not None:
            moves[k] = move
    return moves, best


def _ring_move(window, centre, axes, angle: float, rho: float, s: int, origin, d, ring_cells: int, min_ring: float):
    """One ring's displacement (2,) px from its predicted ``centre``, by the correlation of
    its drawn appearance with the ``window`` (pixels of s x s image pixels from ``origin``)
    within ``ring_cells`` of where the marker's move ``d`` (window px) puts it; None (the
    marker's move stands) near the window's edge, for a peak under ``min_ring`` or one on
    the search's edge."""
    ny, nx = window.shape
    ring = _ring(axes, angle, rho, s, 1.25)
    h = ring.shape[0] // 2
    c = (np.asarray(centre) - origin) / s  # the predicted centre, window px
    at = np.round(c + d).astype(int)  # ... after the marker's move
    lo_k, hi_k = at - h - ring_cells, at + h + ring_cells + 1
    if lo_k.min() < 0 or hi_k[0] > nx or hi_k[1] > ny:
        return None  # too near the window's edge to search: the marker's move
    local, score = _peak(cv2.matchTemplate(window[lo_k[1] : hi_k[1], lo_k[0] : hi_k[0]], ring, cv2.TM_CCOEFF_NORMED))
    # A weak peak, or one on the search's edge (the ring may lie beyond): the marker's move.
    if score >= min_ring and np.all((local >= 0.5) & (local <= 2 * ring_cells - 0.5)):
        return (local + lo_k + h - c) * s
    return None


def inside(ellipses: list, size: tuple, margin: float) -> bool:
    """Whether every ellipse (RotatedRect) lies inside an image of ``size`` (w, h) with a margin."""
    w, h = size
    for (cx, cy), (a, b), _ in ellipses:
        r = max(a, b) / 2 + margin
        if not (r <= cx <= w - 1 - r and r <= cy <= h - 1 - r):
            return False
    return True


def blocks(gray: np.ndarray, side: int) -> np.ndarray:
    """The image's means (float32 grey levels) over ``side`` x ``side`` blocks tiling it
    from the top left (a last partial row or column of pixels is left out), exact: from
    the integral image."""
    side = min(int(side), *gray.shape)
    s = cv2.integral(gray)[::side, ::side]
    return ((s[1:, 1:] - s[:-1, 1:] - s[1:, :-1] + s[:-1, :-1]) / float(side * side)).astype(np.float32)


def changed(before: np.ndarray, after: np.ndarray, k: float, level: float = 1.0, scene: float = 2.0) -> bool:
    """Whether block means (:func:`blocks`) moved beyond their noise between two frames:
    some block by more than ``k`` times the blocks' noise plus ``level`` grey levels.

    The noise is the differences' own robust spread (their median absolute value, as a
    sigma): a marker or a hand coming into view moves a minority of the blocks, and the
    cameras' noise, correlated across pixels or not, sets the spread of the rest. When
    the median block itself moved by more than ``scene`` grey levels (the light, the
    camera or most of the scene changed, or noise too strong to tell), that is a change
    too."""
    d = np.abs(after - before)
    med = float(np.median(d))
    return bool(med > scene or d.max() > k * 1.4826 * med + level)


UNSET = object()  # Tracker.next's expected not given


class Tracker:
    """One marker's state along a video stream, and the step from one pair to the next.

    It holds the last poses (the prior), the cameras' noise as the stream estimated it,
    whether the last pose was found after the prior failed, and, while the marker is
    lost, the pair the next ones must differ from to be detected again. :meth:`next`
    runs the steps the module's docstring describes; the refinement, the verification
    and the detections are the pipeline's (``pipeline``: an object with
    ``fitted(frame, predicted, first_tol, noises)``, ``near(frame, T_pred)``,
    ``cold(frame)``, each an Estimate or None, as :class:`markerpose.pipeline.ToolPipeline`
    has; with capture times, ``fitted`` also takes a :class:`markerpose.sync.Motion` and
    ``moved(frame, est, motion)`` moves a detection's right view). Given each pair's
    capture times, the fits from the prior move the right view to the left view's time
    (:mod:`markerpose.sync`); a cold detection does not.

    Args:
        conf: :data:`default_conf` with overrides.
        rig: the calibrated stereo rig.
        marker: the marker's geometry.
    """

    def __init__(self, conf: dict, rig, marker):
        self.conf, self.rig, self.marker = check_conf(conf), rig, marker
        self.reset()

    def reset(self) -> None:
        """Forget the prior: the next pair is detected cold (a new sequence)."""
        self.history: list = []  # the last poses found, oldest first (at most three)
        self.right_prev, self.t_right_prev = [], []  # the last pairs' right-view centres as measured, and their times
        self.motion = None  # the current pair's (markerpose.sync.Motion), or None
        self.noise: tuple = (None, 0)  # both views' noise sigmas, pairs with a prior since
        self.after_miss = False  # the last pose was found after the prior failed
        self.lost: tuple | None = None  # lost: (block means of the last pair detected cold, pairs skipped since)

    def next(self, frame, pipeline, expected=UNSET, times: tuple | None = None):
        """The marker's pose in the frame's pair (an Estimate), or None; the state moves on.
        ``expected``: what :meth:`expected` gave for this pair, where it was called first;
        ``times``: the views' capture times (t_left, t_right), s, or None (synchronised)."""
        c, grays = self.conf, frame.grays
        self.motion = motion(self.right_prev, self.t_right_prev, times)  # the fits of this pair move the right view with it
        now = None
        if not self.history and self.lost is not None and c["lost_change"]:
            now = [blocks(g, c["lost_block"]) for g in grays]
            before, skipped = self.lost
            if skipped + 1 < c["lost_refresh"] and not any(changed(a, b, c["lost_change"]) for a, b in zip(before, now)):
                self.lost = (before, skipped + 1)
                frame.why = "lost, and the pair has not changed since the last one detected without the marker"
                return None
        if expected is UNSET:
            expected = self.expected(frame)
        est = self._fit(frame, pipeline, expected, c["one_pass_move"]) if self.history else None
        history = self.history
        after_miss = est is None and bool(history)
        if est is None:
            if history:  # first the marker sought near where the prior put it, then detected there
                # After a frame whose prior failed, the step into its pose may be a jump (the
                # marker moved or was put down out of sight of the prior), not a velocity:
                # the search starts from that pose, the marker standing still there.
                T_near = history[-1] if self.after_miss else predict(history)
                est = self._fit(frame, pipeline, self.searched(frame, T_near), 0.0)
                if est is None and self.after_miss:  # where the search could not look: standing still
                    est = self._fit(frame, pipeline, self.predicted(grays, T_near), c["one_pass_move"])
                if est is None:
                    est = self._moved(frame, pipeline, pipeline.near(frame, T_near))
            history = history[-1:]  # the prior's acceleration did not hold: velocity only, from here
            if est is None:
                frame.why = None  # neither the prior's nor the near look's failure is why the frame has no pose
                est = self._moved(frame, pipeline, pipeline.cold(frame))
            frame.why = None if est is not None else (frame.why or "no marker found")
        if est is not None and times is not None:
            seen = est.right_measured if est.right_measured is not None else est.detections[1].centers
            # The last pair's with this one's (consecutive pairs: a pair without the marker
            # resets them). Also after a failed prior: the first pose found under a delay is
            # not compensated, and its bias makes the next pairs' priors fail where the image
            # paths are sound.
            self.right_prev, self.t_right_prev = [*self.right_prev[-1:], seen], [*self.t_right_prev[-1:], times[1]]
        else:
            self.right_prev, self.t_right_prev = [], []
        if after_miss and est is not None and self._jumped(est.T):
            history = []  # the step into this pose is no velocity: the marker stands here
        self.history = [*history, est.T][-3:] if est is not None else []
        if est is None:
            self.noise = (None, 0)  # lost: estimated afresh once the marker is found again
        self.after_miss = after_miss and est is not None
        # Lost: this pair is what the next ones must differ from to be detected again.
        if est is not None or not c["lost_change"]:
            self.lost = None
        else:
            self.lost = (now or [blocks(g, c["lost_block"]) for g in grays], 0)
        return est

    def _jumped(self, T: np.ndarray) -> bool:
        """Whether pose ``T``, found after the prior failed, lies a jump from the last pose:
        the marker's rings moved more than ``jump_ratio`` times as far as in the step
        before (which needs two poses: with one, the step is taken as a velocity). A hand
        speeds up over several frames; a marker put down elsewhere, or a cut, moves it in
        one. The rings' move takes in translation and rotation alike (mm)."""
        ratio = self.conf["jump_ratio"]
        if not ratio or len(self.history) < 2:
            return False
        before, last, now = (self.marker.points3d @ P[:3, :3].T + P[:3, 3] for P in (self.history[-2], self.history[-1], T))
        return bool(np.linalg.norm(now - last, axis=1).max() > ratio * np.linalg.norm(last - before, axis=1).max())

    def expected(self, frame) -> list | None:
        """With a prior, the first step of :meth:`next`: the stream's noise for this pair and
        the rings the prior predicts (:meth:`predicted`; None where they leave an image).
        None without a prior. Called apart when several tools' fits are batched."""
        if not self.history:
            return None
        # The cameras' noise as the stream estimated it (renewed every NOISE_EVERY
        # frames): this pair's fits take it, those of a search or a detection after a
        # failed prior too.
        noises, age = self.noise
        if noises is None or age >= NOISE_EVERY:
            noises, age = frame.noises(frame.grays), 0
        else:
            frame.noises(frame.grays, known=noises)
        self.noise = (noises, age + 1)
        return self.predicted(frame.grays, predict(self.history))

    def _moved(self, frame, pipeline, est):
        """A detection's right view moved to the left view's time, where the pair has times."""
        return est if self.motion is None or est is None else pipeline.moved(frame, est, self.motion)

    def _fit(self, frame, pipeline, predicted: list | None, first_tol: float):
        """The pipeline's fit of ``predicted`` ellipses, gated on the reprojection error."""
        if predicted is None:
            return None
        if self.motion is None:  # (a pipeline for synchronised views need not take motion)
            est = pipeline.fitted(frame, predicted, first_tol, self.noise[0])
        else:
            est = pipeline.fitted(frame, predicted, first_tol, self.noise[0], self.motion)
        return est if est is not None and est.residual_px <= self.conf["max_residual_px"] else None

    def predicted(self, grays: list, T_pred: np.ndarray) -> list | None:
        """Per view, the rings' outer ellipses under pose ``T_pred``; None where one leaves
        its image (:data:`MARGIN_PX`)."""
        mk, out = self.marker, []
        for gray, cam, T in zip(grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            ellipses = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            if not inside(ellipses, gray.shape[::-1], MARGIN_PX):
                return None
            out.append(ellipses)
        return out

    def searched(self, frame, T_pred: np.ndarray) -> list | None:
        """After the prior failed: per view, the prior's rings (pose ``T_pred``) moved to
        where the search by the marker's appearance (:func:`shift`) finds them; None where
        a view's search finds nothing like the marker or the rings leave the image."""
        mk, c = self.marker, self.conf
        if not c["shift_margin"]:
            return None
        moved = []
        for gray, cam, T in zip(frame.grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            rings = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            found = frame.timed("search", shift, gray, cam, T, mk, c["shift_margin"], rings)
            if found is None or found[1] < c["shift_min_score"]:
                return None
            ellipses = [((x + dx, y + dy), axes, angle) for ((x, y), axes, angle), (dx, dy) in zip(rings, found[0])]
            if not inside(ellipses, gray.shape[::-1], MARGIN_PX):
                return None
            moved.append(ellipses)
        return moved


def check_conf(conf: dict) -> dict:
    """``conf`` if every value fits :data:`RULES` (``ValueError`` naming the key)."""
    return settings.check("track", conf, RULES)


__all__ = [
    "MARGIN_PX",
    "NOISE_EVERY",
    "RULES",
    "Tracker",
    "appearance",
    "blocks",
    "changed",
    "check_conf",
    "default_conf",
    "inside",
    "predict",
    "shift",
]
