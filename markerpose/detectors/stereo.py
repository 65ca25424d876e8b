"""The stereo detector (ours, the default): stage-1 candidates of both views matched by the
marker's 3D shape.

Each look of stage 1 (:meth:`~markerpose.stages.propose.NeuralProposer.looks`) gives every
view a handful of candidates; triples of them that triangulate to the marker's shape
(:func:`~markerpose.stages.match.stereo_triples`) are refined in turn. The costly
refinements need ring evidence first (:meth:`StereoDetector.gates`). When no matched
triple passes, one view's refined rings are carried into the other by their pose
(:meth:`StereoDetector.transferred`). A cold detection refines at most ``match.max_fits``
hypotheses (a bounded worst case on an inconsistent pair).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..frame import Frame
from ..geometry import ring_diameter, ring_ellipses
from ..keypoints import look_size
from ..results import Detection
from ..stages import match, verify
from ..stages.match import matched_triples, stereo_triples, transfer, transfer_sources
from .base import NeuralDetector

MASK_GATE_MIN_PX = 16.0  # ring diameter in stage 1's input from which the mask gate applies


def _NO_MASKS(grays, points, views) -> list:  # a mask gate that refuses every view
    return []


class StereoDetector(NeuralDetector):
    """Stage-1 candidates matched across the views by the marker's 3D shape."""

    name = "stereo"

    def pairs(self, frame: Frame) -> Iterator[list[Detection]]:
        if frame.fits_left is None:  # else the frame's budget, of which a near look took a part
            self.start_budget(frame)
        cand = None
        for zoom in self.proposer.looks():
            # The second look resolves rings too small for the first; where the first already
            # fitted one view's rings to the plate, resolution is not what failed, and where
            # the first spent the budget, none of its hypotheses could be refined.
            if cand is not None and (frame.plate_seen or frame.spent or not self.proposer.worth_second_look(cand)):
                return
            look = self.look(frame, zoom, cand)
            cand = frame.unclaimed(look)
            yield from self.from_candidates(frame, cand, zoom, look)

    def look(self, frame: Frame, zoom: float, previous: list | None) -> list:
        """Stage 1's candidates of the look ``zoom`` (:meth:`~markerpose.stages.propose.NeuralProposer.candidates`),
        made once per call for every tool that asks with the same ``previous`` look."""
        key = ("look", zoom, None if previous is None else tuple(self.proposer.near_key(p) for p in previous))
        # The images' noise (what the edge fits need next) is estimated on each view's
        # thread from the residuals its input's pass counted, beside the other view's
        # network, not after both.
        return frame.shared(
            key, frame.timed, "propose", self.proposer.candidates, frame.grays, zoom, previous, frame.looked, frame.estimate_noise
        )

    def first(self, frame: Frame) -> tuple | None:
        """What :meth:`pairs` refines first, for refining it in one batch with other tools'
        (:meth:`markerpose.stages.refine.Refiner.layouts_of`): (per view (centres (3, 2),
        score), the blurred-ring fits' limits), with the frame's budget started; None where
        the first look matches no triple, or this refine stage does not start from the
        layout's ellipses."""
        if not (self.refiner.edge_refit and self.refiner.conf["layout_seed"]):
            return None
        if frame.fits_left is None:
            self.start_budget(frame)
        look = self.look(frame, 1.0, None)
        triples = self.triples(frame, frame.unclaimed(look), look)
        if not triples:
            return None
        pl, pr, s = triples[0]
        return [(pl, s), (pr, s)], self.gates(frame, 1.0)[0]

    def triples(self, frame: Frame, cand: list, look: list | None = None) -> list:
        """The candidates' triples that match across the views by the marker's 3D shape,
        best first (:func:`~markerpose.stages.match.stereo_triples`). ``cand`` is ``look`` (a
        look's candidates, per view) without the candidates other tools' rings claimed:
        the triples are the look's, matched once per call, without those holding a claimed
        candidate (:func:`~markerpose.stages.match.matched_triples`)."""
        m = self.conf["match"]
        look = cand if look is None else look

        def matched():
            found = frame.timed(
                "match", matched_triples, self.rig, look[0], look[1], self.marker.points3d, m["epipolar_tol"], m["shape_tol"]
            )
            return look, found  # the arrays kept with their triples: their ids are not reused while the call lasts

        pl, pr, score, il, ir = frame.shared(("triples", self.marker.name, id(look[0]), id(look[1])), matched)[1]
        if cand is not look:
            keep_l, keep_r = frame.unclaimed_masks(look)
            ok = keep_l[il].all(1) & keep_r[ir].all(1) if len(score) else np.zeros(0, bool)
            pl, pr, score = pl[ok], pr[ok], score[ok]
        return [(pl[n], pr[n], float(score[n])) for n in range(min(len(score), m["max_triples"]))]

    def from_candidates(self, frame: Frame, cand: list, zoom: float, look: list | None = None) -> Iterator[list[Detection]]:
        """Stage 1's candidates of both views (from the look ``zoom``; ``cand`` those of
        ``look`` that no other tool claimed) matched by the marker's 3D shape, each triple
        refined in turn, then the transfer fallback."""
        m = self.conf["match"]
        triples = self.triples(frame, cand, look)
        if not triples:
            frame.failed(
                f"no triple of stage-1 candidates ({len(cand[0])} left, {len(cand[1])} right) "
                "matches across the views with the marker's 3D shape"
            )
        gates = self.gates(frame, zoom)
        for pl, pr, s in triples:
            found = self.fit(frame, frame.grays, list(self.rig.cameras), [(pl, s), (pr, s)], *gates)
            if found is None:
                break
            if m["transfer"]:
                yield from self.completed(frame, found, s, zoom, gates[0])
            yield found
            if not frame.plate_seen:  # the pair was refused: did a view's rings fit the plate?
                frame.plate_seen = any(
                    d is not None and bool(d.refined.all()) and bool(verify.plate_poses(d, cam, self.marker, verify.PLATE_TOL))
                    for d, cam in zip(found, self.rig.cameras)
                )
        if m["transfer"]:
            yield from self.transferred(frame, cand, zoom)

    def completed(self, frame: Frame, found: list, s: float, zoom: float, blur_gate) -> Iterator[list[Detection]]:
        """A matched triple whose rings refined in one view only, completed in the other
        by the refined view's plate pose (:meth:`_guided`), before the pair itself is
        judged: stage 1 can match a steep, blurred view's points well enough to pass the
        matching but too far off for their rings to refine, and the pair would cost
        another hypothesis; the transfer fallback comes only after all of them. Nothing
        where both views or neither refined."""
        ok = [d is not None and bool(d.refined.all()) for d in found]
        if ok[0] == ok[1]:
            return
        a = 0 if ok[0] else 1
        for _, T_b in self._predicted(frame, a, found[a], zoom):
            guided = self._guided(frame, 1 - a, T_b, s, found[a], blur_gate)
            if guided is not None:
                yield [found[a], guided][:: 1 - 2 * a]  # (left, right)

    def _predicted(self, frame: Frame, a: int, det_a: Detection, zoom: float) -> Iterator[tuple]:
        """(the rings' centres (3, 2), the pose T_b) in the other view for each of view
        ``a``'s plate poses of ``det_a``, where that view shows ring evidence there
        (``transfer_min_evidence``)."""
        cams, mk, b = self.rig.cameras, self.marker, 1 - a
        gate = self.conf["match"]["transfer_min_evidence"]
        poses = verify.plate_poses(det_a, cams[a], mk, verify.PLATE_TOL)
        frame.plate_seen |= bool(poses)
        for pred, T_b in transfer(self.rig, a, poses, mk.points3d):
            # Cheap first: the other view must show ring evidence where the pose puts the
            # rings (an inconsistent pair, e.g. one view given twice, does not), before any
            # costly fit there.
            if gate and frame.timed("verify", self.proposer.evidence, frame.grays[b], pred[None], zoom, frame.looked)[0] < gate:
                continue
            yield pred, T_b

    def near(self, frame: Frame, T_pred: np.ndarray) -> Iterator[list[Detection]]:
        """A cold detection whose stage 1 sees, in each view, only a window around where the
        prior put the marker (pose ``T_pred``; ``track.near_margin`` of the predicted
        marker's extent beyond it on each side), refining its best hypothesis only.

        It starts the frame's work budget, which the whole-image detection after it
        continues, so that a frame costs no more than a cold detection allows. Nothing
        where it cannot help: ``near_margin`` 0, the predicted marker outside a view, or a
        window of three quarters of the input's height or more (the whole images are then
        hardly dearer)."""
        margin = self.conf["track"]["near_margin"]
        if not margin:
            return
        mk = self.marker
        w, h = self.proposer.look_size(1.0, frame.grays[0].shape)
        centres, half = [], 0.0
        for gray, cam, T in zip(frame.grays, self.rig.cameras, (T_pred, self.rig.T_right_left @ T_pred)):
            ell = ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            r = max(max(e[1]) for e in ell) / 2
            lo = np.min([e[0] for e in ell], axis=0) - r
            hi = np.max([e[0] for e in ell], axis=0) + r
            H, W = gray.shape
            if hi[0] < 0 or hi[1] < 0 or lo[0] > W - 1 or lo[1] > H - 1:  # predicted out of this view
                return
            extent = (hi - lo) / (W / w, H / h)  # in stage 1's input, px
            half = max(half, float(extent.max()) * (0.5 + margin))
            centres.append(((lo + hi) / 2)[None])
        half = 8 * int(np.ceil(half / 8))  # the network's cells
        if 2 * half >= 0.75 * min(w, h):
            return
        self.start_budget(frame)
        left = frame.fits_left
        frame.fits_left = min(left, 1)
        try:
            cand = frame.timed("propose", self.proposer.near, frame.grays, centres, half, frame.looked)
            yield from self.from_candidates(frame, cand, 1.0)
        finally:
            frame.fits_left = left - (min(left, 1) - frame.fits_left)

    def gates(self, frame: Frame, zoom: float) -> tuple:
        """The refine stage's evidence gates (blur, mask) for hypotheses of the look ``zoom``
        (:meth:`~markerpose.stages.refine.Refiner.__call__`).

        The mask gate keeps a view whose ring evidence reaches ``mask_min_evidence``, and one
        whose rings are under ``MASK_GATE_MIN_PX`` across in the look's input (stage 1 places
        those too far off, relative to their size, for the evidence at its points to tell)
        where the hypothesis has a hold in another view: its rings fitted from the layout
        there, or its evidence passed. A triple with no evidence in any view is clutter
        matched across the views (one view given twice matches its own clutter), not worth
        the masks in either."""
        m = self.conf["match"]

        def evidence(gray, pts):
            return frame.timed("verify", self.proposer.evidence, gray, np.asarray(pts)[None], zoom, frame.looked)[0]

        def small(gray, pts):
            return ring_diameter(pts, self.marker) * look_size(zoom)[0] / gray.shape[1] < MASK_GATE_MIN_PX

        def mask(grays, points, views):
            seen = [k for k in views if bool(evidence(grays[k], points[k][0]) >= m["mask_min_evidence"])]
            held = bool(seen) or any(p is not None and k not in views for k, p in enumerate(points))
            return [k for k in views if k in seen or (held and small(grays[k], points[k][0]))]

        blur = (lambda gray, pts: bool(evidence(gray, pts) >= m["blur_min_evidence"])) if m["blur_min_evidence"] else None
        return blur, (mask if m["mask_min_evidence"] else None)

    def transferred(self, frame: Frame, cand: list, zoom: float) -> Iterator[list[Detection]]:
        """Recover a marker one camera sees too steeply for stage 1 to place its rings within
        the matching tolerances: when triples match loosely, one view's triple is refined
        and, if its rings fit a plate pose, carried into the other view by that pose
        (:func:`~markerpose.stages.match.transfer`), whose predicted ellipses are fitted
        on the image's edges (or, failing that, refined at the predicted centres). Sources
        whose ring evidence is under ``transfer_min_evidence`` are skipped."""
        m, cams, mk, grays = self.conf["match"], self.rig.cameras, self.marker, frame.grays
        loose = frame.timed(
            "match",
            stereo_triples,
            self.rig,
            cand[0],
            cand[1],
            mk.points3d,
            match.TRANSFER_EPIPOLAR_TOL,
            match.TRANSFER_SHAPE_TOL,
            match.TRANSFER_ATTEMPTS,
        )
        if not loose:  # no sign of the marker in both views (the common case without it): stop
            return
        sources = transfer_sources(loose, cand, mk.centers2d, match.VIEW_TRIPLES)
        blur_gate = self.gates(frame, zoom)[0]
        gate = m["transfer_min_evidence"]
        if gate:
            sources = self._evidenced(frame, sources, zoom, gate)
        no_masks = None if m["transfer_masks"] else _NO_MASKS
        for a, pts, s in sources[: match.TRANSFER_SOURCES]:
            b = 1 - a
            det_a = self.fit(frame, [grays[a]], [cams[a]], [(pts, s)], blur_gate, no_masks)
            if det_a is None:
                return
            det_a = det_a[0]
            for pred, T_b in self._predicted(frame, a, det_a, zoom):
                guided = self._guided(frame, b, T_b, s, det_a, blur_gate)
                if guided is not None:
                    yield [det_a, guided][:: 1 - 2 * a]  # (left, right)
                det_b = self.fit(frame, [grays[b]], [cams[b]], [(pred, s)], blur_gate, no_masks)
                if det_b is None:
                    return
                yield [det_a, det_b[0]][:: 1 - 2 * a]

    def _evidenced(self, frame: Frame, sources: list, zoom: float, gate: float) -> list:
        """The transfer ``sources`` (view, points (3, 2), score) whose ring evidence reaches
        ``gate``: one evidence look per view for all of its sources."""
        grays = frame.grays
        keep = np.ones(len(sources), bool)
        for view in (0, 1):
            idx = [k for k, (a, _, _) in enumerate(sources) if a == view]
            if idx:
                ev = frame.timed("verify", self.proposer.evidence, grays[view], np.stack([sources[k][1] for k in idx]), zoom, frame.looked)
                keep[idx] = ev >= gate
        return [u for u, k in zip(sources, keep) if k]

    def _guided(self, frame: Frame, b: int, T_b: np.ndarray, s: float, det_a: Detection, blur_gate) -> Detection | None:
        """The rings of view ``b`` fitted on its edges from the ellipses that the pose ``T_b``
        (view b's camera frame) predicts there, or None.

        The pose predicts the rings' ellipses in the other view to within a pixel or so:
        their edges are fitted from there first; the usual refinement at the predicted
        centres can be led to a neighbouring ring by a steep, blurred view. On seeds where
        no edge fitted, the blurred-ring fit runs only when the source view's rings
        (``det_a``) needed it too (the cameras expose together: the marker's motion blurs
        both views or neither), when its coarse search finds blur, and with ring evidence
        (``blur_gate``)."""
        cams, mk, grays = self.rig.cameras, self.marker, frame.grays
        ellipses = ring_ellipses(cams[b], T_b, mk.points3d, mk.outer_radius)
        return frame.timed(
            "refine",
            self.refiner.from_ellipses,
            frame,
            [grays[b]],
            [cams[b]],
            [ellipses],
            s,
            det_a.blur_px > 0,
            0.0,
            None,
            blur_gate,
        )[0]


__all__ = ["MASK_GATE_MIN_PX", "StereoDetector"]
