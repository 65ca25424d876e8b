"""One call's working state (markerpose.frame.Frame)."""

import numpy as np
import pytest

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


def test_children_share_the_call_but_not_the_budget():
    import numpy as np

    from markerpose.frame import Frame

    frame = Frame([np.zeros((4, 4), np.uint8)] * 2)
    frame.budget(3, 2)
    sub = frame.child()
    assert sub.fits_left is None and sub.why is None and sub.grays is frame.grays
    sub.budget(1, 1)
    assert sub.spend() and not sub.spend() and frame.fits_left == 3
    calls = []
    assert sub.shared("k", lambda: calls.append(1) or 7) == 7 and frame.shared("k", lambda: calls.append(1) or 8) == 7
    assert calls == [1]
    sub.timed("propose", lambda: None)
    assert "propose" in frame.timings


def test_claimed_rings_are_kept_off():
    import numpy as np

    from markerpose.frame import Frame

    frame = Frame([np.zeros((4, 4), np.uint8)] * 2)
    cand = [np.array([[10.0, 10, 0.9], [50, 50, 0.8]]), np.array([[10.0, 10, 0.9]])]
    assert frame.unclaimed(cand) is cand
    frame.child().claim("a", [[((10.0, 10.0), (8.0, 6.0), 0.0)], []])
    assert frame.claimant(0, (13.5, 10)) == "a" and frame.claimant(0, (14.5, 10)) is None and frame.claimant(1, (10, 10)) is None
    left, right = frame.unclaimed(cand)
    np.testing.assert_array_equal(left, cand[0][1:])
    np.testing.assert_array_equal(right, cand[1])


def test_a_call_begun_on_the_worker_gives_its_value_or_its_error_at_result():
    """``Worker.later``: on the worker thread beside the caller; run at once where it is
    asked from the worker itself; an exception is raised by ``result()`` either way."""
    import threading

    import pytest

    from markerpose.threads import Worker, cores

    w = Worker()
    main = threading.get_ident()
    assert (w.later(threading.get_ident).result() != main) == (cores() >= 2)  # one core: here

    def fails():
        raise ValueError("no fit")

    with pytest.raises(ValueError, match="no fit"):
        w.later(fails).result()
    nested = w.submit(lambda: (threading.get_ident(), w.later(threading.get_ident).result())).result()
    assert nested[0] == nested[1]  # from the worker: run there, not queued behind itself
    with pytest.raises(ValueError, match="no fit"):
        w.submit(lambda: w.later(fails)).result().result()


@pytest.mark.parametrize("n_cores", [1, 2])
@pytest.mark.parametrize("n", [0, 1, 2, 3, 4])
def test_the_workers_map_gives_every_items_value_on_one_core_or_two(monkeypatch, n_cores, n):
    """``Worker.map`` returns one value per item, in order, whether the process may use one
    core (everything here, in turn) or two (two at a time)."""
    import threading

    from markerpose import threads

    monkeypatch.setattr(threads, "cores", lambda: n_cores)
    w = threads.Worker()
    seen = []

    def square(x):
        seen.append(threading.get_ident())
        return x * x

    assert w.map(square, list(range(n))) == [k * k for k in range(n)]
    assert (len(set(seen)) > 1) == (n_cores >= 2 and n >= 2)
