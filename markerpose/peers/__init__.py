"""markerpose beside the fiducials people already use (``markerpose peers``).

- :mod:`.targets`: each peer's printed target on the three-ring marker's plate;
- :mod:`.systems`: each system's detector and its mono and stereo poses, one interface;
- :mod:`.experiment`: every system on the same rendered scenes, report and plots.

The peers' detectors are an optional extra: ``pip install -e ".[peers]"``
(``pupil-apriltags``, ``stag-python``; ArUco and ChArUco come with OpenCV).
"""

from .systems import PEERS, SYSTEMS, make, missing

__all__ = ["PEERS", "SYSTEMS", "make", "missing"]
