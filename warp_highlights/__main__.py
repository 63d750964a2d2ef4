"""``python -m warp_highlights``: the same as the ``warp-highlights`` command."""

from .cli.console import run

run()
