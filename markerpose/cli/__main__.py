"""``python -m markerpose.cli``: the ``markerpose`` command."""

from . import console

console()
