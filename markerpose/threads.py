"""A second thread for work that runs outside Python's lock: the networks' runs, the
compiled fits. Two calls at once use both cores of a two-core machine, where one call
spread over both (ONNX Runtime's operators, BLAS) leaves them idle at every barrier."""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor


class Worker:
    """One thread that runs a second call beside the caller's. It is started afresh in a
    process forked from the one that started it (a forked child has none of its parent's
    threads)."""

    def __init__(self):
        self._pool, self._pid = None, None

    def submit(self, fn: Callable, *args):
        """``fn(*args)`` on the worker thread: a future."""
        if self._pid != os.getpid():
            self._pool, self._pid = ThreadPoolExecutor(1, thread_name_prefix="markerpose", initializer=_mark_worker), os.getpid()
        return self._pool.submit(fn, *args)

    def later(self, fn: Callable, *args):
        """``fn(*args)`` begun on the worker thread where this process has two cores or more
        and the caller is not the worker itself (else run here and now): an object whose
        ``result()`` gives its value. Calls begun this way run one after another there."""
        if getattr(_HERE, "worker", False) or cores() < 2:
            done: Future = Future()
            try:
                done.set_result(fn(*args))
            except BaseException as exc:  # raised by result(), as from the worker
                done.set_exception(exc)
            return done
        return self.submit(fn, *args)

    def both(self, first: Callable, second: Callable) -> tuple:
        """(first(), second()), ``second`` on the worker thread while ``first`` runs here; both
        here, in turn, when called from a worker thread (which would otherwise wait on itself)."""
        if getattr(_HERE, "worker", False):
            return first(), second()
        later = self.submit(second)
        return first(), later.result()

    def map(self, fn: Callable, items: list) -> list:
        """``[fn(item) for item in items]``, two at a time (:meth:`both`) where this process
        has two cores or more."""
        if cores() < 2:
            return [fn(item) for item in items]
        out: list = []
        for k in range(0, len(items), 2):
            if k + 1 < len(items):
                out += self.both(functools.partial(fn, items[k]), functools.partial(fn, items[k + 1]))
            else:
                out.append(fn(items[k]))
        return out


_HERE = threading.local()


def _mark_worker() -> None:
    _HERE.worker = True


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


__all__ = ["Worker", "cores"]
