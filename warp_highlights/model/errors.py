"""The one exception type for bad user input, and the array check the model's containers share.

Every message is a single line that says what is wrong, where (file, line) and what to do. The CLI
prints it and exits non-zero; library users catch it like any ``ValueError``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["InputError", "finite_array"]


class InputError(ValueError):
    """Bad user input: a malformed file, a missing image, an impossible parameter.

    Args:
        message: One line: what is wrong, where, and what to do about it.
    """

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def finite_array(value, dtype, name: str) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype``; every element finite after the conversion.

    Raises ``InputError`` naming ``name`` for a non-numeric or complex array, and for non-finite
    values (including values beyond ``dtype``'s range).
    """
    try:
        array = np.asarray(value)
        if not (np.issubdtype(array.dtype, np.number) or array.dtype == bool) or np.iscomplexobj(array):
            raise TypeError(array.dtype)
        with np.errstate(over="ignore", invalid="ignore"):
            array = np.ascontiguousarray(array, dtype=dtype)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real numeric array") from None
    if not np.all(np.isfinite(array)):
        limit = "" if dtype == np.float64 else f" or beyond the {np.dtype(dtype).name} range"
        raise InputError(f"{name} has non-finite values{limit}")
    return array
