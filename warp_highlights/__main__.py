"""``python -m warp_highlights``: the same as the ``warp-highlights`` command."""

from .cli.console import run

if __name__ == "__main__":  # not when a spawned process (a Dask worker) imports the main module again
    run()
