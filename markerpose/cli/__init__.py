"""Command-line interface: thin commands over the package's functions.

One module per command (or command group), each with its handler and a
``register(subparsers)`` that adds its subparser; what several share is in
:mod:`.common`. Handlers import what they run when they run, so ``markerpose --help``
loads no network, renderer or experiment.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from .. import __version__
from .common import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_NOT_FOUND

# The command modules in the order ``markerpose --help`` lists them (calibrate adds pattern
# too). Imported when the parser is built, inside main(), so that a Ctrl-C while they load is
# an interruption like any other.
COMMANDS = (
    "demo",
    "marker",
    "tools",
    "render",
    "estimate",
    "calibrate",
    "track",
    "batch",
    "sync",
    "pivot",
    "handeye",
    "peers",
    "ultrasound",
    "bench",
    "experiments",
    "train",
    "evaluate",
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="markerpose", description="Stereo 6-DoF tracking of a three-ring marker (MarkerPose).")
    p.add_argument("--version", action="version", version=f"markerpose {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return p


def main(argv=None) -> int:
    """Run a command. Exit codes: 0 done, 1 the marker was not found (``estimate``), 2 bad
    input (a one-line message, no traceback), 130 interrupted (also while it starts)."""
    try:
        return _run(argv)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def console() -> None:
    """The ``markerpose`` command (and ``python -m markerpose.cli``): :func:`main`, then an exit
    whose status a Ctrl-C cannot change any more. Once the work is done or stopped, a second
    Ctrl-C (or one that lands while the interpreter shuts down, when Python has given SIGINT
    back to the system) would otherwise end the process by the signal, not with 0 or 130."""
    try:
        rc = main()
    except KeyboardInterrupt:  # in the instant between main() and the line below
        print("interrupted", file=sys.stderr)
        rc = EXIT_INTERRUPTED
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if rc == EXIT_INTERRUPTED:  # stopped: every file is closed; skip the slow, interruptible teardown
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


def _run(argv) -> int:
    from ..signals import held_interrupt

    with held_interrupt():  # the compiled libraries load here, where a Ctrl-C is an interruption
        import cv2  # noqa: F401

        from ..jit import CompileError

    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
        sys.stdout.flush()
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, CompileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:  # e.g. `markerpose estimate ... | head -3`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return int(rc or 0)


__all__ = ["EXIT_BAD_INPUT", "EXIT_INTERRUPTED", "EXIT_NOT_FOUND", "build_parser", "console", "main"]
