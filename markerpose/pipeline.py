"""MarkerPose: two views → propose → match → refine → verify → solve → pose.

The public entry point (docs/design.md)::

    tracker = MarkerPose(rig, preset="default")   # or "paper", "paper-classical", ...
    est = tracker.estimate(left, right)            # stateless cold detection: Estimate or None
    est = tracker.track(left, right)               # video: the previous frames are the prior
    tracker.reset()                                # forget the prior (a new sequence)
    det = tracker.detect(image, view=0)            # one view: Detection or None

    tools = MarkerPose(rig, markers=[a, b, c])     # several tools (markerpose.tools)
    found = tools.estimate_all(left, right)        # {name: Estimate} of the tools found
    found = tools.track_all(left, right)           # the same along a video

The detectors (:mod:`markerpose.detectors`) yield refined hypotheses of both views; a
:class:`ToolPipeline` verifies and solves them (:mod:`markerpose.stages`) for one marker,
and its :class:`~markerpose.stages.track.Tracker` carries the marker from frame to frame.
Each tool has its own, over networks shared by all. What one call needs lives in its
:class:`~markerpose.frame.Frame`.
"""

from __future__ import annotations

import functools
import gc
import threading
from collections.abc import Iterator, Sequence
from contextlib import closing, contextmanager
from pathlib import Path

import numpy as np

from . import classical, detectors, presets
from .camera import StereoRig
from .frame import Frame
from .geometry import ring_ellipses
from .images import as_gray, check_size, gray_pair
from .marker import Marker
from .results import Detection, Estimate
from .rigcheck import RigCheck
from .stages import refine, solve, track, verify
from .sync import Motion, check_times, right_at_left_time
from .tools import check_tools


class _SerialBlas:
    """numpy's BLAS on one thread while any tracker handles a frame.

    The pipeline's products are small (at most a few thousand pixels by a few dozen
    parameters) and gain nothing from more threads, while OpenBLAS's idle threads
    busy-wait for a while after each product and take the cores that the networks'
    runtime needs next. Counted across threads: the first frame in sets one thread, the
    last one out puts back the limits found when the first came in. The limit is the
    process's: while a frame is handled, other threads' numpy runs on one BLAS thread
    too, and a limit they change meanwhile is overwritten at the end. The BLAS libraries
    are those loaded at the first frame."""

    def __init__(self):
        self._lock = threading.Lock()
        self._inside = 0
        self._pools = None  # threadpoolctl's BLAS pools, found when first needed
        self._limit = None

    @contextmanager
    def __call__(self):
        with self._lock:
            if self._inside == 0:
                if self._pools is None:
                    from threadpoolctl import ThreadpoolController

                    self._pools = ThreadpoolController().select(user_api="blas")
                self._limit = self._pools.limit(limits=1)
            self._inside += 1
        try:
            yield
        finally:
            with self._lock:
                self._inside -= 1
                if self._inside == 0:
                    self._limit.restore_original_limits()
                    self._limit = None


serial_blas = _SerialBlas()


