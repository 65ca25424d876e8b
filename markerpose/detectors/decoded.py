"""The decoded detector: one triple per view straight from stage 1.

The paper's configuration names each view's rings by the network's ID head
(``match.method="head"``); the ``layout`` variant by the marker's 2D layout instead. Each
view's triple is refined and the pair verified and solved: no matching across the views,
no second hypothesis.
"""

from __future__ import annotations

from collections.abc import Iterator

from ..frame import Frame
from ..results import Detection
from ..stages import verify
from .base import NeuralDetector


class DecodedDetector(NeuralDetector):
    """One triple per view, decoded by stage 1's ID head or by the marker's layout."""

    name = "decoded"

    def pairs(self, frame: Frame) -> Iterator[list[Detection]]:
        found = frame.timed("propose", self.proposer.decoded, frame.grays, frame.looked)
        for f, view in zip(found, verify.VIEWS):
            if f is None:
                frame.failed(f"stage 1 decoded no triple in the {view} view")
        if found[0] is None or found[1] is None:
            return
        refined = self.fit(frame, frame.grays, list(self.rig.cameras), found)
        if refined is not None:
            yield refined


__all__ = ["DecodedDetector"]
