"""The ``warp-highlights`` command line: one module per command group, ``args`` for what they share.

The top layer: it may import every other sub-package (ARCHITECTURE.md). A new command goes into the
module of its group (or a new one), registered in ``main._build_parser`` in the order ``--help`` lists it.

- ``main``: run the command line with a list of arguments; returns the exit status.
- ``run_demo``: the ``demo`` command as a function: render, fit, evaluate and animate into one folder.
"""

from .demo import run_demo
from .main import main  # the function (it shadows the module of the same name, as it should)

__all__ = ["main", "run_demo"]