class ToolPipeline:
    """One marker's stages: its detector, verification, solve and tracker, over networks
    it may share with other tools' (:meth:`MarkerPose.__init__` builds them).

    It is the ``pipeline`` its :class:`~markerpose.stages.track.Tracker` calls
    (``cold``, ``near``, ``fitted``). A pose whose rings another tool found in the same
    call (:meth:`~markerpose.frame.Frame.claim`) is rejected: one ring is one tool's.
    """

    def __init__(self, conf: dict, rig: StereoRig, marker: Marker, refiner: refine.Refiner, detector: detectors.Detector):
        self.conf, self.rig, self.marker = conf, rig, marker
        self.refiner, self.detector = refiner, detector
        self.tracker = track.Tracker(conf["track"], rig, marker)

    @property
    def name(self) -> str:
        return self.marker.name

    def cold(self, frame: Frame) -> Estimate | None:
        """Detection from scratch: the detector's hypotheses, verified and solved in turn."""
        return self._first(frame, self.detector.pairs(frame))

    def near(self, frame: Frame, T_pred) -> Estimate | None:
        """A detection that looks only near a tracker's predicted pose ``T_pred`` first."""
        return self._first(frame, self.detector.near(frame, T_pred))

    def fitted(self, frame: Frame, predicted: list, first_tol: float, noises: list | None = None, motion: Motion | None = None):
        """Per view, the rings' edges fitted from ``predicted`` ellipses (a tracker's),
        verified and solved (``source`` "tracked"), or None; the blurred-ring fit from the
        tracker's gate (``refine.track_blur_width``). With ``motion`` (the pair's
        capture times and the motion before, :func:`markerpose.sync.motion`), the right view
        is moved to the left view's time before the verification and the solve."""
        found = frame.prefitted(self.name, predicted)
        if found is None:
            found = frame.timed(
                "refine",
                functools.partial(self.refiner.from_ellipses, tracked=True),
                frame,
                frame.grays,
                list(self.rig.cameras),
                predicted,
                1.0,
                False,
                first_tol,
                noises,
            )
        if any(det is None for det in found):
            return None
        checked = found if motion is None else [found[0], right_at_left_time(found[1], motion)]
        if frame.timed("verify", verify.rejection, self.rig, checked, self.marker, self.conf["verify"], True) is not None:
            return None
        est = self._solved(frame, checked, "tracked")
        if est is not None and motion is not None:
            est.right_measured = np.asarray(found[1].centers, np.float64)
        return est

    def moved(self, frame: Frame, est: Estimate, motion: Motion | None) -> Estimate | None:
        """``est`` (a cold detection) solved again with its right view moved to the left
        view's time (``motion``, :func:`markerpose.sync.right_at_left_time`); ``est`` where
        there is no motion, or where the moved pair fails the shape check."""
        if est is None or motion is None:
            return est
        moved = self._solved(frame, [est.detections[0], right_at_left_time(est.detections[1], motion)], est.source)
        if moved is None:
            return est
        moved.right_measured = np.asarray(est.detections[1].centers, np.float64)
        return moved

    def claim(self, frame: Frame, est: Estimate) -> None:
        """Claim, in ``frame``, the rings of this tool's pose ``est``: their fitted outer
        ellipses, or where a view has none, those the pose projects."""
        Ts = (est.T, self.rig.T_right_left @ est.T)
        mk = self.marker
        rings = [
            det.ellipses if det.ellipses is not None else ring_ellipses(cam, T, mk.points3d, mk.outer_radius)
            for det, cam, T in zip(est.detections, self.rig.cameras, Ts)
        ]
        frame.claim(self.name, rings)

    def _first(self, frame: Frame, hypotheses: Iterator) -> Estimate | None:
        """The first of the hypotheses that passes verification, solved; None if none does."""
        with closing(hypotheses):
            for found in hypotheses:
                est = self._solved(frame, found) if self.detector.verified else self._accepted(frame, found)
                if est is not None:
                    return est
        return None

    def _accepted(self, frame: Frame, found: list) -> Estimate | None:
        """The estimate from refined detections of both views if they pass verification."""
        reason = frame.timed("verify", verify.rejection, self.rig, found, self.marker, self.conf["verify"], self.refiner.edge_refit)
        if reason is not None:
            frame.failed(reason)
            return None
        return self._solved(frame, found)

    def _solved(self, frame: Frame, found: list, source: str = "detected") -> Estimate | None:
        """Solve, then reject points that do not have the marker's shape (a wrong triple),
        and rings another tool was found on."""
        est = frame.timed("solve", solve.solve, self.rig, self.marker, found[0], found[1], self.conf["solve"], source)
        if not verify.shape(est.points3d, self.marker, self.conf["verify"]):
            frame.failed(
                f"shape check: the triangulated centres are {verify.shape_error(est.points3d, self.marker.points3d):.2f} mm "
                f"from the marker's layout (limit {self.conf['verify']['max_shape_error']:g} mm)"
            )
            return None
        if any(frame.claimed):
            for view, centres in enumerate(est.centers):
                for c in centres:
                    other = frame.claimant(view, c)
                    if other is not None:
                        frame.failed(f"a ring of this pose is one of {other!r}'s, found in the same pair")
                        return None
        return est


