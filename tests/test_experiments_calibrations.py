"""The calibration and uncertainty experiments run end to end on tiny configurations."""

import numpy as np

from markerpose import Marker, MarkerPose, StereoRig
from markerpose.experiments import handeye, pivot, rigcheck, uncertainty


def test_uncertainty_condition_and_report():
    rig, marker = StereoRig.default(), Marker()
    r = uncertainty.condition(MarkerPose(rig), uncertainty.CONDITIONS["standard"], 4, rig, marker)
    assert r["found"] == 4 and r["without_cov"] == 0 and 0 <= r["inside_95_6d"] <= 1
    assert 0 < r["rms_predicted_mm"] < 0.05
    assert "| standard | 4 | 4 |" in uncertainty.report({"conditions": {"standard": r}})


def test_pivot_simulated_finds_the_tip():
    conf = {**pivot.default_conf, "trials": 2, "poses": 60}
    rows = pivot.simulated(conf, Marker(), np.random.default_rng(0))
    assert [r["noise_mm"] for r in rows] == [0.01, 0.05]
    assert rows[0]["tip_error_median_mm"] < 0.05 and rows[0]["all_outliers_rejected"] == 1.0


def test_rigcheck_catches_a_turned_camera():
    r = rigcheck.bump(StereoRig.default(), ("turn", 0.05, "x"), 2, 3, np.random.default_rng(1))
    assert not r["fired_before"] and r["fired_after"] == 0


def test_handeye_rendered_robot():
    r = handeye.rendered(handeye.default_conf, np.random.default_rng(2), n_cal=8, steps=3)
    assert r["calibration_pairs"] == 8 and r["steps_found"] == 4
    assert r["displacement_mae_mm"] < 0.1 and r["Z_error_mm"] < 1.0
