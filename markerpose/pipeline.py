"""MarkerPose: two views → sub-pixel ring centres → triangulation → pose.

The public entry point (DESIGN §3)::

    tracker = MarkerPose(rig, marker=Marker(), detector="neural")  # or "classical"
    est = tracker.estimate(left, right)   # Estimate or None
    det = tracker.detect(image)           # Detection or None
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from .camera import StereoRig
from .geometry import POSE_METHODS, epipolar_distance, perspective_bias, pose_from_points, pose_rigid, triangulate
from .keypoints import ID_MODES, check_second_look
from .marker import Marker
from .matching import ring_ellipses, stereo_triples, transfer, view_poses, view_triples
from .results import Detection, Estimate

DETECTORS = ("classical", "neural")
IDS = ("stereo", *ID_MODES)  # how the neural detector names the rings (see default_conf["ids"])
REFINERS = ("ellipsegnet", "classical", "none")

default_conf = {
    "detector": "neural",  # "neural" (stage 1 network + refinement) or "classical" (paper §3.4)
    "pose": "rigid",  # "rigid": least-squares SO(3) fit (ours); "paper": R = [x y x×y], t = X0 (reference)
    "subpixel": True,  # classical: refine the outer edge to sub-pixel (False = paper's contour fit)
    "bias_correction": True,  # remove the perspective bias of ellipse centres (False = paper)
    "refine": "ellipsegnet",  # neural: "ellipsegnet" (stage 2, the paper), "classical" (the
    #                           classical ring fit near each stage-1 point) or "none" (stage-1 points)
    "patch": "adaptive",  # ellipsegnet: "adaptive" window (ours) or "fixed" 120 px (paper)
    "fit": "subpixel",  # ellipsegnet: "subpixel" iso-line fit (ours), "ellipse" (paper), "moments"
    "blur_fit": True,  # sub-pixel edge fits: when the edges are smeared to near the black band's
    #                    width (motion blur), refit the three rings together under a blurred-
    #                    image model (classical.refine_blurred, ours); False: the edge fit alone
    "edge_refit": True,  # ellipsegnet: fit the ring's outer edge in the image to sub-pixel,
    #                      starting from the mask's ellipse (ours); False: the mask's centre (paper)
    "ids": "stereo",  # neural: how the rings are found and named:
    #   "stereo" (ours): each view's stage-1 candidates, matched across the views by the
    #            marker's 3D shape (matching.stereo_triples); single views use "layout";
    #   "layout" (ours): one triple per view, named by the marker's 2D layout;
    #   "head"   (paper): one triple per view, named by the ID head.
    "candidates": 16,  # stereo: stage-1 candidates per view
    "candidate_threshold": 0.01,  # stereo: their minimum location score
    "candidate_nms": 4,  # stereo and detect(): NMS radius of the candidates, px at 320x240
    "match_epipolar_tol": 20.0,  # stereo: largest epipolar distance of two matched candidates, px
    #                              (stage 1 misplaces steeply tilted rings by 10-20 px)
    "shape_tol": 0.35,  # stereo: relative error allowed in each triangulated ring distance
    "max_triples": 3,  # stereo: matched triples refined and checked, best first, until one passes
    "transfer": True,  # stereo: when no matched triple passes but some match loosely, one view's
    #                    triple (a side of a loose triple, or the view's best by the 2D layout)
    #                    is refined and, if its rings refine, carried into the other view by
    #                    its pose (matching.transfer) and refined there; False: give up
    "transfer_epipolar_tol": 60.0,  # transfer: loose matching tolerances (px, relative) ...
    "transfer_shape_tol": 0.6,
    "transfer_attempts": 2,  # ... and how many loose triples are tried
    "transfer_sources": 4,  # transfer: one view's triples refined and carried over, at most
    "transfer_min_evidence": 0.1,  # transfer (v0.18): sources whose ring evidence in their view
    #                                is below this are not refined (None: every source, as up
    #                                to v0.17); decoy triples on marker-free pairs cost refits
    "view_triples": 4,  # single view (detect) and transfer: layout triples tried per view
    "plate_tol": 0.05,  # single view (detect) and transfer: largest misfit of the refined rings'
    #                     ellipses to one pose of the marker (relative radius; true markers
    #                     ~0.001-0.015, decoy triples > 0.2 on held-out views)
    "plate_check": True,  # stereo: each view's edge-fitted rings must also fit one plate pose
    #                       within plate_tol (ours): a ring refined onto a neighbour's blur can
    #                       pass the epipolar and shape checks and still give a wrong pose
    "min_evidence": 0.1,  # single view (detect): layout triples whose ring evidence
    #                       (keypoints.ring_evidence: dark bands on one white plate) is below
    #                       this are not refined, the others are tried by score x evidence
    #                       (stage 1's validation set: 285 of 286 true triples above); 0: by
    #                       score alone
    "second_look": 2.0,  # neural, "stereo" ids and single views (detect): when the first pass
    #                      finds no marker, stage 1 looks again at this many times its 320x240
    #                      input, resized from the full image (ours; rings under ~12 px at
    #                      320x240, a marker beyond ~0.8 m with the default rig, are found far
    #                      more often). Costs one forward pass zoom² as large, paid only by
    #                      frames without the marker found; 1: no second look (the paper)
    "keypoint_weights": None,  # neural: stage-1 checkpoint (None = the shipped weights)
    "ellipse_weights": None,  # ellipsegnet: stage-2 checkpoint (None = the shipped weights)
    "epipolar_tol": 3.0,  # neural: max epipolar distance of same-ID refined centres, px
    "epipolar_tol_coarse": 12.0,  # ... of stage-1 points that could not be refined, px
    "max_shape_error": 2.0,  # mm: the triangulated centres must match the marker's layout
    #                          (RMS residual of the rigid fit) or the estimate is rejected
}


def as_gray(image, name: str = "image") -> np.ndarray:
    """Validate an input image and return it as uint8 gray (H, W).

    Accepts uint8 gray (H, W), (H, W, 1) or BGR (H, W, 3); anything else raises
    ``ValueError`` saying what was wrong.
    """
    if image is None:
        raise ValueError(f"{name} is None")
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise ValueError(f"{name} is empty (shape {image.shape})")
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise ValueError(f"{name} must be gray (H, W) or BGR (H, W, 3), got shape {image.shape}")
    return image


def shape_error(points3d: np.ndarray, model: np.ndarray) -> float:
    """RMS distance (mm) between measured points (N, 3) and the rigidly fitted model (N, 3)."""
    T = pose_rigid(points3d, model)
    fitted = model @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((fitted - points3d) ** 2, axis=1))))


class MarkerPose:
    """Stereo pose of the three-ring marker.

    Args:
        rig: the calibrated stereo rig.
        marker: marker geometry (default: the paper's robot target).
        detector: "neural" (default): stage 1 (the SuperPoint-like network, both views in
            one batch) finds the rough centres, then ``refine``; or "classical" (paper §3.4,
            no PyTorch needed).
        pose: "rigid" (default: orthonormal least-squares fit) or "paper" (reference).
        subpixel: classical detector's sub-pixel edge refinement (False = the paper's contour fit).
        bias_correction: an ellipse's centre is not the image of the circle's centre; with
            the first pose, predict that offset in each view, subtract it and triangulate
            again (False = the paper, which triangulates the ellipse centres).
        refine: neural detector's sub-pixel stage: "ellipsegnet" (stage 2: EllipSegNet on a
            patch around each stage-1 point), "classical" (the classical ring fit near each
            stage-1 point) or "none" (stage-1 points, ~1 px).
        ids: how the neural detector finds and names the rings: "stereo" (ours, default:
            stage-1 candidates of both views matched by the marker's 3D shape, see
            :mod:`markerpose.matching`), "layout" (one triple per view, named by the
            marker's 2D layout) or "head" (the paper: named by the ID head).
        patch, fit: EllipSegNet's window ("adaptive" or the paper's "fixed" 120 px) and how
            the centre comes from its mask ("subpixel", the paper's "ellipse", "moments").
        edge_refit: with EllipSegNet, fit the ring's outer edge in the image to sub-pixel,
            starting from the ellipse of the mask (ours); False: the mask's centre (paper).
        blur_fit: where the sub-pixel edges are smeared by motion to near the black band's
            width, refit the three rings together under a blurred-image model (ours,
            :func:`markerpose.classical.refine_blurred`); False: the edge fit alone.
        keypoint_weights, ellipse_weights: checkpoints of the two networks (None: shipped).
    """

    def __init__(self, rig: StereoRig, marker: Marker | None = None, detector: str = "neural", **conf):
        if not isinstance(rig, StereoRig):
            raise ValueError(f"rig must be a StereoRig, got {type(rig).__name__}")
        unknown = set(conf) - set(default_conf)
        if unknown:
            raise ValueError(f"unknown option(s) {sorted(unknown)}; known: {sorted(default_conf)}")
        self.conf = {**default_conf, **conf, "detector": detector}
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; choose from {DETECTORS}")
        if self.conf["refine"] not in REFINERS:
            raise ValueError(f"unknown refine method {self.conf['refine']!r}; choose from {REFINERS}")
        if self.conf["ids"] not in IDS:
            raise ValueError(f"unknown ids method {self.conf['ids']!r}; choose from {IDS}")
        if self.conf["pose"] not in POSE_METHODS:
            raise ValueError(f"unknown pose method {self.conf['pose']!r}; choose from {POSE_METHODS}")
        check_second_look(self.conf["second_look"])
        self.rig = rig
        self.marker = marker or Marker()
        self._classical = {"blur_fit": bool(self.conf["blur_fit"])}  # settings of the classical fits
        self.timings: dict = {}  # seconds per stage of the last estimate() (see markerpose bench)
        self._keypoints = None
        if detector == "neural":
            try:
                from .keypoints import KeypointNet
            except ImportError as exc:  # torch missing
                raise ValueError(f"detector='neural' needs PyTorch ({exc}); pip install 'markerpose[neural]'") from exc
            ids = "layout" if self.conf["ids"] == "stereo" else self.conf["ids"]  # single views
            self._keypoints = KeypointNet(self.conf["keypoint_weights"], {"ids": ids}, marker=self.marker, stereo=True)
        self._ellipses = None
        # EllipSegNet's ellipses refitted on the image's edges (the moments fit has no ellipse).
        self._edge_refit = detector == "neural" and self.conf["refine"] == "ellipsegnet" and self.conf["edge_refit"] and self.conf["fit"] != "moments"
        if detector == "neural" and self.conf["refine"] == "ellipsegnet":
            from .ellipses import EllipseNet

            self._ellipses = EllipseNet(self.conf["ellipse_weights"], {"patch": self.conf["patch"], "fit": self.conf["fit"]})

    def _neural(self, grays: list, cameras: list) -> list:
        """Stage 1 on all views in one batch, then the sub-pixel stage: a Detection or None per view."""
        t0 = time.perf_counter()
        stage1 = self._keypoints(grays)
        t1 = time.perf_counter()
        out = self._refine(grays, cameras, stage1)
        self.timings.update(stage1=t1 - t0, refine=time.perf_counter() - t1)
        return out

    def _refine(self, grays: list, cameras: list, stage1: list) -> list:
        from . import classical

        if self._ellipses is not None:  # all patches of all views in one batch
            seen = [k for k, f in enumerate(stage1) if f is not None]
            refined = self._ellipses([grays[k] for k in seen], [stage1[k][0] for k in seen], self.marker, with_ellipses=self._edge_refit)
            out = [None] * len(grays)
            for k, found in zip(seen, refined):
                centers, ok = found[0], found[1]
                ellipses = None
                if self._edge_refit:  # the image's edges, from the mask's ellipses
                    c2, ok2, ellipses = classical.refine_ellipses(grays[k], found[2], self.marker, self._classical, camera=cameras[k])
                    if not ok2.all():  # a poor mask: the classical ring fit near the point instead
                        c3, ok3, e3 = classical.refine_points(grays[k], centers, self.marker, conf=self._classical, camera=cameras[k])
                        c2 = np.where(ok2[:, None], c2, c3)
                        ellipses = [e if o else f for e, o, f in zip(ellipses, ok2, e3)]
                        ok2 = ok2 | ok3
                    # Only edge-fitted centres count as refined: a mask's centre can be
                    # pixels off, and a pose from it is wrong by a millimetre.
                    centers, ok = np.where(ok2[:, None], c2, centers), ok2
                out[k] = Detection(centers=centers, ellipses=ellipses, score=stage1[k][1], refined=ok)
            return out

        out = []
        for gray, cam, found in zip(grays, cameras, stage1):
            if found is None:
                out.append(None)
                continue
            pts, score = found
            if self.conf["refine"] == "none":
                out.append(Detection(centers=pts, score=score, refined=np.zeros(3, bool)))
                continue
            centers, ok, ellipses = classical.refine_points(gray, pts, self.marker, subpixel=self.conf["subpixel"], conf=self._classical, camera=cam)
            out.append(Detection(centers=centers, ellipses=ellipses, score=score, refined=ok))
        return out

    def __repr__(self):
        opts = ", ".join(f"{k}={v!r}" for k, v in self.conf.items())
        return f"MarkerPose({opts})"

    def _check_size(self, image: np.ndarray, camera, name: str):
        if camera.image_size is not None and (image.shape[1], image.shape[0]) != tuple(camera.image_size):
            w, h = camera.image_size
            raise ValueError(
                f"{name} is {image.shape[1]}x{image.shape[0]} but the rig was calibrated for {w}x{h}"
            )

    def detect(self, image, view: int = 0) -> Detection | None:
        """Ring centres c0, c1, c2 in one view, or None if the marker is not found.

        Args:
            image: uint8 gray (H, W) or BGR (H, W, 3).
            view: which of the rig's cameras took it (0 left, 1 right): the neural detector
                checks with its intrinsics that the three rings lie on one plate.
        """
        gray = as_gray(image)
        if view not in (0, 1):
            raise ValueError(f"view must be 0 (left) or 1 (right), got {view!r}")
        self.timings = {}
        if self._keypoints is None:
            from . import classical

            return classical.detect(gray, self.marker, subpixel=self.conf["subpixel"], conf=self._classical)
        if self.conf["ids"] == "head" or self.conf["refine"] == "none":
            return self._neural([gray], [None])[0]  # the paper's decoding
        # Ours: each triple the marker's 2D layout allows, best first, refined, until one
        # whose rings fit one plate pose (matching.view_poses) — decoys in a marker-like
        # triangle do not.
        t0 = time.perf_counter()
        self.timings.update(stage1=0.0, refine=0.0)
        cam = self.rig.cameras[view]
        for zoom in self._looks():
            t = time.perf_counter()
            cand = self._keypoints.candidates([gray], self.conf["candidate_threshold"], self.conf["candidates"], zoom, self.conf["candidate_nms"])[0]
            self.timings["stage1"] += time.perf_counter() - t
            for pts, s in self._view_triples(gray, cand, zoom):
                t = time.perf_counter()
                det = self._refine([gray], [cam], [(pts, s)])[0]
                self.timings["refine"] += time.perf_counter() - t
                if self._plate_poses(det, cam):
                    self.timings["total"] = time.perf_counter() - t0
                    return det
        self.timings["total"] = time.perf_counter() - t0
        return None

    def _looks(self) -> tuple[float, ...]:
        """Stage 1's zoom factors, tried in turn while the marker is not found."""
        zoom = float(self.conf["second_look"])
        return (1.0, zoom) if zoom > 1 else (1.0,)

    def _view_triples(self, gray: np.ndarray, cand: np.ndarray, zoom: float = 1.0) -> list:
        """One view's layout triples to refine, best first: by score, or with
        ``min_evidence`` by score x ring evidence (in the input of the look ``zoom`` that
        found the candidates), without those below it."""
        n = self.conf["view_triples"]
        if not self.conf["min_evidence"]:
            return view_triples(cand, self.marker.centers2d, max_triples=n)
        triples = view_triples(cand, self.marker.centers2d, max_triples=None)
        if not triples:
            return []
        ev = self._keypoints.evidence(gray, np.stack([p for p, _ in triples]), zoom)
        kept = [(p, s * e) for (p, s), e in zip(triples, ev) if e >= self.conf["min_evidence"]]
        return sorted(kept, key=lambda t: -t[1])[:n]

    def _plate_poses(self, det: Detection | None, camera) -> list:
        """The marker's poses (:func:`~markerpose.matching.view_poses`) if one of them
        explains the three refined rings' ellipses within ``plate_tol``, else []."""
        if det is None or not det.refined.all() or det.ellipses is None:
            return []
        poses = view_poses(camera, det.centers, det.ellipses, self.marker.points3d, self.marker.outer_radius)
        return poses if poses and poses[0][0] <= self.conf["plate_tol"] else []

    def estimate(self, left, right) -> Estimate | None:
        """Pose of the marker from a stereo pair, or None if it is not found in both views.

        Args:
            left, right: uint8 gray (H, W) or BGR (H, W, 3) images of the same size.
        Returns:
            :class:`Estimate` (``T`` = T_left_marker in mm, ``points3d``, ``centers``) or None.
        """
        gl, gr = as_gray(left, "left image"), as_gray(right, "right image")
        if gl.shape != gr.shape:
            raise ValueError(f"left and right images differ in size: {gl.shape[::-1]} vs {gr.shape[::-1]}")
        self._check_size(gl, self.rig.left, "left image")
        self._check_size(gr, self.rig.right, "right image")
        self.timings = {}
        t0 = time.perf_counter()
        if self._keypoints is not None:
            return self._estimate_neural(gl, gr, t0)
        from . import classical

        found = classical.detect_stereo(gl, gr, self.rig, self.marker, subpixel=self.conf["subpixel"], conf=self._classical)
        t1 = time.perf_counter()
        self.timings["detect"] = t1 - t0
        return None if found is None else self._checked_estimate(found, t0, t1)

    def _checked_estimate(self, found, t0: float, t1: float) -> Estimate | None:
        """Triangulate and fit the pose; None when the points do not have the marker's shape."""
        est = self.estimate_from_detections(*found)
        t2 = time.perf_counter()
        self.timings.update(geometry=self.timings.get("geometry", 0.0) + t2 - t1, total=t2 - t0)
        # A wrong triple (a decoy, an occluded ring replaced by something else) triangulates
        # to points that do not have the marker's shape: reject rather than return a wrong pose.
        if shape_error(est.points3d, self.marker.points3d) > self.conf["max_shape_error"]:
            return None
        return est

    def _estimate_neural(self, gl: np.ndarray, gr: np.ndarray, t0: float) -> Estimate | None:
        """Stage 1 on both views, then each hypothesis (matched triples, best first) is
        refined and checked (epipolar distances, shape) until one passes; with "stereo"
        ids, the whole is done again on stage 1's second look if none does."""
        self.timings.update(stage1=0.0, refine=0.0)
        if self.conf["ids"] != "stereo":  # one triple per view (the paper's "head")
            found = self._keypoints([gl, gr])
            self.timings["stage1"] = time.perf_counter() - t0
            hypotheses = [found] if found[0] is not None and found[1] is not None else []
            return self._first_accepted([gl, gr], hypotheses, t0)
        for zoom in self._looks():
            t = time.perf_counter()
            cand = self._keypoints.candidates([gl, gr], self.conf["candidate_threshold"], self.conf["candidates"], zoom, self.conf["candidate_nms"])
            self.timings["stage1"] += time.perf_counter() - t
            triples = stereo_triples(
                self.rig, cand[0], cand[1], self.marker.points3d, self.conf["match_epipolar_tol"],
                self.conf["shape_tol"], self.conf["max_triples"],
            )
            est = self._first_accepted([gl, gr], [[(pl, s), (pr, s)] for pl, pr, s in triples], t0)
            if est is None and self.conf["transfer"]:
                est = self._transferred([gl, gr], list(self.rig.cameras), cand, t0, zoom)
            if est is not None:
                return est
        self.timings["total"] = time.perf_counter() - t0
        return None

    def _first_accepted(self, grays: list, hypotheses: list, t0: float) -> Estimate | None:
        """Each hypothesis (stage-1 points of both views) refined and checked, in turn: the
        first estimate that passes, or None."""
        cameras = list(self.rig.cameras)
        for stage1 in hypotheses:
            t = time.perf_counter()
            found = self._refine(grays, cameras, stage1)
            t1 = time.perf_counter()
            self.timings["refine"] += t1 - t
            est = self._accepted(found, t0, t1)
            if est is not None:
                return est
        self.timings["total"] = time.perf_counter() - t0
        return None

    def _accepted(self, found: list, t0: float, t1: float) -> Estimate | None:
        """The estimate from refined detections of both views if they pass the checks."""
        if found[0] is None or found[1] is None:
            return None
        if self._edge_refit and not (found[0].refined.all() and found[1].refined.all()):
            return None  # with edge refit, a pose only from six edge-fitted centres
        # The IDs give the correspondences; the epipolar constraint checks them.
        d = np.diag(epipolar_distance(self.rig, found[0].centers, found[1].centers))
        both = found[0].refined & found[1].refined
        if np.any(d > np.where(both, self.conf["epipolar_tol"], self.conf["epipolar_tol_coarse"])):
            return None
        if self.conf["plate_check"]:
            for det, cam in zip(found, self.rig.cameras):
                if det.ellipses is not None and det.refined.all() and not self._plate_poses(det, cam):
                    return None
        return self._checked_estimate(found, t0, t1)

    def _transferred(self, grays: list, cameras: list, cand: list, t0: float, zoom: float = 1.0) -> Estimate | None:
        """Recover a marker one camera sees too steeply for stage 1 to place its rings within
        the matching tolerances. Only when triples match loosely (in about a third of cluttered
        marker-free pairs with v0.18's stage 1, hence the evidence gate below): one view's triple — a side of a loosely
        matched triple, or the view's best triple by the marker's 2D layout — is refined;
        if its three rings refine, its pose (:func:`~markerpose.matching.transfer`) says
        where the rings are in the other view and what ellipses they make there; their
        edges are fitted from those ellipses (or, failing that, the rings are refined at the
        predicted centres) and checked like any matched triple. With
        ``transfer_min_evidence``, a source whose ring evidence (in the input of the look
        ``zoom`` that found the candidates) is below it is skipped."""
        from . import classical

        m = self.marker
        loose = stereo_triples(
            self.rig, cand[0], cand[1], m.points3d, self.conf["transfer_epipolar_tol"],
            self.conf["transfer_shape_tol"], self.conf["transfer_attempts"],
        )
        if not loose:  # no sign of the marker in both views (the common case without it): stop
            return None
        sources = [(a, p, s) for pl, pr, s in loose for a, p in ((0, pl), (1, pr))]
        for a in (0, 1):
            sources += [(a, p, s) for p, s in view_triples(cand[a], m.centers2d, max_triples=self.conf["view_triples"])]
        unique: list = []
        for a, pts, s in sources:
            if not any(a == a2 and np.abs(pts - p2).max() < 1e-6 for a2, p2, _ in unique):
                unique.append((a, pts, s))
        gate = self.conf["transfer_min_evidence"]
        if gate is not None:  # one evidence look per view for all of its sources
            keep = np.ones(len(unique), bool)
            for view in (0, 1):
                idx = [k for k, (a, _, _) in enumerate(unique) if a == view]
                if idx:
                    keep[idx] = self._keypoints.evidence(grays[view], np.stack([unique[k][1] for k in idx]), zoom) >= gate
            unique = [u for u, k in zip(unique, keep) if k]
        for a, pts, s in unique[: self.conf["transfer_sources"]]:
            b = 1 - a
            t = time.perf_counter()
            det_a = self._refine([grays[a]], [cameras[a]], [(pts, s)])[0]
            self.timings["refine"] += time.perf_counter() - t
            poses = self._plate_poses(det_a, cameras[a])

            def ordered(det_b):  # (left, right), used within this iteration only
                return [det_a, det_b] if a == 0 else [det_b, det_a]

            for pred, T_b in transfer(self.rig, a, poses, m.points3d):
                # The pose predicts the rings' ellipses in the other view to within a pixel
                # or so: their edges are fitted from there (the classical ring fit, with the
                # blur model where the edges are smeared), and only if that fails is the
                # usual refinement run at the predicted centres — where a steep, blurred
                # view can lead it to a neighbouring ring.
                t = time.perf_counter()
                predicted = ring_ellipses(cameras[b], T_b, m.points3d, m.outer_radius)
                centers, ok, ellipses = classical.refine_ellipses(grays[b], predicted, m, self._classical, camera=cameras[b])
                self.timings["refine"] += time.perf_counter() - t
                if ok.all():
                    guided = Detection(centers=centers, ellipses=ellipses, score=s, refined=ok)
                    est = self._accepted(ordered(guided), t0, time.perf_counter())
                    if est is not None:
                        return est
                t = time.perf_counter()
                det_b = self._refine([grays[b]], [cameras[b]], [(pred, s)])[0]
                t1 = time.perf_counter()
                self.timings["refine"] += t1 - t
                est = self._accepted(ordered(det_b), t0, t1)
                if est is not None:
                    return est
        return None

    def estimate_from_detections(self, det_left: Detection, det_right: Detection) -> Estimate:
        """Triangulate matched centres (ordered by ID) and compute the pose.

        With ``bias_correction`` the returned ``centers`` are the corrected ones: estimates
        of where the rings' 3D centres project, rather than the fitted ellipses' centres.
        """
        centers = np.stack([det_left.centers, det_right.centers]).astype(np.float64)
        X = triangulate(self.rig, centers[0], centers[1])
        if self.conf["bias_correction"]:
            measured = centers.copy()
            m = self.marker
            for _ in range(2):  # the bias varies slowly with pose: two rounds converge
                T = pose_rigid(X, m.points3d)
                Ts = (T, self.rig.T_right_left @ T)
                for i, cam in enumerate(self.rig.cameras):
                    centers[i] = measured[i] - perspective_bias(cam, Ts[i], m.centers2d, m.outer_radius)
                X = triangulate(self.rig, centers[0], centers[1])
        T = pose_from_points(X, self.marker.points3d, self.conf["pose"])
        return Estimate(T=T, points3d=X, centers=centers, detections=(det_left, det_right))