MIN_IMAGE_SIDE = 64  # px: smaller images cannot hold three rings that the detector resolves


class MarkerPose:
    """Stereo pose of the three-ring marker, or of several tools at once.

    Args:
        rig: the calibrated stereo rig.
        marker: marker geometry (default: the paper's robot target).
        markers: instead of ``marker``, several tools (Markers or tool files,
            :meth:`Marker.load`), with distinct names and layouts told apart
            (:func:`markerpose.tools.check_tools`): see :meth:`estimate_all`,
            :meth:`track_all`. One stage 1 per pair serves them all.
        preset: a name of :data:`markerpose.presets.PRESETS` ("default", "paper",
            "paper-classical", ...).
        detector: "neural" or "classical" (shorthand for the presets "default" and "classical"),
            or any name in :data:`markerpose.detectors.DETECTORS`, over the preset.
        threads: (in ``overrides``) the networks' inference threads (None: every core).
        backend: (in ``overrides``) what runs the networks: "onnxruntime" (the default),
            "openvino" or "openvino-bf16" (OpenVINO at float32 or bfloat16; the ``openvino``
            extra).
        **overrides: one dict of settings per stage (``propose``, ``match``, ``refine``,
            ``verify``, ``solve``, ``track``; see each stage's ``default_conf``), applied
            over the preset.

    One MarkerPose handles one call at a time: a call made while another thread's call
    is under way raises ``RuntimeError`` (a video stream's frames come in order; give
    each thread or stream its own MarkerPose, which shares nothing with another).
    """

    def __init__(
        self,
        rig: StereoRig,
        marker: Marker | None = None,
        preset: str = "default",
        detector: str | None = None,
        markers: Sequence[Marker | str | Path] | None = None,
        **overrides,
    ):
        if not isinstance(rig, StereoRig):
            raise ValueError(f"rig must be a StereoRig, got {type(rig).__name__}")
        for cam, view in zip(rig.cameras, ("left", "right")):
            if cam.image_size is not None and min(cam.image_size) < MIN_IMAGE_SIDE:
                raise ValueError(
                    f"the rig's {view} camera is calibrated for {cam.image_size[0]}x{cam.image_size[1]} px images: too small to hold "
                    f"the marker's rings (at least {MIN_IMAGE_SIDE} px a side)"
                )
        self.conf = c = presets.resolve(preset, detector, **overrides)
        self.preset = preset
        self.markers = _markers(marker, markers)
        kind = detectors.DETECTORS[detectors.name_for(c)]
        if len(self.markers) > 1 and kind.name == "decoded":
            raise ValueError("several tools need a detector that matches rings by their 3D shape: use the preset 'default' or 'classical'")
        if c["solve"]["pose"] == "paper":
            for m in self.markers:
                if abs(m.c2[0]) > 1e-9:
                    raise ValueError(f"solve pose 'paper' takes c2 on the marker's +y axis; {m.name!r} has c2 = {m.c2}: use pose 'rigid'")
        self.rig, self.marker = rig, self.markers[0]
        refiner = refine.Refiner(c["refine"], self.marker, kind.neural, c["threads"], c["backend"])
        det = detectors.create(c, rig, self.marker, refiner, c["threads"], c["backend"])
        self.tools = {self.marker.name: ToolPipeline(c, rig, self.marker, refiner, det)}
        for m in self.markers[1:]:  # the first tool's networks serve every tool
            r = refiner.for_marker(m)
            self.tools[m.name] = ToolPipeline(c, rig, m, r, det.for_marker(m, r))
        first = self.tools[self.marker.name]
        self.refiner, self.detector, self.tracker = first.refiner, first.detector, first.tracker
        self.timings: dict = {}  # seconds per stage of the last call (see markerpose bench)
        self.why: str | None = None  # after a call that found nothing: the first reason met
        self.whys: dict[str, str] = {}  # after estimate_all / track_all: why each tool not found was not
        self.rig_check = RigCheck(rig)  # the calibration checked by every tracked pose (track, track_all)
        self._busy = threading.Lock()
        # What is alive now (the compiled kernels' and the networks' runtimes, this tracker)
        # lives as long as the process: Python's cyclic collector is told to skip it, or each
        # full collection, on whichever frame of a stream it falls, scans all of it again.
        # Freed by reference counting as before; only cycles among these objects are kept.
        gc.freeze()

    def __repr__(self):
        names = f", markers={list(self.tools)!r}" if len(self.tools) > 1 else ""
        return f"MarkerPose(preset={self.preset!r}{names}, conf={self.conf!r})"

    @contextmanager
    def _call(self, grays: list):
        """One call's frame, numpy's BLAS on one thread meanwhile; its timings and why kept."""
        if not self._busy.acquire(blocking=False):
            raise RuntimeError("this MarkerPose is handling a call in another thread: give each thread its own MarkerPose")
        frame = Frame(grays)
        try:
            with serial_blas():
                yield frame
        finally:
            self.timings, self.why = frame.finish(), frame.why
            self._busy.release()

    def _one(self, call: str) -> ToolPipeline:
        if len(self.tools) > 1:
            raise ValueError(f"{call}() follows one marker; with several tools call {call}_all(), which returns each tool's")
        return self.tools[self.marker.name]

    def detect(self, image, view: int = 0) -> Detection | None:
        """Ring centres c0, c1, c2 in one view (the fitted outer ellipses' centres), or None.

        Args:
            image: uint8 gray (H, W) or BGR (H, W, 3), of the size the rig was calibrated for.
            view: which of the rig's cameras took it (0 left, 1 right).
        """
        if view not in (0, 1):
            raise ValueError(f"view must be 0 (left) or 1 (right), got {view!r}")
        tool = self._one("detect")
        gray = as_gray(image)
        check_size(gray, self.rig.cameras[view], "image")
        with self._call([gray]) as frame:
            return tool.detector.view(frame, view)

    def estimate(self, left, right) -> Estimate | None:
        """Pose of the marker from a stereo pair, or None if it is not found in both views.
        Stateless: every pair is detected from scratch (see :meth:`track` for video).

        Args:
            left, right: uint8 gray (H, W) or BGR (H, W, 3) images of the same size.
        Returns:
            :class:`Estimate` (``T`` = T_left_marker in mm, ``points3d``, ``centers``) or None.
        """
        tool = self._one("estimate")
        with self._call(gray_pair(left, right, self.rig)) as frame:
            est = self._fits_rig(frame, tool.cold(frame))
            frame.why = None if est is not None else (frame.why or "no marker found")
            return est

    def track(self, left, right, times=None) -> Estimate | None:
        """Pose of the marker in the next pair of a video stream, or None.

        ``times``: the two views' capture times (t_left, t_right) in seconds, for cameras
        that are not synchronised: the pose is then the marker's at ``t_left``, the right
        view's later (or earlier) exposure compensated with the motion since the last pose
        (:mod:`markerpose.sync`); None (the default): the views are taken as simultaneous.

        Uses the previous frames as the prior (:class:`~markerpose.stages.track.Tracker`):
        the rings predicted from the last poses are refitted on the image's edges in both
        views and verified; where that fails (the marker lost, moved too fast, put down
        elsewhere), the marker is sought near the prediction by its appearance and, found
        there, fitted the same way; failing that, the pair is detected cold: first with
        stage 1 looking only near the predicted marker, then in the whole images, as
        :meth:`estimate` does. ``Estimate.source`` says which ("tracked": from the prior,
        without stage 1; "detected"). While the marker is lost, a pair that has not changed
        since the last one detected without it returns None at once (``track``:
        ``lost_change``; a cold detection still runs every ``lost_refresh`` pairs). Call
        :meth:`reset` between sequences.
        """
        tool = self._one("track")
        times = None if times is None else check_times(times)
        with self._call(gray_pair(left, right, self.rig)) as frame:
            return self._checked(tool.tracker.next(frame, tool, times=times), tool, times)

    def estimate_all(self, left, right) -> dict[str, Estimate]:
        """Each tool's pose from a stereo pair, detected from scratch: ``{name: Estimate}``
        of the tools found (``{}`` when none is). Stage 1 looks at the pair once for all
        tools; each tool's triples are matched by its own 3D shape, and the rings of a
        tool found are not another's. ``whys`` says why each missing tool was not found."""
        with self._call(gray_pair(left, right, self.rig)) as frame:
            tools = list(self.tools.values())
            return self._each(frame, lambda tool, sub: self._fits_rig(sub, tool.cold(sub)), tools, self._cold_together)

    def track_all(self, left, right, times=None) -> dict[str, Estimate]:
        """Each tool's pose in the next pair of a video stream: ``{name: Estimate}`` of the
        tools found. Each tool has its own tracker (as :meth:`track` has): the tools
        with a prior are fitted first, then those without are detected cold, with stage 1
        looking once for all of them. ``times``: as :meth:`track`'s. Call :meth:`reset`
        between sequences."""
        times = None if times is None else check_times(times)
        tools = sorted(self.tools.values(), key=lambda t: not t.tracker.history)  # tracked tools claim their rings first
        with self._call(gray_pair(left, right, self.rig)) as frame:
            expected = {t.name: t.tracker.expected(frame) for t in tools if t.tracker.history}
            self._fit_together(frame, expected)
            found = self._each(
                frame,
                lambda tool, sub: tool.tracker.next(sub, tool, expected.get(tool.name, track.UNSET), times=times),
                tools,
                None if expected else self._cold_together,  # every tool cold: their first hypotheses together
            )
        return {name: self._checked(est, self.tools[name], times) for name, est in found.items()}

    def _fits_rig(self, frame: Frame, est: Estimate | None) -> Estimate | None:
        """``est`` of a single pair (estimate, estimate_all), or None where its views do not fit
        the rig: the six centres reproject more than ``verify.max_residual_px`` from the pose,
        which a camera moved since calibration or the wrong rig file gives (a pose millimetres
        off whose every other check passes). In a stream (track) the rig check does this job
        with the statistics of many pairs (status "rig changed")."""
        limit = self.conf["verify"]["max_residual_px"]
        if est is None or est.residual_px <= limit:
            return est
        frame.why = (
            f"the views do not fit the rig: the six centres reproject {est.residual_px:.2f} px RMS from the pose "
            f"(verify.max_residual_px {limit:g}); a camera moved since calibration, or the wrong rig file"
        )
        return None

    def _checked(self, est: Estimate | None, tool: ToolPipeline, times: tuple | None = None) -> Estimate | None:
        """``est`` fed to the rig check (:mod:`markerpose.rigcheck`); once that has fired, the
        pose carries its reason (``rig_warning``, status "rig changed"). A pair exposed apart
        and not compensated (the first found, without the pairs before it) is not fed: its
        views disagree by the motion within the delay, as a moved camera's would."""
        if est is None:
            return est
        if times is not None and times[0] != times[1] and est.right_measured is None:
            est.rig_warning = self.rig_check.fired
            return est
        est.rig_warning = self.rig_check.update(est, tool.marker.points3d)
        return est

    def _fit_together(self, frame: Frame, expected: dict) -> None:
        """The first edge fits of the tools with a prior (``expected``: each one's predicted
        rings, :meth:`~markerpose.stages.track.Tracker.expected`) in one batch, kept in
        ``frame`` for each tool's own step (:meth:`ToolPipeline.fitted`)."""
        items = [(name, rings) for name, rings in expected.items() if rings is not None]
        if len(items) < 2:
            return
        tools = [self.tools[name] for name, _ in items]
        found = frame.timed(
            "refine",
            functools.partial(self.refiner.from_ellipses_of, tracked=True),
            frame,
            frame.grays,
            list(self.rig.cameras),
            [(t.marker, rings, t.tracker.noise[0]) for t, (_, rings) in zip(tools, items)],
            1.0,
            False,
            self.conf["track"]["one_pass_move"],
        )
        for (name, rings), fit in zip(items, found):
            frame.prefit(name, rings, fit)

    def _cold_together(self, frame: Frame, tools: list, subs: list) -> None:
        """The first cold hypotheses of the ``tools`` (each in its child frame of ``subs``),
        refined in one batch (:meth:`~markerpose.stages.refine.Refiner.layouts_of`) and kept
        in each child for its own detection: a tool's first hypothesis is refined from its
        rings' layout whatever the tools before it found, unless their rings were among its
        candidates (:meth:`~markerpose.frame.Frame.prelaid`)."""
        firsts = [(tool, sub, tool.detector.first(sub)) for tool, sub in zip(tools, subs)]
        firsts = [(tool, sub, f) for tool, sub, f in firsts if f is not None]
        if len(firsts) < 2:
            return
        budgets = [classical.FitBudget(sub.blur_fits.left) for _, sub, _ in firsts]  # charged to each tool when it takes its fit
        items = [(tool.marker, points, classical.BlurLimits(b, gate)) for (tool, _, (points, gate)), b in zip(firsts, budgets)]
        found = frame.timed("refine", self.refiner.layouts_of, frame, frame.grays, list(self.rig.cameras), items)
        for (tool, sub, (points, _)), fit, b in zip(firsts, found, budgets):
            sub.prelay(tool.name, points, fit, sub.blur_fits.left - b.left)

    def _each(self, frame: Frame, step, tools: list, prepare=None) -> dict[str, Estimate]:
        """``step(tool, frame)`` of each tool in its own child frame (``prepare(frame, tools,
        children)`` first); those found claim their rings."""
        found, self.whys = {}, {}
        subs = [frame.child() for _ in tools]
        if prepare is not None and len(tools) > 1:
            prepare(frame, tools, subs)
        for k, (tool, sub) in enumerate(zip(tools, subs)):
            est = step(tool, sub)
            if est is None:
                self.whys[tool.name] = sub.why or "not found"
                continue
            found[tool.name] = est
            if k < len(tools) - 1:  # the last tool's rings no other tool will look at
                tool.claim(frame, est)
        frame.why = "; ".join(f"{n}: {w}" for n, w in self.whys.items()) if not found else None
        return {name: found[name] for name in self.tools if name in found}

    def reset(self) -> None:
        """Forget the prior: the next :meth:`track` detects cold (a new sequence)."""
        for tool in self.tools.values():
            tool.tracker.reset()


def _markers(marker: Marker | None, markers) -> list[Marker]:
    """The tools a MarkerPose follows: ``marker`` (default: the paper's), or ``markers``
    (Markers or tool files), checked to be told apart."""
    if markers is None:
        if marker is not None and not isinstance(marker, Marker):
            raise ValueError(f"marker must be a Marker, got {type(marker).__name__}")
        return [marker or Marker()]
    if marker is not None:
        raise ValueError("give marker or markers, not both")
    if isinstance(markers, (str, Path, Marker)) or not len(markers):
        raise ValueError("markers must be a non-empty list of Markers or tool files")
    loaded = [m if isinstance(m, Marker) else Marker.load(m) for m in markers]
    return check_tools(loaded, [str(m) if not isinstance(m, Marker) else m.name for m in markers])


__all__ = ["MIN_IMAGE_SIDE", "MarkerPose", "ToolPipeline", "serial_blas"]
