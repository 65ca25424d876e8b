"""The classical detector (paper §3.4): binarise, contours, concentric ellipses.

Each view's ring candidates and its marker-like triples come from
:func:`markerpose.classical.view_triples`; the two views' triples are paired by the
epipolar constraint (:func:`~markerpose.stages.match.pair_triples`) and the chosen pair
refined (sub-pixel edges and the blurred-ring fit, or the paper's contour ellipses). The
pairing is the detector's check: its pair goes straight to the solve stage.
"""

from __future__ import annotations

from collections.abc import Iterator

from .. import classical
from ..frame import Frame
from ..results import Detection
from ..stages import match, propose, verify
from .base import Detector


class ClassicalDetector(Detector):
    """Contour-based rings, paired across the views by the epipolar constraint."""

    name = "classical"
    verified = True

    def pairs(self, frame: Frame) -> Iterator[list[Detection]]:
        views = [frame.timed("propose", propose.classical_view, g, self.marker, self.refiner.classical) for g in frame.grays]
        pair = frame.timed("match", match.pair_triples, self.rig, views[0][2:], views[1][2:], match.PAIR_EPIPOLAR_TOL)
        if pair is None:
            counts = ", ".join(f"{len(v[3])} {name}" for v, name in zip(views, verify.VIEWS))
            frame.failed(f"no pair of marker-like ring triples ({counts}) agrees with the epipolar geometry")
            return
        il, ir, cl, cr = pair
        found = [
            frame.timed("refine", self.refiner.triple, frame, v, tri, cost, cam)
            for v, tri, cost, cam in zip(views, (il, ir), (cl, cr), self.rig.cameras)
        ]
        for det, view in zip(found, verify.VIEWS):
            if not det.refined.all():
                frame.failed(f"the blurred-ring fit and the edge fit disagree in the {view} view")
                return
        yield found

    def view(self, frame: Frame, view: int) -> Detection | None:
        det = frame.timed("propose", classical.detect, frame.grays[0], self.marker, self.conf["refine"]["subpixel"], self.refiner.classical)
        frame.why = None if det is not None else "no marker-like triple of rings in this view"
        return det


__all__ = ["ClassicalDetector"]
