"""What several commands share: exit codes, the rig, the marker and tracker options,
``--set`` parsing and argument types."""

from __future__ import annotations

import argparse
import math

EXIT_NOT_FOUND = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # as a shell reports a command ended by Ctrl-C (128 + SIGINT)

TOP_LEVEL = ("detector", "threads", "backend")  # settings of the whole pipeline, not of a stage


def rig(path):
    """The rig file at ``path``, or the built-in rig when None."""
    from ..camera import StereoRig

    return StereoRig.default() if path is None else StereoRig.load(path)


def marker(args):
    """The marker of a command's geometry options (:func:`add_marker_args`)."""
    from ..marker import Marker

    return Marker(
        outer_diameter=args.outer_diameter,
        inner_diameter=args.inner_diameter,
        c1=(args.c1, 0.0),
        c2=(0.0, args.c2),
        margin=args.margin,
    )


# The marker-geometry options (:func:`add_marker_args`) and their defaults, the paper's marker.
MARKER_DEFAULTS = {"outer_diameter": 20.0, "inner_diameter": 8.0, "c1": 25.0, "c2": 40.0, "margin": 10.0}


def add_marker_args(p):
    d = MARKER_DEFAULTS
    g = p.add_argument_group("marker geometry (mm)")
    g.add_argument("--outer-diameter", type=float, default=d["outer_diameter"], help="black ring diameter (default 20)")
    g.add_argument("--inner-diameter", type=float, default=d["inner_diameter"], help="white inner disk diameter (default 8)")
    g.add_argument("--c1", type=float, default=d["c1"], help="distance c0→c1 along x (default 25)")
    g.add_argument("--c2", type=float, default=d["c2"], help="distance c0→c2 along y (default 40)")
    g.add_argument("--margin", type=float, default=d["margin"], help="plate margin around the rings (default 10)")


def geometry_given(args) -> list[str]:
    """The marker-geometry options whose values differ from their defaults, as flags (e.g. ``--c1``)."""
    return ["--" + k.replace("_", "-") for k, v in MARKER_DEFAULTS.items() if getattr(args, k, v) != v]


def port(text: str) -> int:
    """A TCP port number, 1 to 65535 (argparse type)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 1 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 1 to 65535, got {n}")
    return n


def positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, got {n}")
    return n


def pixel(text: str) -> tuple[float, float]:
    """Two finite numbers ``A,B`` (argparse type)."""
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers A,B, got {text!r}") from None
    if not (math.isfinite(u) and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected two finite numbers A,B, got {text!r}")
    return u, v


def spacing(text: str) -> tuple[float, float]:
    """An ultrasound pixel size ``SX,SY`` in mm, each in (0, 10] (argparse type)."""
    sx, sy = pixel(text)
    if not (0 < sx <= 10 and 0 < sy <= 10):
        raise argparse.ArgumentTypeError(f"a pixel size is over 0 and at most 10 mm, got {text!r}")
    return sx, sy


def setting(text: str) -> tuple[str, str | None, object]:
    """``STAGE.KEY=VALUE`` (or ``KEY=VALUE`` for ``detector`` / ``threads`` / ``backend``) →
    (stage or key, key or None, value); the value is read as JSON (numbers, true, false,
    null, lists), anything else as a string."""
    import json

    name, sep, raw = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected STAGE.KEY=VALUE (e.g. track.lost_change=0), got {text!r}")
    try:
        value = json.loads(raw)
    except ValueError:
        value = raw
    stage, dot, key = name.partition(".")
    return (stage, key, value) if dot else (stage, None, value)


def overrides(settings: list | None) -> dict:
    """--set settings → MarkerPose's overrides: one dict per stage, and top-level keys;
    ``ValueError`` (one line) for an unknown stage. The values are checked where the API's
    are, by :func:`markerpose.presets.resolve`."""
    from ..presets import default_conf

    out: dict = {}
    for stage, key, value in settings or ():
        if stage in TOP_LEVEL:
            if key is not None:
                raise ValueError(f"--set {stage}.{key}: {stage} takes a value, e.g. --set {stage}=...")
            out[stage] = value
            continue
        if stage not in default_conf:
            known = [k for k in default_conf if k not in TOP_LEVEL]
            raise ValueError(f"--set {stage}{'.' + key if key else ''}: unknown stage {stage!r}; stages: {known}")
        if key is None:
            raise ValueError(f"--set {stage}: expected {stage}.KEY=VALUE")
        out.setdefault(stage, {})[key] = value
    return out


def tracker(args):
    """The MarkerPose of a command's --rig, marker, --preset / --detector and --set; with
    ``--tools`` (where the command has it), of those tool files, which define the
    geometry: a marker-geometry option given with them is a ``ValueError``."""
    from ..pipeline import MarkerPose

    tools = getattr(args, "tools", None)
    if tools:
        given = geometry_given(args)
        if given:
            raise ValueError(f"{', '.join(given)} with --tools: the tool files define the geometry; drop {', '.join(given)}")
    found = overrides(args.settings)
    detector = found.pop("detector", args.detector)
    if tools:
        return MarkerPose(rig(args.rig), markers=list(tools), preset=args.preset, detector=detector, **found)
    return MarkerPose(rig(args.rig), marker(args), preset=args.preset, detector=detector, **found)


def add_set_arg(p) -> None:
    p.add_argument(
        "--set",
        dest="settings",
        action="append",
        type=setting,
        metavar="STAGE.KEY=VALUE",
        help="a stage setting over the preset (docs/design.md §1.4), e.g. track.lost_change=0 or "
        "match.max_fits=5; also threads=N, backend=NAME, detector=NAME; repeatable",
    )


def add_rig_arg(p) -> None:
    p.add_argument("--rig", help="rig file (OpenCV YAML/XML with K1 dist1 K2 dist2 R t); default: the built-in rig")


def add_preset_args(p) -> None:
    """--preset and --detector of the commands that run the tracker (estimate, track)."""
    from ..presets import ORDER

    p.add_argument("--preset", default="default", choices=list(ORDER), help="pipeline configuration (default: default)")
    p.add_argument("--detector", choices=["neural", "classical"], help="shorthand: classical = --preset classical")
