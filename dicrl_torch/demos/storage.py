"""Expert demonstrations in memory and on disk (DESIGN §2, §3).

A set of ``m`` demonstrations of ``N`` experts over a horizon ``T`` is two integer
arrays: the per-expert cells visited, ``states [m, T+1, N]``, and the per-expert
actions taken, ``actions [m, T, N]``. On disk they live in an ``.npz`` archive that is
read with ``allow_pickle=False``: nothing is ever unpickled, and every field is
checked against a fixed schema so a stale or damaged file fails loudly, naming the
file, the field and the fix.
"""

from __future__ import annotations

import os
import uuid
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

FORMAT_VERSION = 1
ARRAY_FIELDS: tuple[str, ...] = ("states", "actions")
SCALAR_FIELDS: tuple[str, ...] = ("n_cells", "n_actions", "format_version")
FIELDS: tuple[str, ...] = ARRAY_FIELDS + SCALAR_FIELDS

# What np.load / zipfile / zlib raise on a damaged archive or member.
_READ_ERRORS = (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, KeyError)


def _is_int(x: object) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


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
    bad = (a < 0) | (a >= upper)
    if bad.any():
        m, t, i = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(
            f"{source}: field '{field}' holds {int(a[m, t, i])} at (trajectory={m}, "
            f"time={t}, expert={i}), outside [0, {upper}). The data does not match "
            f"{'n_cells' if field == 'states' else 'n_actions'}={upper}; regenerate it "
            f"for this configuration."
        )


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
        if not _is_int(value) or value < 1:
            raise ValueError(f"{source}: field '{name}' must be a positive int, got {value!r}.")
    states, actions = np.asarray(states), np.asarray(actions)
    _check_integer_array(states, "states", source)
    _check_integer_array(actions, "actions", source)
    if states.ndim != 3:
        raise ValueError(
            f"{source}: field 'states' must have shape [m, T+1, N] (3 dims), got shape "
            f"{states.shape}."
        )
    if actions.ndim != 3:
        raise ValueError(
            f"{source}: field 'actions' must have shape [m, T, N] (3 dims), got shape "
            f"{actions.shape}."
        )
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
class Demonstrations:
    """Trajectories of ``N`` experts, validated on construction.

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
            a = np.array(getattr(self, name), dtype=np.int64, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "n_cells", int(self.n_cells))
        object.__setattr__(self, "n_actions", int(self.n_actions))

    @property
    def n_trajectories(self) -> int:
        """``m``."""
        return self.states.shape[0]

    @property
    def horizon(self) -> int:
        """``T``, the number of decisions per trajectory."""
        return self.actions.shape[1]

    @property
    def n_experts(self) -> int:
        """``N``."""
        return self.states.shape[2]

    def subset(self, indices: ArrayLike) -> Demonstrations:
        """The trajectories at ``indices`` (1-D ints, in that order, or a ``[m]`` bool
        mask) as new demonstrations."""
        idx = np.asarray(indices)
        if idx.dtype == np.bool_:
            if idx.shape != (self.n_trajectories,):
                raise ValueError(
                    f"A boolean subset mask must have shape ({self.n_trajectories},), got "
                    f"{idx.shape}."
                )
            idx = np.flatnonzero(idx)
        if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(
                f"subset indices must be a 1-D sequence of ints, got dtype {idx.dtype} "
                f"shape {idx.shape}."
            )
        if idx.size and (idx.min() < -self.n_trajectories or idx.max() >= self.n_trajectories):
            raise ValueError(
                f"subset indices must lie in [0, {self.n_trajectories}), got "
                f"[{idx.min()}, {idx.max()}]."
            )
        idx = idx.astype(np.int64)
        return Demonstrations(
            states=self.states[idx], actions=self.actions[idx],
            n_cells=self.n_cells, n_actions=self.n_actions,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Demonstrations):
            return NotImplemented
        return (
            self.n_cells == other.n_cells and self.n_actions == other.n_actions
            and np.array_equal(self.states, other.states)
            and np.array_equal(self.actions, other.actions)
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-by-content arrays: unhashable

    def __repr__(self) -> str:
        return (
            f"Demonstrations(m={self.n_trajectories}, T={self.horizon}, N={self.n_experts}, "
            f"n_cells={self.n_cells}, n_actions={self.n_actions})"
        )


def save_demonstrations(path: str | os.PathLike[str], demos: Demonstrations) -> Path:
    """Write ``demos`` to ``path`` as a compressed ``.npz``, atomically.

    The archive is written to a temporary file next to ``path`` and moved into place
    with ``os.replace``, so a crash never leaves a half-written file under ``path``.
    ``path`` is used as given (no ``.npz`` suffix is appended); parent directories are
    created.

    Returns:
        The path written.
    """
    if not isinstance(demos, Demonstrations):
        raise TypeError(
            f"save_demonstrations expects a Demonstrations, got {type(demos).__name__}; "
            f"wrap the arrays with Demonstrations(states=..., actions=..., ...)."
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    # os.open with mode 0o666 lets the umask decide the final permissions, as for a
    # plain open(); O_EXCL guards against clobbering anything.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            # A file object, not a name: np.savez would otherwise append ".npz".
            np.savez_compressed(
                f,
                states=demos.states,
                actions=demos.actions,
                n_cells=np.int64(demos.n_cells),
                n_actions=np.int64(demos.n_actions),
                format_version=np.int64(FORMAT_VERSION),
            )
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _read_scalar(archive: np.lib.npyio.NpzFile, field: str, source: str) -> int:
    a = _read_field(archive, field, source)
    if a.ndim != 0 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(
            f"{source}: field '{field}' must be an integer scalar, got dtype {a.dtype} "
            f"shape {a.shape}. Re-save the file with save_demonstrations."
        )
    return int(a)


def _read_field(archive: np.lib.npyio.NpzFile, field: str, source: str) -> np.ndarray:
    try:
        return archive[field]
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise ValueError(
                f"{source}: field '{field}' is an object (pickled) array, which is never "
                f"loaded for safety; store it as an integer array and re-save with "
                f"save_demonstrations."
            ) from e
        raise ValueError(
            f"{source}: field '{field}' cannot be read ({e}); the file is corrupt. "
            f"Regenerate it with save_demonstrations."
        ) from e
    except _READ_ERRORS as e:
        raise ValueError(
            f"{source}: field '{field}' cannot be read ({type(e).__name__}: {e}); the file "
            f"is truncated or corrupt. Regenerate it with save_demonstrations."
        ) from e


def _read_archive(
    archive: np.lib.npyio.NpzFile, source: str
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Check the field names and version, then read ``states, actions, n_cells,
    n_actions`` (not yet validated against each other)."""
    names = set(archive.files)
    missing = [f for f in FIELDS if f not in names]
    if missing:
        raise ValueError(
            f"{source}: missing field(s) {missing}; a demonstrations file needs "
            f"{list(FIELDS)}. Re-save it with save_demonstrations."
        )
    unknown = sorted(names - set(FIELDS))
    if unknown:
        raise ValueError(
            f"{source}: unknown field(s) {unknown}; a demonstrations file holds only "
            f"{list(FIELDS)}. Re-save it with save_demonstrations."
        )
    # The version first: a newer layout could make every other check misleading.
    version = _read_scalar(archive, "format_version", source)
    if version != FORMAT_VERSION:
        raise ValueError(
            f"{source}: field 'format_version' is {version}, but this code reads only "
            f"version {FORMAT_VERSION}; regenerate the file with this version of "
            f"dicrl_torch."
        )
    n_cells = _read_scalar(archive, "n_cells", source)
    n_actions = _read_scalar(archive, "n_actions", source)
    states = _read_field(archive, "states", source)
    actions = _read_field(archive, "actions", source)
    return states, actions, n_cells, n_actions


