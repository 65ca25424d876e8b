"""The schema of the pipeline's settings: each stage states what each of its keys takes.

A stage module holds ``default_conf`` (the values) and ``RULES`` (what each key takes,
built with :func:`number`, :func:`flag`, :func:`choice` and :func:`path`);
:func:`markerpose.presets.resolve` checks every stage's settings against its rules once,
for the API and the command line's ``--set`` alike, and names the stage, the key and
what it takes when a value does not fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Rule:
    """What one setting takes: ``test(value)`` is None when it fits, else what it takes."""

    test: Callable[[object], str | None]


def number(lo: float = -math.inf, hi: float = math.inf, *, above: bool = False, integer: bool = False, no_limit: bool = False) -> Rule:
    """A finite number in [lo, hi] (``above``: greater than ``lo``); ``integer``: whole;
    ``no_limit``: also +inf (a tolerance that then checks nothing)."""
    kind = "a whole number" if integer else "a number"
    span = f" {'>' if above else '>='} {lo:g}" if math.isfinite(lo) else ""
    if math.isfinite(hi):
        span = f" in {'(' if above else '['}{lo:g}, {hi:g}]" if math.isfinite(lo) else f" <= {hi:g}"
    want = kind + span + (" or inf (no limit)" if no_limit else "")

    def test(v):
        if no_limit and isinstance(v, (int, float)) and not isinstance(v, bool) and v == math.inf:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return want
        if integer and v != int(v):
            return want
        if v < lo or v > hi or (above and v == lo):
            return want
        return None

    return Rule(test)


def flag(optional: bool = False) -> Rule:
    """True or False; with ``optional`` also None (a default decided where it is used)."""
    if optional:
        return Rule(lambda v: None if v is None or isinstance(v, bool) else "true, false or null")
    return Rule(lambda v: None if isinstance(v, bool) else "true or false")


def choice(*options: str) -> Rule:
    """One of ``options``."""
    return Rule(lambda v: None if v in options else f"one of {list(options)}")


def path() -> Rule:
    """A file's path, or None (the default)."""
    return Rule(lambda v: None if v is None or isinstance(v, str) or hasattr(v, "__fspath__") else "a file's path or None")


def check(stage: str, conf: dict, rules: dict[str, Rule]) -> dict:
    """``conf`` if every key is known and fits its rule, else ``ValueError`` naming
    ``stage.key``, the value and what it takes."""
    for key, value in conf.items():
        if key not in rules:
            raise ValueError(f"unknown {stage} setting {key!r}; known: {sorted(rules)}")
        want = rules[key].test(value)
        if want is not None:
            raise ValueError(f"{stage}.{key} must be {want}, got {value!r}")
    return conf


__all__ = ["Rule", "check", "choice", "flag", "number", "path"]
