"""Every system of the comparison behind one interface.

A system finds its points in a view (:meth:`System.observe` → :class:`Observation`:
point keys and sub-pixel image points) and turns them into a pose two ways:

- **mono**, as its users run it: OpenCV's IPPE from the left view alone (``IPPE_SQUARE``
  for a square tag, ``IPPE`` for the ChArUco board's corners), with the camera's full
  lens model; IPPE returns both solutions of the planar ambiguity, best first;
- **stereo**: the points seen in both views triangulated with the rig
  (:func:`markerpose.geometry.triangulate`) and the rigid fit markerpose uses
  (:func:`markerpose.geometry.pose_rigid`), so the marker is compared, not the method.

markerpose itself is a stereo system: its pose is ``MarkerPose.estimate`` (no mono pose).

How each peer is set up: twice where its library has settings a user would change, at
the library's defaults (``NAME-defaults``) and at its documented settings for accuracy
(``NAME``), so that neither hides what the other shows (AprilTag's decimation, for
instance, trades corner accuracy for robustness to blur):

- ``apriltag``: ``pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0,
  quad_sigma=0.0, refine_edges=1, decode_sharpening=0.25)``, one thread: full-resolution
  quad detection. ``apriltag-defaults``: the library's defaults (``quad_decimate=2.0``,
  the rest as above). Its corners are in a pixel-corner convention (a pixel spans
  [i, i + 1]); half a pixel is taken off so they are in OpenCV's (a pixel's centre at i),
  which every pose here uses.
- ``aruco``: ``cv2.aruco.ArucoDetector`` on ``DICT_4X4_50`` with
  ``cornerRefinementMethod = CORNER_REFINE_SUBPIX`` (OpenCV's sub-pixel corner
  refinement); ``aruco-defaults``: ``DetectorParameters()`` as they come (no refinement).
- ``charuco``: ``cv2.aruco.CharucoDetector`` (its markers refined with
  ``CORNER_REFINE_SUBPIX``; the chessboard corners are ``cornerSubPix``-refined by the
  detector); ``charuco-defaults``: its markers unrefined. A pose needs at least 4 corners.
- ``stag``: ``stag.detectMarkers(image, 21)`` (STag's own ellipse-based corner
  refinement is part of its detector; it has no other setting).

Beside these, each peer at further settings that its documentation suggests for hard
images (:data:`TUNED`, :data:`SETTINGS`): the comparison reports, per condition, the best
of a peer's settings (tuned per condition, which a user would have to know in advance).

A detector that finds several candidates reports the one with the expected ID; any other
ID counts as a wrong detection.
"""

from __future__ import annotations

import importlib.util
import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import pose_rigid, triangulate
from . import targets

PEERS = ("apriltag", "apriltag-defaults", "aruco", "aruco-defaults", "charuco", "charuco-defaults", "stag")
SYSTEMS = ("markerpose",) + PEERS
_SUBPIX, _CONTOUR, _APRILTAG = (getattr(cv2.aruco, f"CORNER_REFINE_{k}") for k in ("SUBPIX", "CONTOUR", "APRILTAG"))
# Each peer's settings: (peer, its detector's settings, where they come from). The first
# seven are the systems above; the rest (TUNED) are settings the libraries' documentation
# suggests for noisy, dark or blurred images.
SETTINGS = {
    "apriltag": ("apriltag", {"quad_decimate": 1.0}, "full-resolution quads (the accuracy setting)"),
    "apriltag-defaults": ("apriltag", {"quad_decimate": 2.0}, "the library's defaults"),
    "apriltag-d3": ("apriltag", {"quad_decimate": 3.0}, "quads on a third of the resolution: faster, more robust to blur"),
    "apriltag-sigma": ("apriltag", {"quad_decimate": 2.0, "quad_sigma": 0.8}, "quad_sigma 0.8: what the docs suggest for noisy images"),
    "apriltag-sharp": ("apriltag", {"quad_decimate": 2.0, "decode_sharpening": 1.0}, "decode_sharpening 1.0: more sharpening of the bits"),
    "aruco": ("aruco", {"cornerRefinementMethod": _SUBPIX}, "CORNER_REFINE_SUBPIX"),
    "aruco-defaults": ("aruco", {}, "DetectorParameters() as they come"),
    "aruco-contour": ("aruco", {"cornerRefinementMethod": _CONTOUR}, "CORNER_REFINE_CONTOUR (lines fitted to the contour)"),
    "aruco-apriltag": ("aruco", {"cornerRefinementMethod": _APRILTAG}, "CORNER_REFINE_APRILTAG (AprilTag's edge refinement)"),
    "aruco-blur": (
        "aruco",
        {
            "cornerRefinementMethod": _SUBPIX,
            "adaptiveThreshWinSizeMax": 53,
            "polygonalApproxAccuracyRate": 0.06,
            "cornerRefinementWinSize": 9,
        },
        "SUBPIX with wider threshold windows (up to 53 px), a looser polygon fit (0.06) and a 9 px refinement window",
    ),
    "charuco": ("charuco", {"cornerRefinementMethod": _SUBPIX}, "its markers CORNER_REFINE_SUBPIX"),
    "charuco-defaults": ("charuco", {}, "DetectorParameters() and CharucoParameters() as they come"),
    "charuco-refine": (
        "charuco",
        {"cornerRefinementMethod": _SUBPIX, "tryRefineMarkers": True},
        "SUBPIX, tryRefineMarkers (missed markers found from the board)",
    ),
    "charuco-blur": (
        "charuco",
        {"cornerRefinementMethod": _SUBPIX, "tryRefineMarkers": True, "adaptiveThreshWinSizeMax": 53, "polygonalApproxAccuracyRate": 0.06},
        "SUBPIX, tryRefineMarkers, wider threshold windows and a looser polygon fit",
    ),
    "stag": ("stag", {}, "errorCorrection at its maximum (the library's default)"),
    "stag-ec5": ("stag", {"errorCorrection": 5}, "errorCorrection 5 of 10"),
}
TUNED = tuple(n for n in SETTINGS if n not in PEERS)
PIP = {"apriltag": "pupil-apriltags", "stag": "stag-python"}  # the others come with OpenCV
LABELS = {
    "markerpose": "markerpose (three rings)",
    "apriltag": "AprilTag 3 tag36h11",
    "apriltag-defaults": "AprilTag 3 tag36h11, library defaults",
    "aruco": "ArUco 4×4",
    "aruco-defaults": "ArUco 4×4, library defaults",
    "charuco": "ChArUco 5×6",
    "charuco-defaults": "ChArUco 5×6, library defaults",
    "stag": "STag HD21",
}
LABELS.update({n: f"{LABELS[SETTINGS[n][0]]}, {n.split('-', 1)[1]}" for n in TUNED})
_MODULE = {"apriltag": "pupil_apriltags", "stag": "stag"}


