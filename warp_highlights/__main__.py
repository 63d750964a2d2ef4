"""``python -m warp_highlights``: the same as the ``warp-highlights`` command."""

import sys

from .cli.app import main

sys.exit(main())
