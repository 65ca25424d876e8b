"""Tools: markers told apart by the layout of their rings.

A tool is a :class:`~markerpose.marker.Marker` with a name, kept in a YAML file
(:meth:`Marker.load`). Several tools in one scene are told apart by the 3D shape of their
three ring centres, which stereo measures to a few hundredths of a millimetre: a triple
of rings is taken for a tool only when the centres' RMS distance from the tool's layout,
after the best rigid placement, is within ``verify.max_shape_error`` (2 mm by default).
Two layouts are therefore told apart with margin when that distance between them, over
every order of the rings (a triple's naming is not known in advance), is at least
:data:`MIN_DIFFERENCE_MM`: twice the acceptance limit, many times what the measurement
itself moves it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .marker import Marker
from .stages.verify import default_conf as verify_conf
from .stages.verify import shape_error

MIN_DIFFERENCE_MM = 2 * verify_conf["max_shape_error"]
MIN_GAP_MM = 5.0  # between two rings' outer edges in a generated layout
MAX_PLATE_MM = 100.0  # a generated tool's plate fits in a square of this side


def layout_difference(a: Marker, b: Marker) -> float:
    """The least RMS distance (mm) between ``a``'s ring centres and ``b``'s, over rigid
    placements and every order of ``b``'s rings: how far apart stereo sees the layouts."""
    A, B = a.points3d, b.points3d
    return min(shape_error(B[list(order)], A) for order in itertools.permutations(range(3)))


def check_tools(tools: Sequence[Marker], sources: Sequence[str] | None = None) -> list[Marker]:
    """``tools`` if their names are distinct and every two layouts differ by at least
    :data:`MIN_DIFFERENCE_MM` (:func:`layout_difference`), else ``ValueError`` naming the
    two (by ``sources``, e.g. their files, where given)."""
    tools = list(tools)
    where = list(sources) if sources is not None else [t.name for t in tools]
    for i, j in itertools.combinations(range(len(tools)), 2):
        if tools[i].name == tools[j].name:
            raise ValueError(f"{where[i]} and {where[j]}: two tools named {tools[i].name!r}; each tool needs its own name")
        d = layout_difference(tools[i], tools[j])
        if d < MIN_DIFFERENCE_MM:
            raise ValueError(
                f"{where[i]} and {where[j]}: the layouts of {tools[i].name!r} and {tools[j].name!r} differ by {d:.2f} mm, "
                f"under the {MIN_DIFFERENCE_MM:g} mm that tells tools apart; move a ring (markerpose tools --count N "
                "makes a set that is told apart)"
            )
    return tools


def load_tools(paths: Sequence[str | Path]) -> list[Marker]:
    """The tools of these files (:meth:`Marker.load`), checked to be told apart (:func:`check_tools`)."""
    return check_tools([Marker.load(p) for p in paths], [str(p) for p in paths])


def _candidates(base: Marker) -> list[Marker]:
    """Layouts near the paper's: c1 25-45 mm along +x, c2 35-60 mm at 70-110° (c0 the
    corner, c1 the nearer ring), rings apart by ``MIN_GAP_MM``, the plate within
    ``MAX_PLATE_MM``; the rings' sizes and the margin of ``base``."""
    out = []
    for d01, d02, angle in itertools.product(np.arange(25, 46, 2.5), np.arange(35, 61, 2.5), np.arange(70, 111, 5)):
        if d02 < d01 + 5:
            continue
        c2 = (round(float(d02 * np.cos(np.radians(angle))), 1), round(float(d02 * np.sin(np.radians(angle))), 1))  # printable to 0.1 mm
        try:
            m = Marker(base.outer_diameter, base.inner_diameter, (float(d01), 0.0), c2, base.margin)
        except ValueError:
            continue
        c = m.centers2d
        gaps = [np.linalg.norm(c[i] - c[j]) - m.outer_diameter for i, j in ((0, 1), (0, 2), (1, 2))]
        x0, y0, x1, y1 = m.plate
        if min(gaps) >= MIN_GAP_MM and max(x1 - x0, y1 - y0) <= MAX_PLATE_MM:
            out.append(m)
    return out


def tool_set(count: int, base: Marker | None = None, prefix: str = "tool") -> list[Marker]:
    """``count`` tools named ``{prefix}1``... whose layouts are told apart: the first is
    ``base``'s layout (the paper's marker by default), each next the candidate layout
    farthest (:func:`layout_difference`) from those chosen (a greedy max-min choice, so the
    least difference is as large as this simple search finds)."""
    if not 1 <= int(count) <= 12:
        raise ValueError(f"count must be 1 to 12 tools, got {count!r}")
    base = base or Marker()
    chosen = [base]
    cands = _candidates(base)
    nearest = np.full(len(cands), np.inf)  # each candidate's least difference from those chosen
    while len(chosen) < count:
        nearest = np.minimum(nearest, [layout_difference(c, chosen[-1]) for c in cands])
        chosen.append(cands[int(np.argmax(nearest))])
    tools = [Marker(m.outer_diameter, m.inner_diameter, m.c1, m.c2, m.margin, name=f"{prefix}{k + 1}") for k, m in enumerate(chosen)]
    return check_tools(tools)


def least_difference(tools: Sequence[Marker]) -> float:
    """The smallest :func:`layout_difference` between two of ``tools`` (inf for fewer than two)."""
    return min((layout_difference(a, b) for a, b in itertools.combinations(tools, 2)), default=float("inf"))


__all__ = [
    "MAX_PLATE_MM",
    "MIN_DIFFERENCE_MM",
    "MIN_GAP_MM",
    "check_tools",
    "layout_difference",
    "least_difference",
    "load_tools",
    "tool_set",
]