def _base(name: str) -> str:
    """The peer a system name is a setting of (``apriltag-defaults`` → ``apriltag``)."""
    return SETTINGS[name][0] if name in SETTINGS else name


@dataclass
class Observation:
    """What a system measured in one view.

    Attributes:
        keys: (N,) which of the target's points (index into ``target.points``).
        points: (N, 2) sub-pixel image points, OpenCV's pixel-centre convention.
        wrong_id: the detector reported only a marker of another ID.
    """

    keys: np.ndarray
    points: np.ndarray
    wrong_id: bool = False


def missing(names=PEERS) -> dict[str, str]:
    """{system: pip package} of the peers whose package is not installed."""
    return {n: PIP[_base(n)] for n in names if _base(n) in _MODULE and importlib.util.find_spec(_MODULE[_base(n)]) is None}


class System:
    """A fiducial system: its printed target, its detector and its two poses."""

    name = ""
    mono = True  # has a monocular pose
    square = True  # a square tag: IPPE_SQUARE on its four corners

    def __init__(self):
        self.target = self.make_target()

    def make_target(self):
        raise NotImplementedError

    def observe(self, image: np.ndarray) -> Observation | None:
        raise NotImplementedError

    def mono_poses(self, camera, obs: Observation) -> list[np.ndarray]:
        """IPPE's solutions (T_cam_marker), best first; [] with too few points."""
        if obs is None or obs.wrong_id or len(obs.keys) < 4:
            return []
        model = self.target.points[obs.keys]
        pts = obs.points.reshape(-1, 1, 2).astype(np.float64)
        if self.square:
            half = targets.SQUARE_MM / 2
            canon = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]], np.float64)
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(canon[obs.keys], pts, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            offset = model.mean(0)  # the canonical frame sits at the square's centre
        else:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(model, pts, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
            offset = np.zeros(3)
        out = []
        for r, t in zip(rvecs, tvecs):
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(r)[0]
            T[:3, 3] = t.ravel() - T[:3, :3] @ offset
            out.append(T)
        return out if ok else []

    def stereo_pose(self, rig, left: Observation | None, right: Observation | None) -> np.ndarray | None:
        """T_left_marker from the points both views saw (≥ 4), or None."""
        if left is None or right is None or left.wrong_id or right.wrong_id:
            return None
        common, il, ir = np.intersect1d(left.keys, right.keys, return_indices=True)
        if len(common) < 4:
            return None
        X = triangulate(rig, left.points[il], right.points[ir])
        return pose_rigid(X, self.target.points[common])


def _apriltag_detector(**settings):
    """A ``pupil_apriltags.Detector`` that is freed in the right order.

    pupil-apriltags' own ``__del__`` frees the tag families before the detector, whose
    destructor still reads them: an intermittent segfault whenever a detector is
    collected. Freeing the detector first, then its families, is the C library's order.
    """
    import pupil_apriltags

    class Detector(pupil_apriltags.Detector):
        def __del__(self):
            ptr = getattr(self, "tag_detector_ptr", None)
            if ptr is None:
                return
            self.tag_detector_ptr = None
            self.libc.apriltag_detector_destroy.restype = None
            self.libc.apriltag_detector_destroy(ptr)
            for family, tf in self.tag_families.items():
                destroy = getattr(self.libc, f"{family}_destroy")
                destroy.restype = None
                destroy(tf)

    return Detector(**settings)


class AprilTag(System):
    name = "apriltag"
    tag_id = 0
    # pupil_apriltags reports the corners of OpenCV's tag36h11 raster as TR, TL, BL, BR;
    # this reorders them to the target's TL, TR, BR, BL.
    _order = np.array([1, 0, 3, 2])

    def __init__(self, name: str = "apriltag"):
        super().__init__()
        self.name = name
        settings = {"quad_sigma": 0.0, "refine_edges": 1, "decode_sharpening": 0.25, **SETTINGS[name][1]}
        self.detector = _apriltag_detector(families="tag36h11", nthreads=1, **settings)

    def make_target(self):
        return targets.apriltag_target(self.tag_id)

    def observe(self, image):
        found = self.detector.detect(np.ascontiguousarray(image))
        if not found:
            return None
        ours = [d for d in found if d.tag_id == self.tag_id]
        if not ours:
            return Observation(np.arange(0), np.zeros((0, 2)), wrong_id=True)
        c = np.asarray(ours[0].corners, np.float64)[self._order] - 0.5
        return Observation(np.arange(4), c)


class Aruco(System):
    name = "aruco"
    marker_id = 0

    def __init__(self, name: str = "aruco"):
        super().__init__()
        self.name = name
        self.detector = cv2.aruco.ArucoDetector(targets.aruco_dictionary("DICT_4X4_50"), _parameters(SETTINGS[name][1])[0])

    def make_target(self):
        return targets.aruco_target(self.marker_id)

    def observe(self, image):
        corners, ids, _ = self.detector.detectMarkers(image)
        if ids is None or len(ids) == 0:
            return None
        hit = np.flatnonzero(ids.ravel() == self.marker_id)
        if len(hit) == 0:
            return Observation(np.arange(0), np.zeros((0, 2)), wrong_id=True)
        return Observation(np.arange(4), np.asarray(corners[hit[0]], np.float64).reshape(4, 2))


class Charuco(System):
    name = "charuco"
    square = False

    def __init__(self, name: str = "charuco"):
        super().__init__()
        self.name = name
        p, c = _parameters(SETTINGS[name][1])
        self.detector = cv2.aruco.CharucoDetector(targets.charuco_board(), c, p)

    def make_target(self):
        return targets.charuco_target()

    def observe(self, image):
        corners, ids, _, _ = self.detector.detectBoard(image)
        if ids is None or len(ids) == 0:
            return None
        return Observation(ids.ravel().astype(np.intp), np.asarray(corners, np.float64).reshape(-1, 2))


class STag(System):
    name = "stag"
    marker_id = 0

    def __init__(self, name: str = "stag"):
        super().__init__()
        self.name = name
        self.error_correction = SETTINGS[name][1].get("errorCorrection", -1)

    def make_target(self):
        return targets.stag_target(self.marker_id)

    def observe(self, image):
        import stag

        corners, ids, _ = stag.detectMarkers(image, 21, self.error_correction)
        if ids is None or len(ids) == 0:
            return None
        ids = np.asarray(ids).ravel()
        hit = np.flatnonzero(ids == self.marker_id)
        if len(hit) == 0:
            return Observation(np.arange(0), np.zeros((0, 2)), wrong_id=True)
        c = np.asarray(corners[hit[0]], np.float64).reshape(4, 2)[targets.STAG_ORDER]
        return Observation(np.arange(4), c)


class Ours(System):
    """markerpose's default preset: a stereo pose, no mono pose."""

    name = "markerpose"
    mono = False

    def __init__(self, rig, preset: str = "default"):
        from ..pipeline import MarkerPose

        self.tracker = MarkerPose(rig, preset=preset, threads=1)
        self.target = self.tracker.marker

    def estimate(self, left, right):
        e = self.tracker.estimate(left, right)
        return None if e is None else e.T


PEER_CLASSES = {"apriltag": AprilTag, "aruco": Aruco, "charuco": Charuco, "stag": STag}


def _parameters(settings: dict):
    """OpenCV's ArUco DetectorParameters and CharucoParameters with ``settings`` (each key
    belongs to the one that has it)."""
    p, c = cv2.aruco.DetectorParameters(), cv2.aruco.CharucoParameters()
    for key, value in settings.items():
        setattr(c if hasattr(c, key) else p, key, value)
    return p, c


def make(name: str, rig=None) -> System:
    """The system called ``name`` (``ImportError`` naming the pip package if it is missing)."""
    if name == "markerpose":
        return Ours(rig)
    if name not in SETTINGS:
        raise ValueError(f"unknown system {name!r}; known: {list(SYSTEMS + TUNED)}")
    gone = missing([name])
    if gone:
        raise ImportError(f'{name} needs the package {gone[name]}: pip install {gone[name]} (or pip install -e ".[peers]")')
    return PEER_CLASSES[_base(name)](name)


def timed(fn, *args):
    """(result, seconds) of one call."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0
