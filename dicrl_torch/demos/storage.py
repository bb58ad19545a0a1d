"""Expert demonstrations in memory and on disk (docs/design.md §2, §3).

A set of ``m`` demonstrations of ``N`` experts over a horizon ``T`` is two integer
arrays: the per-expert cells visited, ``states [m, T+1, N]``, and the per-expert
actions taken, ``actions [m, T, N]``. On disk they live in an ``.npz`` archive that is
read with ``allow_pickle=False``: nothing is ever unpickled, and every field is
checked against a fixed schema so a stale or damaged file fails loudly, naming the
file, the field and the fix.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from dicrl_torch.demos.npz import (
    check_expected,
    check_ndim,
    frozen,
    is_int,
    open_archive,
    read_field,
    read_scalar,
    refuse_first,
    save_archive,
)
from dicrl_torch.demos.trajectories import TrajectoryArrays

FORMAT_VERSION = 1
ARRAY_FIELDS: tuple[str, ...] = ("states", "actions")
SCALAR_FIELDS: tuple[str, ...] = ("n_cells", "n_actions", "format_version")
FIELDS: tuple[str, ...] = ARRAY_FIELDS + SCALAR_FIELDS


def _check_integer_array(a: np.ndarray, field: str, source: str) -> None:
    if np.issubdtype(a.dtype, np.integer):
        return
    hint = f"store it as integers, e.g. `{field}.astype(np.int64)`"
    if np.issubdtype(a.dtype, np.inexact) and not np.all(np.isfinite(a)):
        raise ValueError(
            f"{source}: field '{field}' has float dtype {a.dtype} and contains NaN or "
            f"inf values; {field} must be integer indices. Regenerate the demonstrations."
        )
    raise ValueError(
        f"{source}: field '{field}' has dtype {a.dtype}, but it must be an integer array; "
        f"{hint}."
    )


def _check_range(a: np.ndarray, field: str, upper: int, source: str) -> None:
    refuse_first((a < 0) | (a >= upper), lambda m, t, i: (
        f"{source}: field '{field}' holds {int(a[m, t, i])} at (trajectory={m}, "
        f"time={t}, expert={i}), outside [0, {upper}). The data does not match "
        f"{'n_cells' if field == 'states' else 'n_actions'}={upper}; regenerate it "
        f"for this configuration."))


def validate_arrays(
    states: ArrayLike, actions: ArrayLike, n_cells: int, n_actions: int, *, source: str
) -> None:
    """Check demonstration arrays against the schema; raise ``ValueError`` if not.

    Args:
        states: ``[m, T+1, N]`` integer cell indices in ``[0, n_cells)``.
        actions: ``[m, T, N]`` integer action indices in ``[0, n_actions)``.
        n_cells: number of cells ``S1`` of one expert.
        n_actions: number of actions ``A1`` of one expert.
        source: what the arrays came from (a file path, a class name), put at the
            start of every error message.

    Raises:
        ValueError: naming ``source``, the offending field and the fix.
    """
    for name, value in (("n_cells", n_cells), ("n_actions", n_actions)):
        if not is_int(value) or value < 1:
            raise ValueError(f"{source}: field '{name}' must be a positive int, got {value!r}.")
    states, actions = np.asarray(states), np.asarray(actions)
    _check_integer_array(states, "states", source)
    _check_integer_array(actions, "actions", source)
    check_ndim(states, "states", 3, "[m, T+1, N]", source)
    check_ndim(actions, "actions", 3, "[m, T, N]", source)
    m, t1, n = states.shape
    if m == 0:
        raise ValueError(
            f"{source}: field 'states' holds zero trajectories (shape {states.shape}); "
            f"generate at least one demonstration."
        )
    if t1 < 2 or n < 1:
        raise ValueError(
            f"{source}: field 'states' shape {states.shape} needs T+1 >= 2 time steps and "
            f"N >= 1 experts."
        )
    if actions.shape != (m, t1 - 1, n):
        raise ValueError(
            f"{source}: field 'actions' has shape {actions.shape}, but states "
            f"{states.shape} = [m, T+1, N] requires actions of shape {(m, t1 - 1, n)} "
            f"= [m, T, N]."
        )
    _check_range(states, "states", n_cells, source)
    _check_range(actions, "actions", n_actions, source)


@dataclass(frozen=True, eq=False, repr=False)
class Demonstrations(TrajectoryArrays):
    """Trajectories of ``N`` experts, validated on construction (a
    :class:`~dicrl_torch.demos.trajectories.Trajectories`; equal by content).

    The arrays are copied to read-only int64 so the object really is immutable.

    Args:
        states: ``[m, T+1, N]`` int cell index of each expert at each time.
        actions: ``[m, T, N]`` int action index (``0..n_actions-1``) of each expert.
        n_cells: cells per expert ``S1``.
        n_actions: actions per expert ``A1`` (9 in the grid world).
    """

    states: np.ndarray
    actions: np.ndarray
    n_cells: int
    n_actions: int

    def __post_init__(self) -> None:
        validate_arrays(
            self.states, self.actions, self.n_cells, self.n_actions, source="Demonstrations"
        )
        for name in ARRAY_FIELDS:
            # Range already checked, so the cast to int64 is lossless.
            object.__setattr__(self, name, frozen(getattr(self, name), np.int64))
        object.__setattr__(self, "n_cells", int(self.n_cells))
        object.__setattr__(self, "n_actions", int(self.n_actions))

    @property
    def n_experts(self) -> int:
        """``N``."""
        return self.states.shape[2]

    def __repr__(self) -> str:
        return (
            f"Demonstrations(m={self.n_trajectories}, T={self.horizon}, N={self.n_experts}, "
            f"n_cells={self.n_cells}, n_actions={self.n_actions})"
        )


def _archive_fields(demos: Demonstrations) -> dict[str, np.ndarray]:
    return {"states": demos.states, "actions": demos.actions,
            "n_cells": np.int64(demos.n_cells), "n_actions": np.int64(demos.n_actions),
            "format_version": np.int64(FORMAT_VERSION)}


def save_demonstrations(path: str | os.PathLike[str], demos: Demonstrations) -> Path:
    """Write ``demos`` to ``path`` for :func:`load_demonstrations`: a compressed ``.npz``,
    written atomically by :func:`~dicrl_torch.demos.npz.save_archive` (no suffix is
    appended, parent directories are created); return the path."""
    return save_archive(path, demos, Demonstrations, fields=_archive_fields,
                        writer="save_demonstrations",
                        how="wrap the arrays with Demonstrations(states=..., actions=..., ...)")


def load_demonstrations(
    path: str | os.PathLike[str],
    *,
    n_cells: int | None = None,
    n_actions: int | None = None,
    n_experts: int | None = None,
    horizon: int | None = None,
) -> Demonstrations:
    """Read demonstrations written by :func:`save_demonstrations`, never unpickling.

    Args:
        path: the ``.npz`` file.
        n_cells, n_actions, n_experts, horizon: when given, the file must have been
            made for exactly this configuration.

    Returns:
        The validated demonstrations.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a valid demonstrations archive or does not match
            the expected configuration; the message names the file, the field and
            the fix.
    """
    path = Path(path)
    source = f"demonstrations file '{path}'"
    fix = "save_demonstrations"
    with open_archive(path, source=source, required=FIELDS, version=FORMAT_VERSION, fix=fix,
                      generate="Generate the demonstrations first") as archive:
        file_cells = read_scalar(archive, "n_cells", source, fix)
        file_actions = read_scalar(archive, "n_actions", source, fix)
        states = read_field(archive, "states", source, fix)
        actions = read_field(archive, "actions", source, fix)
    # Validate here, not only in Demonstrations, so the messages name the file.
    validate_arrays(states, actions, file_cells, file_actions, source=source)
    found = {
        "n_cells": file_cells, "n_actions": file_actions,
        "n_experts": states.shape[2], "horizon": actions.shape[1],
    }
    check_expected(
        source, found,
        {"n_cells": n_cells, "n_actions": n_actions, "n_experts": n_experts, "horizon": horizon},
    )
    return Demonstrations(
        states=states, actions=actions, n_cells=file_cells, n_actions=file_actions
    )
