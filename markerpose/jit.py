"""Compiled loops: numba's ``njit``, cached on disk where numba can write its cache.

numba keeps compiled code beside the module (``__pycache__``) or, when that is
read-only, in the user's cache directory. Where neither is writable (a read-only
install run by a user without a home, as in some containers) ``cache=True`` fails at
import; there the loops are compiled once per process instead.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from .signals import held_interrupt

# Floating-point rewrites that keep NaN and infinity semantics (no "nnan" / "ninf": the loops'
# ``not x > 0`` tests must still see a NaN): contraction into fused multiply-adds, reassociation,
# reciprocals and approximate library functions, so that LLVM can vectorise and reorder.
FAST_MATH = frozenset({"contract", "afn", "reassoc", "arcp", "nsz"})


def compiled(fn=None, *, fast: bool = False):
    """``fn`` compiled by numba (nopython, releasing the GIL), its machine code cached on
    disk when there is somewhere to write it; with ``fast`` (``@compiled(fast=True)``) under
    :data:`FAST_MATH`, for loops whose results may move in the last bits."""
    if fn is None:
        return lambda f: compiled(f, fast=fast)
    opts = {"nogil": True, **({"fastmath": set(FAST_MATH)} if fast else {})}
    try:
        return numba.njit(cache=True, **opts)(fn)
    except RuntimeError:  # numba found no writable cache location
        return numba.njit(**opts)(fn)


class CompileError(RuntimeError):
    """The compiled loops could not be built with the installed numpy / numba."""


def warm_up(*steps: Callable[[], None]) -> None:
    """Run each module's warm-up (which compiles its loops, or loads them from the cache),
    a Ctrl-C held until it ends; a typing failure, which a numpy or numba outside the tested
    ranges can cause, becomes one :class:`CompileError` that names the versions and the fix
    instead of numba's page-long trace at the first frame."""
    try:
        with held_interrupt():  # a Ctrl-C inside LLVM's callbacks is printed and lost, not raised: held to the end
            for step in steps:
                step()
    except numba.core.errors.NumbaError as exc:
        first = next((line for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise CompileError(
            f"markerpose's compiled loops do not build with numpy {np.__version__} and numba {numba.__version__} "
            f"({first.strip()}); install the versions markerpose declares and tests, e.g. "
            f"pip install 'numpy>=1.23,<2.5' 'numba>=0.60,<0.69', and report the versions that failed"
        ) from exc


__all__ = ["CompileError", "compiled", "warm_up"]
