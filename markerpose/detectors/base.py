"""What every detector is: one interface between the pipeline and a way of finding the marker.

A detector turns a call's images (:class:`~markerpose.frame.Frame`) into hypotheses:
refined detections of both views, best first (:meth:`Detector.pairs`), which the
pipeline verifies and solves in turn until one gives a pose. It also finds the marker in
one view alone (:meth:`Detector.view`) and, where it can, near a pose a tracker predicts
(:meth:`Detector.near`). The detectors that run stage 1 share :class:`NeuralDetector`.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator

import numpy as np

from ..camera import StereoRig
from ..frame import Frame
from ..marker import Marker
from ..results import Detection
from ..stages import propose, verify
from ..stages.match import VIEW_TRIPLES, best_per_set, layout_orders
from ..stages.refine import Refiner


class Detector:
    """The interface. Subclasses set :attr:`name` and implement :meth:`pairs` and :meth:`view`.

    Args:
        conf: the pipeline's resolved settings (:func:`markerpose.presets.resolve`).
        rig: the calibrated stereo rig.
        marker: the marker's geometry.
        refiner: the refine stage, shared with the pipeline's tracking.
    """

    name = ""
    neural = False  # True: it runs stage 1, and the refine stage EllipSegNet
    verified = False  # True: its pairs were checked as the detector pairs views; the pipeline only solves them

    def __init__(self, conf: dict, rig: StereoRig, marker: Marker, refiner: Refiner):
        self.conf, self.rig, self.marker, self.refiner = conf, rig, marker, refiner

    def for_marker(self, marker: Marker, refiner: Refiner) -> Detector:
        """This detector for another marker (with that marker's ``refiner``), sharing its networks."""
        other = copy.copy(self)
        other.marker, other.refiner = marker, refiner
        return other

    def pairs(self, frame: Frame) -> Iterator[list[Detection]]:
        """Refined hypotheses of both views ([left, right] Detections), best first."""
        raise NotImplementedError

    def near(self, frame: Frame, T_pred: np.ndarray) -> Iterator[list[Detection]]:
        """Hypotheses found only near where a tracker's prior puts the marker (pose
        ``T_pred``): none unless the detector can look there for less."""
        yield from ()

    def first(self, frame: Frame) -> tuple | None:
        """What :meth:`pairs` refines first, for refining it in one batch with other tools'
        (:meth:`markerpose.stages.refine.Refiner.layouts_of`): none unless the detector
        starts from a hypothesis it can name before refining."""
        return None

    def view(self, frame: Frame, view: int) -> Detection | None:
        """The marker in one view (``frame.grays[0]``, taken by camera ``view``), or None."""
        raise NotImplementedError


class NeuralDetector(Detector):
    """A detector that starts from stage 1 (:class:`~markerpose.stages.propose.NeuralProposer`).

    Args:
        ids: how stage 1's points are named: "stereo" (candidates, matched across views),
            "layout" or "head" (one triple per view by its layout or the ID head).
        threads, backend: the network's runtime.
    """

    neural = True

    def __init__(
        self, conf: dict, rig: StereoRig, marker: Marker, refiner: Refiner, threads: int | None = None, backend: str = "onnxruntime"
    ):
        super().__init__(conf, rig, marker, refiner)
        self.ids = conf["match"]["method"]
        self.proposer = propose.NeuralProposer(conf["propose"], marker, self.ids, threads, backend)

    def for_marker(self, marker: Marker, refiner: Refiner) -> NeuralDetector:
        other = super().for_marker(marker, refiner)
        other.proposer = self.proposer.for_marker(marker)
        return other

    def start_budget(self, frame: Frame) -> None:
        """A cold detection's work budget (``match.max_fits``, ``refine.max_blur_fits``)."""
        frame.budget(self.conf["match"]["max_fits"], self.conf["refine"]["max_blur_fits"])

    def fit(self, frame: Frame, *args) -> list | None:
        """One hypothesis refined (``refiner(frame, *args)``), charged to the work budget;
        None, with the reason, once it is spent."""
        if not frame.spend():
            return None
        return frame.timed("refine", self.refiner, frame, *args)

    def view(self, frame: Frame, view: int) -> Detection | None:
        gray, cam = frame.grays[0], self.rig.cameras[view]
        if self.ids == "head" or not self.refiner.gives_ellipses:  # the paper's decoding: one triple
            points = frame.timed("propose", self.proposer.decoded, [gray], frame.looked)
            det = frame.timed("refine", self.refiner, frame, [gray], [cam], points)[0]
            frame.why = None if det is not None else "stage 1 decoded no triple in this view"
            return det
        self.start_budget(frame)
        cand = None
        for zoom in self.proposer.looks():  # layout triples, best first, until one fits a plate
            if cand is not None and (frame.spent or not self.proposer.worth_second_look([cand])):
                break  # the first look spent the budget, or shows no marker a second look could resolve
            cand = frame.timed("propose", self.proposer.candidates, [gray], zoom, None if cand is None else [cand], frame.looked)[0]
            for pts, s in self.layout_triples(frame, gray, cand, zoom):
                found = self.fit(frame, [gray], [cam], [(pts, s)])
                if found is None:
                    break
                reason = verify.plate_rejection(found[0], cam, self.marker, verify.PLATE_TOL, verify.VIEWS[view])
                if reason is None:
                    return found[0]
                frame.failed(reason)
        return None

    def layout_triples(self, frame: Frame, gray: np.ndarray, cand: np.ndarray, zoom: float) -> list:
        """One view's layout triples to refine, best first: by score x ring evidence,
        without those under ``min_evidence`` (0: by score alone)."""
        m = self.conf["match"]
        if m["min_evidence"]:
            p, s, sets = layout_orders(cand, self.marker.centers2d, m["view_min_ratio"])
        else:
            p, s, sets = layout_orders(cand, self.marker.centers2d)
        if not len(p):
            frame.failed(
                f"no triple of the {len(cand)} stage-1 candidates has the marker's layout"
                if len(cand) >= 3
                else f"stage 1 found {len(cand)} ring candidate{'s' * (len(cand) != 1)}, fewer than three"
            )
            return []
        # With evidence, every order of a triple, not only the most marker-like one: at a
        # steep tilt a wrong order can have the larger layout ratio, and its rings the
        # wrong sizes. Without, each triple in its order of highest score.
        ev = self.proposer.evidence(gray, p, zoom, frame.looked) if m["min_evidence"] else np.ones(len(s))
        best = best_per_set(s * ev, sets)
        kept = [(p[k], float(s[k] * ev[k])) for k in best if ev[k] >= m["min_evidence"]]
        if not kept:
            frame.failed(f"ring evidence: the best of {len(best)} layout triples has {ev.max():.3f} (min_evidence {m['min_evidence']:g})")
        return kept[:VIEW_TRIPLES]


__all__ = ["Detector", "NeuralDetector"]
