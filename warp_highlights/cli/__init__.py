"""The ``warp-highlights`` command line: one module per command group, ``args`` for what they share.

The top layer: it may import every other sub-package (ARCHITECTURE.md). Each command module lists its
subcommands in ``COMMANDS``; ``app`` builds the parser from ``app.COMMAND_MODULES`` and runs it.

- ``main``: run the command line with a list of arguments; returns the exit status.
- ``run_demo``: the ``demo`` command as a function: render, fit, evaluate and animate into one folder.
- ``EXIT_INPUT_ERROR``: the exit status after bad input (2), with one line on stderr.
- ``EXIT_INTERRUPTED``: the exit status after Ctrl-C (130).
- ``EXIT_TERMINATED``: the exit status after SIGTERM (143).
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["main", "EXIT_INPUT_ERROR", "EXIT_INTERRUPTED", "EXIT_TERMINATED"], "app"),
        "run_demo": "demo",
    },
)
