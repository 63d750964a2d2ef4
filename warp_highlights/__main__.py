"""``python -m warp_highlights``: the same as the ``warp-highlights`` command."""

import sys

from .cli.main import main

sys.exit(main())
