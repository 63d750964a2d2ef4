"""The one exception type for bad user input.

Every message is a single line that says what is wrong, where (file, line) and what to do. The CLI
prints it and exits non-zero; library users catch it like any ``ValueError``.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad user input: a malformed file, a missing image, an impossible parameter.

    Args:
        message: One line: what is wrong, where, and what to do about it.
    """

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))
