"""Compiled loops: numba's ``njit``, cached on disk where numba can write its cache.

numba keeps compiled code beside the module (``__pycache__``) or, when that is
read-only, in the user's cache directory. Where neither is writable (a read-only
install run by a user without a home, as in some containers) ``cache=True`` fails at
import; there the loops are compiled once per process instead.
"""

from __future__ import annotations

import numba


def compiled(fn):
    """``fn`` compiled by numba (nopython, releasing the GIL), its machine code cached on
    disk when there is somewhere to write it."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # numba found no writable cache location
        return numba.njit(nogil=True)(fn)


__all__ = ["compiled"]
