"""Command-line interface: thin commands over the package's functions.

One module per command (or command group), each with its handler and a
``register(subparsers)`` that adds its subparser; what several share is in
:mod:`.common`. Handlers import what they run when they run, so ``markerpose --help``
loads no network, renderer or experiment.
"""

from __future__ import annotations

import argparse
import os
import sys

from .. import __version__
from . import (
    bench,
    calibrate,
    demo,
    estimate,
    evaluate,
    experiments,
    handeye,
    marker,
    peers,
    pivot,
    render,
    sync,
    tools,
    track,
    train,
    ultrasound,
)
from .common import EXIT_BAD_INPUT, EXIT_NOT_FOUND

# The commands in the order ``markerpose --help`` lists them (calibrate adds pattern too).
COMMANDS = (
    demo,
    marker,
    tools,
    render,
    estimate,
    calibrate,
    track,
    sync,
    pivot,
    handeye,
    peers,
    ultrasound,
    bench,
    experiments,
    train,
    evaluate,
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="markerpose", description="Stereo 6-DoF tracking of a three-ring marker (MarkerPose).")
    p.add_argument("--version", action="version", version=f"markerpose {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.register(sub)
    return p


def main(argv=None) -> int:
    """Run a command. Exit codes: 0 done, 1 the marker was not found (``estimate``), 2 bad
    input (a one-line message, no traceback), 130 interrupted (also while it starts)."""
    try:
        return _run(argv)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _run(argv) -> int:
    from ..jit import CompileError  # numba: imported here, where a Ctrl-C is an interruption

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
        return 130
    return int(rc or 0)


__all__ = ["EXIT_BAD_INPUT", "EXIT_NOT_FOUND", "build_parser", "main"]
