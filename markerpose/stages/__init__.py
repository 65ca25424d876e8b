"""The pipeline's stages, in the order the data flows through them (docs/design.md):

propose (:mod:`.propose`) → match (:mod:`.match`) → refine (:mod:`.refine`) →
verify (:mod:`.verify`) → solve (:mod:`.solve`); on video, :mod:`.track` predicts the
rings from the previous poses and goes straight to refine.

Each module has its own small ``default_conf``; :class:`markerpose.MarkerPose`
orchestrates them and :mod:`markerpose.presets` names coherent settings of all five.
"""

from . import match, propose, refine, solve, track, verify

STAGES = ("propose", "match", "refine", "verify", "solve", "track")

__all__ = ["STAGES", "match", "propose", "refine", "solve", "track", "verify"]
