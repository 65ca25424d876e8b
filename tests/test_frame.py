"""One call's working state (markerpose.frame.Frame)."""

import numpy as np

from markerpose.frame import Frame


def test_the_work_budget_counts_hypotheses_and_says_when_spent():
    frame = Frame([np.zeros((32, 32), np.uint8)])
    assert frame.spend() and frame.why is None  # no budget: always
    frame.budget(2, 3)
    assert frame.spend() and frame.spend() and not frame.spend()
    assert frame.why == "work budget: 2 hypotheses refined, none accepted"
    assert frame.blur_fits.left == 3


def test_the_first_reason_stays_and_timings_add_up():
    frame = Frame([])
    frame.failed("first")
    frame.failed("second")
    assert frame.why == "first"
    assert frame.timed("refine", lambda a, b: a + b, 1, 2) == 3
    frame.timed("refine", lambda: None)
    timings = frame.finish()
    assert set(timings) == {"refine", "total"} and timings["total"] >= timings["refine"] >= 0
