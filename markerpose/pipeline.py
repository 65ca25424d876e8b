"""MarkerPose: two views → propose → match → refine → verify → solve → pose.

The public entry point (docs/design.md)::

    tracker = MarkerPose(rig, preset="default")   # or "paper", "paper-classical", ...
    est = tracker.estimate(left, right)            # stateless cold detection: Estimate or None
    est = tracker.track(left, right)               # video: the previous frames are the prior
    tracker.reset()                                # forget the prior (a new sequence)
    det = tracker.detect(image, view=0)            # one view: Detection or None

The stages live in :mod:`markerpose.stages`; this class only runs them in order.
"""

from __future__ import annotations

import functools
import threading
import time
from contextlib import contextmanager

import numpy as np

from . import presets
from .camera import StereoRig
from .geometry import ring_diameter, ring_ellipses
from .images import as_gray, check_size
from .keypoints import look_size
from .marker import Marker
from .results import Detection, Estimate
from .stages import match, propose, refine, solve, track, verify
from .stages.match import best_per_set, layout_orders, stereo_triples, transfer, transfer_sources

MASK_GATE_MIN_PX = 16.0  # ring diameter in stage 1's input from which the mask gate applies


class _SerialBlas:
    """numpy's BLAS on one thread while any tracker handles a frame.

    The pipeline's products are small (at most a few thousand pixels by a few dozen
    parameters) and gain nothing from more threads, while OpenBLAS's idle threads
    busy-wait for a while after each product and take the cores that the networks'
    runtime needs next. Counted across threads: the first frame in sets one thread, the
    last one out puts back the limits found when the first came in. The limit is the
    process's: while a frame is handled, other threads' numpy runs on one BLAS thread
    too, and a limit they change meanwhile is overwritten at the end. The BLAS libraries
    are those loaded at the first frame."""

    def __init__(self):
        self._lock = threading.Lock()
        self._inside = 0
        self._pools = None  # threadpoolctl's BLAS pools, found when first needed
        self._limit = None

    @contextmanager
    def __call__(self):
        with self._lock:
            if self._inside == 0:
                if self._pools is None:
                    from threadpoolctl import ThreadpoolController

                    self._pools = ThreadpoolController().select(user_api="blas")
                self._limit = self._pools.limit(limits=1)
            self._inside += 1
        try:
            yield
        finally:
            with self._lock:
                self._inside -= 1
                if self._inside == 0:
                    self._limit.restore_original_limits()
                    self._limit = None


serial_blas = _SerialBlas()


def _blas_serial(method):
    """The method run with numpy's BLAS on one thread (:class:`_SerialBlas`)."""
    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with serial_blas():
            return method(self, *args, **kwargs)

    return run


