"""The verify stage (markerpose.stages.verify): a pose only from rings that are the marker."""

import re

import numpy as np
import pytest

import markerpose as mp
from markerpose.synth import look_at_pose, render_stereo


@pytest.fixture(scope="module")
def frame(rig):
    return render_stereo(rig, look_at_pose([15, -10, 560], 30, 40, 25), seed=11)


def test_a_triple_without_the_marker_shape_is_rejected(rig, frame):
    """Regression guard: a wrong triple triangulates to a shape unlike the marker's → None."""
    from markerpose.stages.verify import shape_error

    tracker = mp.MarkerPose(rig, detector="classical")
    est = tracker.estimate(*frame.images)
    assert est is not None and shape_error(est.points3d, tracker.marker.points3d) < 0.05
    bad = est.points3d.copy()
    bad[2] += [0.0, 8.0, 0.0]  # c2 somewhere else: 40 mm → ~48 mm from c0
    assert shape_error(bad, tracker.marker.points3d) > 2.0
    strict = mp.MarkerPose(rig, detector="classical", verify={"max_shape_error": 1e-6})
    assert strict.estimate(*frame.images) is None  # the check is applied


def test_rejection_names_the_failed_check(rig, frame):
    from dataclasses import replace

    from markerpose.stages import verify

    tracker = mp.MarkerPose(rig, detector="classical")
    left, right = tracker.estimate(*frame.images).detections
    conf = verify.default_conf
    assert verify.rejection(rig, [left, right], tracker.marker, conf, True) is None
    moved = replace(right, centers=right.centers + [0.0, 8.0])
    assert re.match(
        r"epipolar check: c\d is \d+\.\d px from its epipolar line \(limit 3 px\)",
        verify.rejection(rig, [left, moved], tracker.marker, conf, True),
    )
    unrefined = replace(right, refined=np.array([True, False, True]))
    assert verify.rejection(rig, [left, unrefined], tracker.marker, conf, True) == (
        "c1 not refined in the right view (the sub-pixel edge fit failed, or under heavy blur the blurred-ring fit "
        "disagreed with it or could not run)"
    )
