"""The pipeline's stages, in the order the data flows through them (docs/design.md):

propose (:mod:`.propose`) → match (:mod:`.match`) → refine (:mod:`.refine`) →
verify (:mod:`.verify`) → solve (:mod:`.solve`).

Each module has its own small ``default_conf``; :class:`markerpose.MarkerPose`
orchestrates them and :mod:`markerpose.presets` names coherent settings of all five.
"""

from . import match, propose, refine, solve, verify

STAGES = ("propose", "match", "refine", "verify", "solve")

__all__ = ["STAGES", "match", "propose", "refine", "solve", "verify"]