class MarkerPose:
    """Stereo pose of the three-ring marker.

    Args:
        rig: the calibrated stereo rig.
        marker: marker geometry (default: the paper's robot target).
        preset: a name of :data:`markerpose.presets.PRESETS` ("default", "paper",
            "paper-classical", ...).
        detector: "neural" or "classical": shorthand for the presets "default" and
            "classical" (with another preset: that preset with this detector).
        threads: (in ``overrides``) the networks' inference threads (None: every core).
        backend: (in ``overrides``) what runs the networks: "onnxruntime" (the default),
            "openvino" or "openvino-bf16" (OpenVINO at float32 or bfloat16; the ``openvino``
            extra).
        **overrides: one dict of settings per stage (``propose``, ``match``, ``refine``,
            ``verify``, ``solve``; see each stage's ``default_conf``), applied over the preset.
    """

    def __init__(self, rig: StereoRig, marker: Marker | None = None, preset: str = "default", detector: str | None = None, **overrides):
        if not isinstance(rig, StereoRig):
            raise ValueError(f"rig must be a StereoRig, got {type(rig).__name__}")
        self.conf = presets.resolve(preset, detector, **overrides)
        self.preset = preset
        self.rig, self.marker = rig, marker or Marker()
        self.timings: dict = {}  # seconds per stage of the last call (see markerpose bench)
        c = self.conf
        neural = c["detector"] == "neural"
        self.ids = c["match"]["method"] if neural else "classical"
        self.proposer = propose.NeuralProposer(c["propose"], self.marker, self.ids, c["threads"], c["backend"]) if neural else None
        self.refiner = refine.Refiner(c["refine"], self.marker, neural, c["threads"], c["backend"])
        self._history: list = []  # the last poses track() found, oldest first
        self._noise: tuple = (None, 0)  # track(): both views' noise sigmas, frames with a prior since
        self._after_miss = False  # track(): the last pose was found after the prior failed
        self._lost: tuple | None = None  # track(), lost: (block means of the last pair detected cold, pairs skipped since)
        self._fits_left: int | None = None  # work budget of the cold detection under way
        self.why: str | None = None  # after a call that found nothing: the first reason met

    def __repr__(self):
        return f"MarkerPose(preset={self.preset!r}, conf={self.conf!r})"

    def _failed(self, reason: str) -> None:
        """Remember why the best hypothesis of this call failed (the first reason met)."""
        if self.why is None:
            self.why = reason

    def _start(self) -> float:
        self.timings, self.why = {}, None
        self._fits_left = None  # no work budget until a cold detection sets one (_budget)
        self.refiner.budget(None)
        if self.proposer is not None:
            self.proposer.forget()
        self.refiner.frame(True)  # last: the call's finally (_end) ends the frame
        return time.perf_counter()

    def _end(self, t0: float) -> None:
        self.timings["total"] = time.perf_counter() - t0
        self.refiner.frame(False)

    def _budget(self) -> None:
        """Start a cold detection's work budget: ``match.max_fits`` refined hypotheses,
        ``refine.max_blur_fits`` blurred-ring fits."""
        self._fits_left = self.conf["match"]["max_fits"]
        self.refiner.budget(self.conf["refine"]["max_blur_fits"])

    def _timed(self, stage: str, fn, *args):
        t = time.perf_counter()
        out = fn(*args)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t
        return out

    @_blas_serial
    def detect(self, image, view: int = 0) -> Detection | None:
        """Ring centres c0, c1, c2 in one view (the fitted outer ellipses' centres), or None.

        Args:
            image: uint8 gray (H, W) or BGR (H, W, 3), of the size the rig was calibrated for.
            view: which of the rig's cameras took it (0 left, 1 right).
        """
        if view not in (0, 1):
            raise ValueError(f"view must be 0 (left) or 1 (right), got {view!r}")
        gray = as_gray(image)
        cam = self.rig.cameras[view]
        check_size(gray, cam, "image")
        t0 = self._start()
        try:
            if self.proposer is None:
                from . import classical

                det = self._timed("propose", classical.detect, gray, self.marker, self.conf["refine"]["subpixel"], self.refiner.classical)
                self.why = None if det is not None else "no marker-like triple of rings in this view"
                return det
            if self.ids == "head" or not self.refiner.gives_ellipses:  # the paper's decoding: one triple
                det = self._timed("refine", self.refiner, [gray], [cam], self._timed("propose", self.proposer.decoded, [gray]))[0]
                self.why = None if det is not None else "stage 1 decoded no triple in this view"
                return det
            tried = 0
            self._budget()
            cand = None
            for zoom in self.proposer.looks():  # ours: layout triples, best first, until one fits a plate
                cand = self._timed("propose", self.proposer.candidates, [gray], zoom, None if cand is None else [cand])[0]
                for pts, s in self._view_triples(gray, cand, zoom):
                    found = self._fit(self.refiner, [gray], [cam], [(pts, s)])
                    if found is None:
                        break
                    tried += 1
                    reason = verify.plate_rejection(found[0], cam, self.marker, self.conf["verify"]["plate_tol"], verify.VIEWS[view])
                    if reason is None:
                        return found[0]
                    self._failed(reason)
            return None
        finally:
            self._end(t0)

    def _view_triples(self, gray: np.ndarray, cand: np.ndarray, zoom: float) -> list:
        """One view's layout triples to refine, best first: by score x ring evidence,
        without those under ``min_evidence`` (0: by score alone)."""
        m = self.conf["match"]
        p, s, sets = layout_orders(cand, self.marker.centers2d, m["view_min_ratio"]) if m["min_evidence"] else layout_orders(cand, self.marker.centers2d)
        if not len(p):
            self._failed(f"no triple of the {len(cand)} stage-1 candidates has the marker's layout" if len(cand) >= 3 else
                         f"stage 1 found {len(cand)} ring candidate{'s' * (len(cand) != 1)}, fewer than three")
            return []
        # With evidence, every order of a triple, not only the most marker-like one: at a
        # steep tilt a wrong order can have the larger layout ratio, and its rings the
        # wrong sizes. Without, each triple in its order of highest score.
        ev = self.proposer.evidence(gray, p, zoom) if m["min_evidence"] else np.ones(len(s))
        best = best_per_set(s * ev, sets)
        kept = [(p[k], float(s[k] * ev[k])) for k in best if ev[k] >= m["min_evidence"]]
        if not kept:
            self._failed(f"ring evidence: the best of {len(best)} layout triples has {ev.max():.3f} (min_evidence {m['min_evidence']:g})")
        return kept[: m["view_triples"]]

    def _pair(self, left, right) -> list:
        gl, gr = as_gray(left, "left image"), as_gray(right, "right image")
        if gl.shape != gr.shape:
            raise ValueError(f"left and right images differ in size: {gl.shape[::-1]} vs {gr.shape[::-1]}")
        check_size(gl, self.rig.left, "left image")
        check_size(gr, self.rig.right, "right image")
        return [gl, gr]

    @_blas_serial
    def estimate(self, left, right) -> Estimate | None:
        """Pose of the marker from a stereo pair, or None if it is not found in both views.
        Stateless: every pair is detected from scratch (see :meth:`track` for video).

        Args:
            left, right: uint8 gray (H, W) or BGR (H, W, 3) images of the same size.
        Returns:
            :class:`Estimate` (``T`` = T_left_marker in mm, ``points3d``, ``centers``) or None.
        """
        grays = self._pair(left, right)
        t0 = self._start()
        try:
            est = self._cold(grays)
            self.why = None if est is not None else (self.why or "no marker found")
            return est
        finally:
            self._end(t0)

    @_blas_serial
    def track(self, left, right) -> Estimate | None:
        """Pose of the marker in the next pair of a video stream, or None.

        Uses the previous frames as the prior (:mod:`markerpose.stages.track`): the rings
        predicted from the last poses are refitted on the image's edges in both views and
        verified; where that fails (the marker lost, moved too fast, put down elsewhere),
        the marker is sought near the prediction by its appearance and, found there,
        fitted the same way; failing that, the pair is detected cold: first with stage 1
        looking only near the predicted marker, then in the whole images, as
        :meth:`estimate` does. ``Estimate.source`` says which ("tracked": from the prior,
        without stage 1; "detected"). While the marker is lost, a pair that has not changed
        since the last one detected without it returns None at once (``track``:
        ``lost_change``; a cold detection still runs every ``lost_refresh`` pairs). Call
        :meth:`reset` between sequences.
        """
        grays = self._pair(left, right)
        t0 = self._start()
        try:
            c = self.conf["track"]
            now = None
            if not self._history and self._lost is not None and c["lost_change"]:
                now = [track.blocks(g, c["lost_block"]) for g in grays]
                before, skipped = self._lost
                if skipped + 1 < c["lost_refresh"] and not any(track.changed(a, b, c["lost_change"]) for a, b in zip(before, now)):
                    self._lost = (before, skipped + 1)
                    self.why = "lost, and the pair has not changed since the last one detected without the marker"
                    return None
            if self._history:
                # The cameras' noise as the stream estimated it (renewed every noise_every
                # frames): this pair's fits take it, those of a search or a detection after a
                # failed prior too.
                noises, age = self._noise
                if noises is None or age >= c["noise_every"]:
                    noises, age = self.refiner.noises(grays), 0
                else:
                    self.refiner.noises(grays, known=noises)
                self._noise = (noises, age + 1)
            est = self._tracked(grays, track.predict(self._history)) if self._history else None
            history = self._history
            after_miss = est is None and bool(history)
            if est is None:
                if history:  # first the marker sought near where the prior put it, then detected there
                    # After a frame whose prior failed, the step into its pose may be a jump (the
                    # marker moved or was put down out of sight of the prior), not a velocity:
                    # the search starts from that pose, the marker standing still there.
                    T_near = history[-1] if self._after_miss else track.predict(history)
                    est = self._shifted(grays, T_near)
                    if est is None and self._after_miss:  # where the search could not look: standing still
                        est = self._tracked(grays, T_near)
                    if est is None:
                        est = self._near(grays, T_near)
                history = history[-1:]  # the prior's acceleration did not hold: velocity only, from here
                if est is None:
                    self.why = None  # neither the prior's nor the near look's failure is why the frame has no pose
                    est = self._cold(grays)
                self.why = None if est is not None else (self.why or "no marker found")
            self._history = [*history, est.T][-3:] if est is not None else []
            if est is None:
                self._noise = (None, 0)  # lost: estimated afresh once the marker is found again
            self._after_miss = after_miss and est is not None
            # Lost: this pair is what the next ones must differ from to be detected again.
            if est is not None or not c["lost_change"]:
                self._lost = None
            else:
                self._lost = (now or [track.blocks(g, c["lost_block"]) for g in grays], 0)
            return est
        finally:
            self._end(t0)

    def reset(self) -> None:
        """Forget the prior: the next :meth:`track` detects cold (a new sequence)."""
        self._history = []
        self._noise = (None, 0)
        self._after_miss = False
        self._lost = None

    def _tracked(self, grays: list, T_pred: np.ndarray) -> Estimate | None:
        """The rings refitted from their predicted ellipses in both views, verified, solved."""
        mk, c = self.marker, self.conf["track"]
        predicted = []
        for gray, cam, T in zip(grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            ellipses = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            if not track.inside(ellipses, gray.shape[::-1], c["margin_px"]):
                return None
            predicted.append(ellipses)
        return self._fitted(grays, predicted, c["one_pass_move"])

    def _shifted(self, grays: list, T_pred: np.ndarray) -> Estimate | None:
        """After the prior failed: the marker sought in each view around where the prior
        (pose ``T_pred``) put it, by the correlation of its drawn appearance
        (:func:`~markerpose.stages.track.shift`), and the prior's rings, moved by what the
        search found, fitted and verified as a tracked frame's (to convergence). None
        where a view's search finds nothing like the marker or the fit fails."""
        mk, c = self.marker, self.conf["track"]
        if not c["shift_margin"]:
            return None
        moved = []
        for gray, cam, T in zip(grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            rings = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            found = self._timed("search", track.shift, gray, cam, T, mk, c["shift_margin"], rings)
            if found is None or found[1] < c["shift_min_score"]:
                return None
            ellipses = [((x + dx, y + dy), axes, angle) for ((x, y), axes, angle), (dx, dy) in zip(rings, found[0])]
            if not track.inside(ellipses, gray.shape[::-1], c["margin_px"]):
                return None
            moved.append(ellipses)
        return self._fitted(grays, moved, 0.0)

    def _fitted(self, grays: list, predicted: list, first_tol: float) -> Estimate | None:
        """Per view, the rings' edges fitted from ``predicted`` ellipses, verified, solved,
        gated on the reprojection error: the tracked estimate, or None."""
        c = self.conf["track"]
        found = self._timed("refine", self.refiner.from_ellipses, grays, list(self.rig.cameras), predicted, 1.0, False,
                            first_tol, self._noise[0])
        if any(det is None for det in found):
            return None
        reason = self._timed("verify", verify.rejection, self.rig, found, self.marker, self.conf["verify"], True)
        if reason is not None:
            return None
        est = self._solved(found, "tracked")
        return est if est is not None and est.residual_px <= c["max_residual_px"] else None

    def _cold(self, grays: list) -> Estimate | None:
        """Detection from scratch: propose, match, refine, verify, solve."""
        if self.proposer is None:
            return self._classical(grays)
        if self.ids != "stereo":  # one triple per view, by the ID head (paper) or the layout
            found = self._timed("propose", self.proposer.decoded, grays)
            for f, view in zip(found, verify.VIEWS):
                if f is None:
                    self._failed(f"stage 1 decoded no triple in the {view} view")
            return self._first_accepted(grays, [found] if found[0] is not None and found[1] is not None else [])
        if self._fits_left is None:  # else the frame's budget, of which a near look took a part
            self._budget()
        cand = None
        for zoom in self.proposer.looks():
            cand = self._timed("propose", self.proposer.candidates, grays, zoom, cand)
            est = self._from_candidates(grays, cand, zoom)
            if est is not None:
                return est
        return None

    def _from_candidates(self, grays: list, cand: list, zoom: float) -> Estimate | None:
        """Stage 1's candidates of both views (from the look ``zoom``) matched by the marker's
        3D shape, each triple refined and verified in turn, then the transfer fallback."""
        m = self.conf["match"]
        triples = self._timed("match", stereo_triples, self.rig, cand[0], cand[1], self.marker.points3d,
                              m["epipolar_tol"], m["shape_tol"], m["max_triples"])
        if not triples:
            self._failed(f"no triple of stage-1 candidates ({len(cand[0])} left, {len(cand[1])} right) "
                         "matches across the views with the marker's 3D shape")
        est = self._first_accepted(grays, [[(pl, s), (pr, s)] for pl, pr, s in triples], zoom)
        if est is None and m["transfer"]:
            est = self._transferred(grays, cand, zoom)
        return est

    def _near(self, grays: list, T_pred: np.ndarray) -> Estimate | None:
        """A cold detection whose stage 1 sees, in each view, only a window around where the
        prior put the marker (pose ``T_pred``; ``track.near_margin`` of the predicted
        marker's extent beyond it on each side), refining its best hypothesis only.

        It starts the frame's work budget (:meth:`_budget`), which the whole-image detection
        after it continues, so that a frame costs no more than :meth:`estimate` allows.
        None where it finds nothing, and without a look where it cannot help: the classical
        detector or a stage 1 that decodes one triple per view, ``near_margin`` 0, the
        predicted marker outside a view, or a window of three quarters of the input's
        height or more (the whole images are then hardly dearer)."""
        margin = self.conf["track"]["near_margin"]
        if self.proposer is None or self.ids != "stereo" or not margin:
            return None
        mk = self.marker
        w, h = look_size(1.0)
        centres, half = [], 0.0
        for gray, cam, T in zip(grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            ell = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            r = max(max(e[1]) for e in ell) / 2
            lo = np.min([e[0] for e in ell], axis=0) - r
            hi = np.max([e[0] for e in ell], axis=0) + r
            H, W = gray.shape
            if hi[0] < 0 or hi[1] < 0 or lo[0] > W - 1 or lo[1] > H - 1:  # predicted out of this view
                return None
            extent = (hi - lo) / (W / w, H / h)  # in stage 1's input, px
            half = max(half, float(extent.max()) * (0.5 + margin))
            centres.append(((lo + hi) / 2)[None])
        half = 8 * int(np.ceil(half / 8))  # the network's cells
        if 2 * half >= 0.75 * min(w, h):
            return None
        self._budget()
        left = self._fits_left
        self._fits_left = min(left, 1)
        try:
            cand = self._timed("propose", self.proposer.near, grays, centres, half)
            return self._from_candidates(grays, cand, 1.0)
        finally:
            self._fits_left = left - (min(left, 1) - self._fits_left)

    def _classical(self, grays: list) -> Estimate | None:
        """Paper §3.4: each view's ring triples, paired by the epipolar constraint, refined."""
        views = [self._timed("propose", propose.classical_view, g, self.marker, self.refiner.classical) for g in grays]
        pair = self._timed("match", match.pair_triples, self.rig, views[0][2:], views[1][2:], self.conf["match"]["pair_epipolar_tol"])
        if pair is None:
            counts = ", ".join(f"{len(v[3])} {name}" for v, name in zip(views, verify.VIEWS))
            self._failed(f"no pair of marker-like ring triples ({counts}) agrees with the epipolar geometry")
            return None
        il, ir, cl, cr = pair
        found = [self._timed("refine", self.refiner.triple, v, tri, cost, cam) for v, tri, cost, cam in zip(views, (il, ir), (cl, cr), self.rig.cameras)]
        for det, view in zip(found, verify.VIEWS):
            if not det.refined.all():
                self._failed(f"the blurred-ring fit and the edge fit disagree in the {view} view")
                return None
        return self._solved(found)

    def _fit(self, fn, *args):
        """One hypothesis refined (``fn(*args)``), charged to the cold detection's work
        budget (``match.max_fits``); None, with the reason, once it is spent."""
        if self._fits_left is not None:
            if self._fits_left <= 0:
                self._failed(f"work budget: {self.conf['match']['max_fits']} hypotheses refined, none accepted")
                return None
            self._fits_left -= 1
        return self._timed("refine", fn, *args)

    def _gates(self, zoom: float | None) -> tuple:
        """The refine stage's evidence gates (blur, mask) for hypotheses of the look
        ``zoom`` (:meth:`~markerpose.stages.refine.Refiner.__call__`); None without a look.
        The mask gate passes rings under ``MASK_GATE_MIN_PX`` across in the look's input:
        stage 1 places those too far off, relative to their size, for the evidence at its
        points to tell."""
        m = self.conf["match"]
        if zoom is None:
            return None, None

        def evidence(gray, pts):
            return self._timed("verify", self.proposer.evidence, gray, np.asarray(pts)[None], zoom)[0]

        def small(gray, pts):
            return ring_diameter(pts, self.marker) * look_size(zoom)[0] / gray.shape[1] < MASK_GATE_MIN_PX

        blur = (lambda gray, pts: bool(evidence(gray, pts) >= m["blur_min_evidence"])) if m["blur_min_evidence"] else None
        mask = (lambda gray, pts: small(gray, pts) or bool(evidence(gray, pts) >= m["mask_min_evidence"])) if m["mask_min_evidence"] else None
        return blur, mask

    def _first_accepted(self, grays: list, hypotheses: list, zoom: float | None = None) -> Estimate | None:
        """Each hypothesis (points of both views) refined and verified in turn: the first
        estimate that passes, or None. With the ``zoom`` of the look that found them, the
        costly refinements need ring evidence first (:meth:`_gates`)."""
        gates = self._gates(zoom)
        for points in hypotheses:
            found = self._fit(self.refiner, grays, list(self.rig.cameras), points, *gates)
            if found is None:
                return None
            est = self._accepted(found)
            if est is not None:
                return est
        return None

    def _accepted(self, found: list) -> Estimate | None:
        """The estimate from refined detections of both views if they pass verification."""
        reason = self._timed("verify", verify.rejection, self.rig, found, self.marker, self.conf["verify"], self.refiner.edge_refit)
        if reason is not None:
            self._failed(reason)
            return None
        return self._solved(found)

    def _solved(self, found: list, source: str = "detected") -> Estimate | None:
        """Solve, then reject points that do not have the marker's shape (a wrong triple)."""
        est = self._timed("solve", solve.solve, self.rig, self.marker, found[0], found[1], self.conf["solve"], source)
        if verify.shape(est.points3d, self.marker, self.conf["verify"]):
            return est
        self._failed(f"shape check: the triangulated centres are {verify.shape_error(est.points3d, self.marker.points3d):.2f} mm "
                     f"from the marker's layout (limit {self.conf['verify']['max_shape_error']:g} mm)")
        return None

    def _transferred(self, grays: list, cand: list, zoom: float) -> Estimate | None:
        """Recover a marker one camera sees too steeply for stage 1 to place its rings within
        the matching tolerances: when triples match loosely, one view's triple is refined
        and, if its rings fit a plate pose, carried into the other view by that pose
        (:func:`~markerpose.stages.match.transfer`), whose predicted ellipses are fitted
        on the image's edges (or, failing that, refined at the predicted centres) and
        verified like any matched triple. Sources whose ring evidence is under
        ``transfer_min_evidence`` are skipped."""
        m, cams, mk = self.conf["match"], self.rig.cameras, self.marker
        loose = self._timed("match", stereo_triples, self.rig, cand[0], cand[1], mk.points3d,
                            m["transfer_epipolar_tol"], m["transfer_shape_tol"], m["transfer_attempts"])
        if not loose:  # no sign of the marker in both views (the common case without it): stop
            return None
        sources = transfer_sources(loose, cand, mk.centers2d, m["view_triples"])
        blur_gate = self._gates(zoom)[0]
        if m["transfer_min_evidence"]:  # one evidence look per view for all of its sources
            keep = np.ones(len(sources), bool)
            for view in (0, 1):
                idx = [k for k, (a, _, _) in enumerate(sources) if a == view]
                if idx:
                    ev = self._timed("verify", self.proposer.evidence, grays[view], np.stack([sources[k][1] for k in idx]), zoom)
                    keep[idx] = ev >= m["transfer_min_evidence"]
            sources = [u for u, k in zip(sources, keep) if k]
        for a, pts, s in sources[: m["transfer_sources"]]:
            b = 1 - a
            det_a = self._fit(self.refiner, [grays[a]], [cams[a]], [(pts, s)], blur_gate)
            if det_a is None:
                return None
            det_a = det_a[0]
            poses = verify.plate_poses(det_a, cams[a], mk, self.conf["verify"]["plate_tol"])
            for pred, T_b in transfer(self.rig, a, poses, mk.points3d):
                # Cheap first: the other view must show ring evidence where the pose puts the
                # rings (an inconsistent pair, e.g. one view given twice, does not), before
                # any costly fit there.
                gate = m["transfer_min_evidence"]
                if gate and self._timed("verify", self.proposer.evidence, grays[b], pred[None], zoom)[0] < gate:
                    continue
                # The pose predicts the rings' ellipses in the other view to within a pixel
                # or so: their edges are fitted from there first; the usual refinement at
                # the predicted centres can be led to a neighbouring ring by a steep,
                # blurred view. On seeds where no edge fitted, the blurred-ring fit runs
                # only when the source view's rings needed it too (the cameras expose
                # together: the marker's motion blurs both views or neither), when its
                # coarse search finds blur, and with ring evidence (blur_gate).
                ellipses = ring_ellipses(cams[b], T_b, mk.points3d, mk.outer_radius)
                guided = self._timed("refine", self.refiner.from_ellipses, [grays[b]], [cams[b]], [ellipses], s, det_a.blur_px > 0,
                                     0.0, None, blur_gate)[0]
                if guided is not None and (est := self._accepted([det_a, guided][:: 1 - 2 * a])) is not None:
                    return est
                det_b = self._fit(self.refiner, [grays[b]], [cams[b]], [(pred, s)], blur_gate)
                if det_b is None:
                    return None
                est = self._accepted([det_a, det_b[0]][:: 1 - 2 * a])  # (left, right)
                if est is not None:
                    return est
        return None

__all__ = ["MarkerPose"]
