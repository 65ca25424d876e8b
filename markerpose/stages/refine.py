"""Refine: sub-pixel ring centres and outer ellipses near the proposed points.

- ``"ellipsegnet"`` (the paper's stage 2, :mod:`markerpose.ellipses`): a patch around
  each point (the paper's fixed 120 px, or ours: 1.8 ring diameters resampled to
  120x120), the ring's mask, its centre (the paper's ``cv2.fitEllipse``, or ours: the
  mask's sub-pixel iso-line). With ``edge_refit`` (ours) the ring's outer edge is then
  fitted in the image itself from the mask's ellipse (:func:`classical.refine_ellipses`),
  and only edge-fitted centres count as refined. With ``layout_seed`` as well (ours) the
  edges are first fitted from the ellipses the three points' layout predicts, and the
  network runs only for views where that fails.
- ``"classical"``: the classical sub-pixel ring fit near each point
  (:func:`classical.refine_points`).
- ``"none"``: the proposed points as they are (~1 px).

Every sub-pixel edge fit ends, when the edges are smeared by motion to near the black
band's width, with the three rings refitted together under a model of box-blurred rings
(``blur_fit``, ours; :func:`classical.refine_blurred`, :mod:`markerpose.blurfit`). The
classical detector's own triples are refined by :meth:`Refiner.triple`.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from .. import camera, classical, edges, geometry, jit
from ..ellipses import FITS, PATCH_MODES
from ..frame import Frame
from ..geometry import cq_to_rect, layout_affine
from ..marker import Marker
from ..results import Detection
from ..settings import choice, flag, number, path

default_conf = {
    "method": "ellipsegnet",  # "ellipsegnet" (paper's stage 2), "classical" or "none"
    "weights": None,  # ellipsegnet: weights file (None: the shipped one)
    "patch": "adaptive",  # ellipsegnet: "adaptive" window (ours) or "fixed" 120 px (paper)
    "fit": "subpixel",  # ellipsegnet: "subpixel" iso-line (ours), "ellipse" (paper), "moments"
    "edge_refit": True,  # ellipsegnet: fit the outer edge in the image from the mask's ellipse (ours)
    "layout_seed": True,  # with edge_refit: first fit the edges from the ellipses the three
    #                       points' layout predicts, EllipSegNet only for views where that
    #                       fails (ours: the network's masks are then rarely needed)
    "subpixel": True,  # classical fits: sub-pixel edges (False: the paper's contour ellipse)
    "blur_fit": True,  # sub-pixel fits: refit motion-blurred rings under a blur model (ours)
    "blur_blocks": True,  # ... the fit's samples (block means) modelled as means (ours; False: as
    #                       their centres: cheaper, and start-dependent at sharp edges)
    "blur_tangents": True,  # ... its lines across the motion smoothed near the rings' tangents
    #                         (ours; False: bare lines, whose chords open as square roots there:
    #                         a cost with cusps, more iterations, start-dependent fits)
    "blur_width": 0.4,  # ... due when the widest outer edge's 10-90 % width exceeds this fraction
    #                     of the smallest minor semi-axis (0.3: before blurred neighbours reach
    #                     into the edge fit's rays, but a shadow's edge can then send sharp rings
    #                     to a motion model that cannot explain it; design §4)
    "blur_long_width": 0.3,  # ... or this fraction, where that width is also at least
    "blur_long_px": 7.5,  # ... this many px (about 10 px of motion blur, which the edge fit
    #                       loses to the model whatever the rings' size; shorter blur on
    #                       foreshortened rings, or a shadow's edge, stays with the edge fit;
    #                       0: no such rule; design §4) ...
    "blur_long_even": 0.6,  # ... and where the edges' widths are uneven around the rings (the
    #                         25th percentile at most this fraction of the 75th, the rings'
    #                         median): motion widens the edges along it only, defocus or
    #                         resampling all of them alike (1: any edges)
    "track_blur_width": 0.4,  # ... the same for the rings a tracker predicted or searched near
    #                           its prediction, without the rule for long blur: the fit is the
    #                           costliest step of a tracked frame, whose budget is the stream's
    #                           frame interval
    "max_blur_fits": 4,  # blur-model fits (one per view) per cold detection: the costliest
    #                      refinement; two hypotheses of a blurred pair (both views) need four
    "plate_edge": True,  # sub-pixel fits: leave out what the plate's blurred edge reaches (ours;
    #                      plates tight around the rings: classical.plate_sides)
}
METHODS = ("ellipsegnet", "classical", "none")
RULES = {
    "method": choice(*METHODS),
    "weights": path(),
    "patch": choice(*PATCH_MODES),
    "fit": choice(*FITS),
    "edge_refit": flag(),
    "layout_seed": flag(),
    "subpixel": flag(),
    "blur_fit": flag(),
    "blur_blocks": flag(),
    "blur_tangents": flag(),
    "blur_width": number(0.0, above=True),
    "blur_long_width": number(0.0, above=True),
    "blur_long_px": number(0.0),
    "blur_long_even": number(0.0, 1.0),
    "track_blur_width": number(0.0, above=True),
    "max_blur_fits": number(0, integer=True),
    "plate_edge": flag(),
}


class Refiner:
    """The refine stage with its network (if any).

    Args:
        conf: :data:`default_conf` with overrides.
        marker: the marker's geometry.
        neural: whether the points come from stage 1 (False: the classical detector, which
            only uses :meth:`triple`).
    """

    def __init__(self, conf: dict, marker: Marker, neural: bool = True, threads: int | None = None, backend: str = "onnxruntime"):
        if conf["method"] not in METHODS:
            raise ValueError(f"unknown refine method {conf['method']!r}; choose from {METHODS}")
        self.conf, self.marker = conf, marker
        self.classical = {  # settings of the classical fits
            "blur_fit": bool(conf["blur_fit"]),
            "blur_fit_blocks": bool(conf["blur_blocks"]),
            "blur_fit_tangents": bool(conf["blur_tangents"]),
            "blur_fit_width": float(conf["blur_width"]),
            "blur_fit_long_width": float(conf["blur_long_width"]),
            "blur_fit_long_px": float(conf["blur_long_px"]),
            "blur_fit_long_even": float(conf["blur_long_even"]),
            "plate_edge": bool(conf["plate_edge"]),
        }
        # Compiled now, not in a stream's first frames (a live tracker would stall on them).
        steps = [edges.warm_up, camera.warm_up, geometry.warm_up, classical.warm_up]
        if conf["blur_fit"]:
            from .. import blurfit

            steps.append(blurfit.warm_up)
        jit.warm_up(*steps)
        self.net = None
        if neural and conf["method"] == "ellipsegnet":
            from ..ellipses import EllipseNet

            self.net = EllipseNet(conf["weights"], {"patch": conf["patch"], "fit": conf["fit"]}, threads=threads, backend=backend)
        # EllipSegNet's ellipses refitted on the image's edges (the moments fit has no ellipse).
        self.edge_refit = self.net is not None and bool(conf["edge_refit"]) and conf["fit"] != "moments"
        # Whether refined detections carry the rings' ellipses (what the plate check needs).
        self.gives_ellipses = self.edge_refit or conf["method"] == "classical"

    def for_marker(self, marker: Marker) -> Refiner:
        """This refine stage for another marker's rings, sharing its network."""
        other = copy.copy(self)
        other.marker = marker
        return other

    def __call__(self, frame: Frame, grays: list, cameras: list, points: list, blur_gate=None, mask_gate=None) -> list:
        """Per view, the Detection near (points (3, 2), score), or None where None is given.

        ``frame``: the call's context (the images' noise, the budget of blurred-ring fits).
        Gates (None: none): ``blur_gate``, a test ``(gray, points (3, 2)) -> bool`` that a
        view's rings must pass before their blurred-ring fit (:class:`~markerpose.classical.BlurLimits`);
        ``mask_gate``, ``(grays, points, views) -> views``: which of the views whose layout
        seeds did not fit go on to EllipSegNet's masks (a decoy's triple is not worth the
        network's cost).
        """
        conf, limits = self.classical, classical.BlurLimits(frame.blur_fits, blur_gate)
        if self.net is not None:
            return self._ellipsegnet(frame, grays, cameras, points, limits, mask_gate)
        out = []
        for gray, cam, found in zip(grays, cameras, points):
            if found is None:
                out.append(None)
                continue
            pts, score = found
            if self.conf["method"] == "none":
                out.append(Detection(centers=pts, score=score, refined=np.zeros(3, bool)))
                continue
            centers, ok, ellipses, blur, cov = classical.refine_points(
                gray,
                pts,
                self.marker,
                subpixel=self.conf["subpixel"],
                conf=conf,
                camera=cam,
                detail=True,
                noise=frame.noises([gray])[0],
                limits=limits,
            )
            out.append(Detection(centers=centers, ellipses=ellipses, score=score, refined=ok, blur_px=blur, center_cov=cov))
        return out

    def layout_ellipses(self, points: np.ndarray, marker: Marker | None = None) -> list | None:
        """The rings' outer ellipses (RotatedRects) that three ring centres (3, 2) of
        ``marker`` (None: this stage's) imply: the affine map of the marker's layout onto
        them takes each ring's circle to an ellipse (perspective across the plate is small);
        None for a degenerate triple."""
        marker = self.marker if marker is None else marker
        (a, b), (c, d) = layout_affine(np.asarray(points, np.float64), marker.centers2d).tolist()
        r2 = marker.outer_radius**2
        m00, m01, m11 = (a * a + b * b) * r2, (a * c + b * d) * r2, (c * c + d * d) * r2  # M = A A^T r^2: x = p + A r u, |u| = 1
        det = m00 * m11 - m01 * m01
        if not (math.isfinite(det) and det > 1e-9):
            return None
        Q = np.array([[m11, -m01], [-m01, m00]]) / det  # M^-1
        return [cq_to_rect(np.asarray(p, np.float64), Q) for p in points]

    def _ellipsegnet(self, frame: Frame, grays: list, cameras: list, points: list, limits, mask_gate=None) -> list:
        """:meth:`__call__` with EllipSegNet: with ``layout_seed``, the edges fitted from the
        layout's ellipses first; EllipSegNet's masks for the views where they did not fit
        (those of them that ``mask_gate`` keeps)."""
        seen = [k for k, f in enumerate(points) if f is not None]
        out = [None] * len(grays)
        if self.edge_refit and self.conf["layout_seed"]:
            self._from_layout(frame, grays, cameras, points, seen, limits, out)
            seen = [k for k in seen if out[k] is None]
            if seen and mask_gate is not None:
                seen = mask_gate(grays, points, seen)
            if not seen:
                return out
        self._from_masks(frame, grays, cameras, points, seen, limits, out)
        return out

    def _from_layout(self, frame: Frame, grays: list, cameras: list, points: list, seen: list, limits, out: list) -> None:
        """Into ``out``, per view of ``seen``, the Detection whose three rings' edges fit
        from the layout's ellipses (both views in one batch); no blur fit on seeds that
        found no ring (the masks' ellipses get their turn). Where this hypothesis was
        refined already, in one batch with other tools' (:meth:`layouts_of`), that is
        taken instead, its blurred-ring fits charged to ``limits``' budget."""
        kept = frame.prelaid(self.marker.name, points) if len(seen) == len(points) else None
        if kept is not None:
            out[:], fits = kept
            if limits.budget is not None:
                limits.budget.left -= fits
            return
        self._layouts(frame, grays, cameras, [(self.marker, points, limits, seen, out)])

    def layouts_of(self, frame: Frame, grays: list, cameras: list, items: list) -> list:
        """:meth:`_from_layout` of several tools' hypotheses in the same views, in one batch:
        ``items`` are (marker, per view (centres (3, 2), score), the blurred-ring fits'
        :class:`~markerpose.classical.BlurLimits`); per item, per view a Detection or None."""
        outs = [[None] * len(grays) for _ in items]
        self._layouts(frame, grays, cameras, [(mk, pts, lim, range(len(grays)), o) for (mk, pts, lim), o in zip(items, outs)])
        return outs

    def _layouts(self, frame: Frame, grays: list, cameras: list, jobs: list) -> None:
        """The edge fits of ``jobs`` (marker, per view (centres, score), BlurLimits, the views
        to fit, out) from their layouts' ellipses, in one batch: into each job's ``out``, per
        view to fit, the Detection where all three rings refined."""
        batch = []  # (job, view, seeds)
        for job in jobs:
            mk, points, _, seen, _ = job
            for k in seen:
                seeds = self.layout_ellipses(points[k][0], mk)
                if seeds is not None:
                    batch.append((job, k, seeds))
        if not batch:
            return
        fits = classical.refine_ellipses_views(
            [grays[k] for _, k, _ in batch],
            [seeds for _, _, seeds in batch],
            self.marker,
            {**self.classical, "blur_fit_unrefined": False},
            [cameras[k] for _, k, _ in batch],
            frame.noises([grays[k] for _, k, _ in batch]),
            detail=True,
            limits=[job[2] for job, _, _ in batch],
            markers=None if all(job[0] is self.marker for job in jobs) else [job[0] for job, _, _ in batch],
        )
        for (job, k, _), (centers, ok, ellipses, blur, cov) in zip(batch, fits):
            if ok.all():
                job[4][k] = Detection(centers=centers, ellipses=ellipses, score=job[1][k][1], refined=ok, blur_px=blur, center_cov=cov)

    def _from_masks(self, frame: Frame, grays: list, cameras: list, points: list, seen: list, limits, out: list) -> None:
        """Into ``out``, per view of ``seen``, the Detection from EllipSegNet's masks (all
        patches of all views in one batch), with ``edge_refit`` their ellipses refitted on
        the image's edges (all views in one batch)."""
        conf = self.classical
        refined = self.net([grays[k] for k in seen], [points[k][0] for k in seen], self.marker, with_ellipses=self.edge_refit)
        fits = [None] * len(seen)
        if self.edge_refit:  # the image's edges, from the masks' ellipses (all views in one batch)
            fits = classical.refine_ellipses_views(
                [grays[k] for k in seen],
                [f[2] for f in refined],
                self.marker,
                conf,
                [cameras[k] for k in seen],
                frame.noises([grays[k] for k in seen]),
                detail=True,
                limits=limits,
            )
        for k, found, fit in zip(seen, refined, fits):
            centers, ok = found[0], found[1]
            ellipses, blur, cov = None, 0.0, None
            if fit is not None:
                c2, ok2, ellipses, blur, cov = self._mended(frame, grays[k], cameras[k], centers, fit, limits)
                # Only edge-fitted centres count as refined: a mask's centre can be
                # pixels off, and a pose from it is wrong by a millimetre.
                centers, ok = np.where(ok2[:, None], c2, centers), ok2
            out[k] = Detection(centers=centers, ellipses=ellipses, score=points[k][1], refined=ok, blur_px=blur, center_cov=cov)

    def _mended(self, frame: Frame, gray: np.ndarray, camera, centers: np.ndarray, fit: tuple, limits) -> tuple:
        """The edge refit ``fit`` = (centres (3, 2), refined (3,), ellipses, blur px, covariances) of a
        view's masks, where a ring's mask was poor (not refined) the classical ring fit
        near its mask's centre (``centers`` (3, 2)) instead."""
        c2, ok2, ellipses, blur, cov = fit
        if not ok2.all():  # a poor mask: the classical ring fit near the point instead
            c3, ok3, e3, b3, cov3 = classical.refine_points(
                gray,
                centers,
                self.marker,
                conf=self.classical,
                camera=camera,
                detail=True,
                noise=frame.noises([gray])[0],
                limits=limits,
            )
            c2, blur = np.where(ok2[:, None], c2, c3), max(blur, b3)
            ellipses = [e if o else f for e, o, f in zip(ellipses, ok2, e3)]
            cov = np.where(ok2[:, None, None], cov, cov3)
            ok2 = ok2 | ok3
        return c2, ok2, ellipses, blur, cov

    def from_ellipses(
        self,
        frame: Frame,
        grays: list,
        cameras: list,
        ellipses: list,
        score: float,
        blur_unrefined: bool = True,
        first_tol: float = 0.0,
        noises: list | None = None,
        blur_gate=None,
        tracked: bool = False,
    ) -> list:
        """The rings' edges fitted from predicted outer ellipses (the transfer, tracking),
        all views in one batch: per view a Detection when all three refine, else None.
        ``blur_unrefined=False``: no blur fit when the edge fit found none of the rings (a
        prediction that missed them). ``first_tol``: the edge fit may stop after its first
        pass when that moved the ellipses less than this (px; see ``refine_first_tol``).
        ``noises``: per view, the image's noise sigma if known. ``blur_gate``: as in
        :meth:`__call__`. ``tracked``: the ellipses are a tracker's prediction (the
        blurred-ring fit's gate is then ``track_blur_width``)."""
        return self.from_ellipses_of(
            frame, grays, cameras, [(self.marker, ellipses, noises)], score, blur_unrefined, first_tol, blur_gate, tracked
        )[0]

    def from_ellipses_of(
        self,
        frame: Frame,
        grays: list,
        cameras: list,
        items: list,
        score: float,
        blur_unrefined: bool = True,
        first_tol: float = 0.0,
        blur_gate=None,
        tracked: bool = False,
    ) -> list:
        """:meth:`from_ellipses` of several markers' rings in the same views, in one batch:
        ``items`` are (marker, per view its predicted ellipses, per view the noise sigma or
        None); per item, per view a Detection or None."""
        conf = self.classical if blur_unrefined else {**self.classical, "blur_fit_unrefined": False}
        if first_tol:
            conf = {**conf, "refine_first_tol": float(first_tol)}
        if tracked:
            conf = {**conf, "blur_fit_width": float(self.conf["track_blur_width"]), "blur_fit_long_px": 0.0}
        n = len(grays)
        fits = classical.refine_ellipses_views(
            grays * len(items),
            [e for _, ellipses, _ in items for e in ellipses],
            items[0][0],
            conf,
            cameras * len(items),
            [s for _, _, noises in items for s in (frame.noises(grays) if noises is None else noises)],
            detail=True,
            limits=classical.BlurLimits(frame.blur_fits, blur_gate),
            markers=None if len(items) == 1 else [m for m, _, _ in items for _ in range(n)],
        )
        found = [
            Detection(centers=c, ellipses=e, score=score, refined=ok, blur_px=b, center_cov=v) if ok.all() else None
            for c, ok, e, b, v in fits
        ]
        return [found[k * n : (k + 1) * n] for k in range(len(items))]

    def triple(self, frame: Frame, view: tuple, tri: tuple, cost: float, camera) -> Detection:
        """The classical detector's triple ``tri`` of a view (gray, noise, rings, ...)
        refined: sub-pixel edges and the blur fit with ``subpixel``, else the paper's
        contour ellipses."""
        gray, noise, rings = view[:3]
        return classical.refine_triple(
            gray, rings, tri, cost, self.marker, self.conf["subpixel"], self.classical, noise, camera, classical.BlurLimits(frame.blur_fits)
        )


__all__ = ["METHODS", "RULES", "Refiner", "default_conf"]
