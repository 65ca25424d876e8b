"""File formats written by markerpose, in one place: strict JSON (no NaN or Infinity
tokens, which strict parsers reject: a missing or infinite figure is ``null``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def jsonable(obj):
    """``obj`` with numpy scalars and arrays as Python numbers and lists, tuples as lists,
    and every non-finite float as None."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def dumps(obj, indent: int | None = 1) -> str:
    """Strict JSON text of ``obj`` (see :func:`jsonable`)."""
    return json.dumps(jsonable(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON; returns the path."""
    path = Path(path)
    path.write_text(dumps(obj, indent) + "\n")
    return path


__all__ = ["dumps", "jsonable", "write_json"]
