"""Argument checks shared by the SAC solver's modules (see :mod:`dicrl_torch.solvers.sac`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dicrl_torch.checks import is_int as _is_int  # noqa: F401 (the package's name for it)


def _check_gamma(gamma: Any) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, int | float | np.floating) \
            or not 0.0 < float(gamma) < 1.0:
        raise ValueError(f"gamma must be a float in (0, 1), got {gamma!r}.")
    return float(gamma)


def _weights(value: Any, name: str, dim: int) -> np.ndarray:
    """``value`` as a finite float64 ``[dim]`` array, or a ValueError naming it."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a float vector of shape [{dim}], got {type(value).__name__}."
        ) from None
    if arr.shape != (dim,):
        raise ValueError(
            f"{name} must have shape [{dim}] (one weight per feature of its basis), got "
            f"{list(arr.shape)}."
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf values: {arr.tolist()[:8]}...")
    return arr


def _check_fraction(value: Any, name: str) -> float:
    """A batch share in ``[0, 1)`` (some of each batch must be the policy's own)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating) \
            or not 0.0 <= float(value) < 1.0:
        raise ValueError(f"{name} must be a float in [0, 1), got {value!r}: the batch needs "
                         f"some of the policy's own transitions.")
    return float(value)
