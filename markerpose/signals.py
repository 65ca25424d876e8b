"""Ctrl-C held while a compiled library loads.

A C extension whose module initialisation imports numpy's C API (onnxruntime, OpenCV,
numba's helpers) turns a KeyboardInterrupt that lands in that instant into an
``ImportError`` ("import numpy failed"), which would read as a missing library. Loading
such libraries inside :func:`held_interrupt` keeps a Ctrl-C an interruption.
"""

from __future__ import annotations

import contextlib
import signal
import threading


@contextlib.contextmanager
def held_interrupt():
    """Run the block with SIGINT held; a Ctrl-C during it is raised as KeyboardInterrupt when
    the block ends. Outside the main thread, or where someone else handles SIGINT, the block
    runs as it is."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    seen: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if seen:
        raise KeyboardInterrupt


__all__ = ["held_interrupt"]