def _check_expected(source: str, found: dict[str, int], expected: dict[str, int | None]) -> None:
    for name, want in expected.items():
        if want is not None and found[name] != want:
            raise ValueError(
                f"{source}: field '{name}' is {found[name]} in the file but {want} was "
                f"expected; the file was made for a different configuration. Regenerate "
                f"the demonstrations for this configuration or point to the matching file."
            )


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
    if not path.is_file():
        raise FileNotFoundError(
            f"No {source}: it does not exist or is not a file. Generate the "
            f"demonstrations first, or fix the path."
        )
    # Open the file ourselves so it is closed on every path: np.load leaks its handle
    # when the archive turns out unreadable.
    with open(path, "rb") as fh:
        try:
            archive = np.load(fh, allow_pickle=False)
        except _READ_ERRORS as e:
            # numpy's own text for a non-array file suggests unpickling it; do not echo it.
            why = ("not an array file" if "pickle" in str(e)
                   else f"{type(e).__name__}: {e}")
            raise ValueError(
                f"{source} cannot be opened as an .npz archive ({why}); it is truncated, "
                f"corrupt or not an .npz. Regenerate it with save_demonstrations."
            ) from e
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise ValueError(
                f"{source} holds a single .npy array, not an .npz archive with fields "
                f"{list(FIELDS)}; re-save it with save_demonstrations."
            )
        with archive:
            states, actions, file_cells, file_actions = _read_archive(archive, source)
    # Validate here, not only in Demonstrations, so the messages name the file.
    validate_arrays(states, actions, file_cells, file_actions, source=source)
    found = {
        "n_cells": file_cells, "n_actions": file_actions,
        "n_experts": states.shape[2], "horizon": actions.shape[1],
    }
    _check_expected(
        source, found,
        {"n_cells": n_cells, "n_actions": n_actions, "n_experts": n_experts, "horizon": horizon},
    )
    return Demonstrations(
        states=states, actions=actions, n_cells=file_cells, n_actions=file_actions
    )
