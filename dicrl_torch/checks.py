"""Scalar argument checks shared across the library: each returns the plain Python value
or raises a ValueError that names the argument and what it must be."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["check_finite", "check_int", "check_positive", "is_int"]


def is_int(x: Any) -> bool:
    """An int (Python or numpy), and not a bool."""
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def check_int(name: str, value: Any, least: int = 1) -> int:
    """``value`` as an int ``>= least``."""
    if not is_int(value) or value < least:
        what = "a positive int" if least == 1 else f"an int >= {least}"
        raise ValueError(f"{name} must be {what}, got {value!r}.")
    return int(value)


def check_finite(name: str, value: Any) -> float:
    """``value`` as a finite float (ints and numpy scalars accepted, bools not)."""
    if isinstance(value, bool | np.bool_) \
            or not isinstance(value, int | float | np.integer | np.floating) \
            or not np.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}.")
    return float(value)


def check_positive(name: str, value: Any) -> float:
    """``value`` as a finite float ``> 0``."""
    if isinstance(value, bool | np.bool_) \
            or not isinstance(value, int | float | np.integer | np.floating) \
            or not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}.")
    return float(value)
