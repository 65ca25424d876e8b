"""Detectors found by name (markerpose.detectors): the registry, and a new detector in one class."""

import numpy as np
import pytest

import markerpose as mp
from markerpose import detectors
from markerpose.detectors import DETECTORS, Detector
from markerpose.presets import resolve
from markerpose.results import Detection
from markerpose.synth import look_at_pose, render_stereo


@pytest.mark.parametrize(
    "settings, name",
    [
        ({}, "stereo"),
        ({"preset": "paper"}, "decoded"),
        ({"match": {"method": "layout"}}, "decoded"),
        ({"detector": "classical"}, "classical"),
        ({"preset": "paper-classical"}, "classical"),
    ],
)
def test_the_settings_name_the_detector(settings, name):
    conf = resolve(**settings)
    assert detectors.name_for(conf) == name and DETECTORS[name].name == name


class _Truth(Detector):
    """A detector that knows where the rings are: one hypothesis, the rendered truth."""

    name = "truth"

    def __init__(self, conf, rig, marker, refiner):
        super().__init__(conf, rig, marker, refiner)
        self.views: list = []

    def pairs(self, frame):
        yield [Detection(centers=v.outer_centers.copy()) for v in self.views]

    def view(self, frame, view):
        return Detection(centers=self.views[view].outer_centers.copy())


def test_a_new_detector_is_one_class_and_one_registry_line(rig, monkeypatch):
    monkeypatch.setitem(DETECTORS, "truth", _Truth)
    T = look_at_pose([10, -5, 560], 30, 45, 20)
    f = render_stereo(rig, T, seed=3)
    tracker = mp.MarkerPose(rig, detector="truth")
    assert isinstance(tracker.detector, _Truth) and tracker.refiner.net is None
    tracker.detector.views = f.views
    est = tracker.estimate(*f.images)
    assert est is not None and np.linalg.norm(est.t - T[:3, 3]) < 0.01
    np.testing.assert_array_equal(tracker.detect(f.images[1], view=1).centers, f.views[1].outer_centers)
    # Tracking hands it over to the prior after its first pose, as with any detector.
    assert tracker.track(*f.images).source == "detected" and tracker.track(*f.images).source == "tracked"


def test_an_unknown_detector_names_the_known_ones(rig):
    with pytest.raises(ValueError, match=r"detector must be one of \['neural', 'stereo', 'decoded', 'classical'\], got 'truth'"):
        mp.MarkerPose(rig, detector="truth")


def _counted_looks(monkeypatch) -> list:
    """The zooms of the stereo detector's stage-1 looks, in order, from now on."""
    from markerpose.detectors.stereo import StereoDetector

    looks, real = [], StereoDetector.look

    def counted(self, frame, zoom, previous):
        looks.append(zoom)
        return real(self, frame, zoom, previous)

    monkeypatch.setattr(StereoDetector, "look", counted)
    return looks


def test_no_second_look_once_the_first_spent_the_budget(rig, monkeypatch):
    """A pair no pose explains (the bench's first pair, its left view twice) whose first
    look's hypotheses spend the work budget without fitting a view to the plate: the second
    look is not taken (none of its hypotheses could be refined), and the outcome and its
    reason are those of a detector that takes it. (The mid stage-1 network's candidates:
    with them this pair's first look spends the budget.)"""
    from markerpose.experiments.bench import _pairs
    from markerpose.frame import Frame

    left = _pairs(1, 0)[2][0].images[0]
    looks = _counted_looks(monkeypatch)
    tracker = mp.MarkerPose(rig, propose={"network": "mid"})
    assert tracker.estimate(left, left) is None and looks == [1.0]
    why = tracker.why
    monkeypatch.setattr(Frame, "spent", property(lambda self: False))
    looks.clear()
    assert tracker.estimate(left, left) is None and looks == [1.0, 2.0]
    assert tracker.why == why


def test_no_second_look_where_a_view_already_fitted_the_plate(rig, monkeypatch):
    """A pair no pose explains (the left view given twice: the rings miss each other's
    epipolar lines), whose rings a view resolved and fitted to the plate at the first look:
    the second look, for rings too small to resolve, is not taken (one look, not two); and
    ``plate_seen`` is each child frame's own, a tool at a time."""
    from markerpose.frame import Frame

    left = render_stereo(rig, look_at_pose([10, -5, 600], 20, 40, 15), seed=4).images[0]
    looks = _counted_looks(monkeypatch)
    tracker = mp.MarkerPose(rig)
    assert tracker.estimate(left, left) is None and "epipolar" in tracker.why
    assert looks == [1.0]
    frame = Frame([left, left])
    frame.plate_seen = True
    assert frame.child().plate_seen is False
