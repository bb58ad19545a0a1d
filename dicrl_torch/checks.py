"""Scalar argument checks shared across the library: each returns the plain Python value
or raises a ValueError that names the argument and what it must be.

The ``setting_*`` checks are those of a run's settings (what a config sets): they raise
:class:`InvalidSetting`, whose message also gives an example that works, and which the
entry points re-raise under the config's own key (``experiments/common.py``)."""

from __future__ import annotations

import string
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["InvalidSetting", "check_finite", "check_int", "check_positive", "is_int",
           "setting_bool", "setting_choice", "setting_int", "setting_number"]


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


# ---------------------------------------------------------------------- settings
class InvalidSetting(ValueError):
    """A setting out of range or of the wrong kind. The message names it, its value, what
    it must be and an example that works::

        threshold=1.5 is invalid: it must be a number in (0, 1] (...); set e.g. threshold=0.5.

    ``must`` may name other settings its rule involves as ``{name}`` fields (e.g. a
    chunk count bounded by ``{final_timesteps}``): :meth:`renamed` renames them with the
    setting itself, so that a config reports every name as its own key.

    Attributes:
        name, value, must, example: as in the message (``must`` unformatted).
        names: how the settings named in ``must`` are called (default: as they are).
    """

    def __init__(self, name: str, value: Any, must: str, example: Any, *,
                 names: Mapping[str, str] | None = None) -> None:
        self.name, self.value, self.must, self.example = name, value, must, example
        self.names = dict(names or {})
        text = must.format_map(_AsNamed(self.names))
        super().__init__(f"{name}={value!r} is invalid: it must be {text}; set e.g. "
                         f"{name}={example}.")

    def renamed(self, keys: Mapping[str, str]) -> InvalidSetting:
        """The same error with every setting it names called as ``keys`` says (argument
        name -> e.g. config key; names ``keys`` lacks stay as they are)."""
        fields = {f for _, f, _, _ in string.Formatter().parse(self.must) if f}
        return InvalidSetting(keys.get(self.name, self.name), self.value, self.must,
                              self.example, names={f: keys.get(f, self.names.get(f, f))
                                                   for f in fields})

    def __reduce__(self):  # keyword-only names: pickle (a learner process's error) by hand
        return _invalid_setting, (self.name, self.value, self.must, self.example, self.names)


def _invalid_setting(name, value, must, example, names) -> InvalidSetting:
    return InvalidSetting(name, value, must, example, names=names)


class _AsNamed(dict):
    def __missing__(self, key: str) -> str:
        return key


def _must(what: str, why: str) -> str:
    return f"{what} ({why})" if why else what


def setting_int(name: str, value: Any, *, least: int = 1, example: Any, why: str = "",
                none: str | None = None) -> int | None:
    """``value`` as an int ``>= least``; with ``none`` (what None means) None too.

    Raises:
        InvalidSetting: anything else (a bool, a float, a string, a smaller int).
    """
    if value is None and none is not None:
        return None
    if not is_int(value) or value < least:
        what = _must(f"an int >= {least}", why)
        raise InvalidSetting(name, value, f"null ({none}) or {what}" if none else what,
                             example)
    return int(value)


def _bound(x: float) -> str:
    return f"{x:g}"


def setting_number(name: str, value: Any, *, low: float | None = None,
                   high: float | None = None, low_open: bool = False,
                   high_open: bool = False, example: Any, why: str = "",
                   none: str | None = None) -> float | None:
    """``value`` as a finite float within the bounds given (``low_open``/``high_open``:
    the bound itself excluded); with ``none`` (what None means) None too.

    Raises:
        InvalidSetting: anything else (a bool, a string, NaN, infinity, out of bounds).
    """
    if value is None and none is not None:
        return None
    ok = (not isinstance(value, bool | np.bool_)
          and isinstance(value, int | float | np.integer | np.floating)
          and bool(np.isfinite(value))
          and (low is None or (value > low if low_open else value >= low))
          and (high is None or (value < high if high_open else value <= high)))
    if not ok:
        if low is None and high is None:
            what = "a finite number"
        elif high is None:
            what = "a positive number" if low == 0 and low_open else \
                f"a number {'>' if low_open else '>='} {_bound(low)}"
        elif low is None:
            what = f"a number {'<' if high_open else '<='} {_bound(high)}"
        else:
            what = (f"a number in {'(' if low_open else '['}{_bound(low)}, {_bound(high)}"
                    f"{')' if high_open else ']'}")
        what = _must(what, why)
        raise InvalidSetting(name, value, f"null ({none}) or {what}" if none else what,
                             example)
    return None if value is None else float(value)


def setting_choice(name: str, value: Any, choices: Sequence[str], *, why: str = "",
                   example: Any = None) -> str:
    """``value``, one of the strings ``choices`` (example: the first).

    Raises:
        InvalidSetting: anything else.
    """
    if not isinstance(value, str) or value not in choices:
        listed = " or ".join(f"'{c}'" for c in choices) if len(choices) <= 2 else \
            "one of " + ", ".join(f"'{c}'" for c in choices)
        raise InvalidSetting(name, value, _must(listed, why),
                             choices[0] if example is None else example)
    return value


def setting_bool(name: str, value: Any, *, example: bool = True) -> bool:
    """``value``, a bool (numpy's too).

    Raises:
        InvalidSetting: anything else (a string such as 'no', an int).
    """
    if not isinstance(value, bool | np.bool_):
        raise InvalidSetting(name, value, "true or false", str(example).lower())
    return bool(value)
