"""``python -m markerpose.cli``: the ``markerpose`` command."""

import sys

from . import main

sys.exit(main())
