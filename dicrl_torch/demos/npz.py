"""Safe ``.npz`` archives for demonstrations (grid, drone and continuous alike), and the
small array helpers their schemas share.

Writes are atomic (a temporary file moved into place). Reads never unpickle
(``allow_pickle=False``), check the field names against a schema and turn every
failure into a ``ValueError`` that names the file, the field and the fix; ``fix`` is the
function that writes a good file (e.g. ``"save_demonstrations"``).
"""

from __future__ import annotations

import os
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from dicrl_torch.io import atomic_write

# What np.load / zipfile / zlib raise on a damaged archive or member.
READ_ERRORS = (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, KeyError)


def is_int(x: object) -> bool:
    """Whether ``x`` is a Python or numpy integer (bools are not)."""
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def frozen(array: ArrayLike, dtype: DTypeLike) -> np.ndarray:
    """A read-only copy of ``array`` as ``dtype`` (the fields of immutable
    demonstrations)."""
    out = np.array(array, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def check_float_dtype(a: np.ndarray, field: str, source: str) -> None:
    """Refuse a non-float ``a``, naming ``source``, the ``field`` and the fix."""
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(
            f"{source}: field '{field}' has dtype {a.dtype}, but it must be a float array; "
            f"store it as `{field}.astype(np.float64)`.")


def pad_episodes(episodes: Sequence[tuple[np.ndarray, np.ndarray]]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stack episodes of different lengths into padded arrays.

    Args:
        episodes: per episode ``states [L+1, ...]`` and ``actions [L, ...]`` (one shape
            per step across all of them).

    Returns:
        float64 ``states [m, T+1, ...]`` (each episode's last state repeated after its
        end), float64 ``actions [m, T, ...]`` (0 after the end) and int64 ``lengths
        [m]`` (the ``L``), with ``T`` the longest ``L``.
    """
    lengths = np.array([len(a) for _, a in episodes], dtype=np.int64)
    horizon = int(lengths.max())
    s0, a0 = episodes[0]
    states = np.empty((len(episodes), horizon + 1, *s0.shape[1:]))
    actions = np.zeros((len(episodes), horizon, *a0.shape[1:]))
    for k, (s, a) in enumerate(episodes):
        states[k, :len(s)] = s
        states[k, len(s):] = s[-1]
        actions[k, :len(a)] = a
    return states, actions, lengths


def atomic_savez(path: str | os.PathLike[str], fields: Mapping[str, np.ndarray]) -> Path:
    """Write ``fields`` to ``path`` as a compressed ``.npz``, atomically.

    Through :func:`dicrl_torch.io.atomic_write`: a crash never leaves a half-written file
    under ``path``. ``path`` is used as given (no ``.npz`` suffix is appended).
    """
    # A file object, not a name: np.savez would otherwise append ".npz".
    return atomic_write(path, lambda f: np.savez_compressed(f, **fields))


def check_ndim(a: np.ndarray, field: str, ndim: int, layout: str, source: str,
               hint: str = "") -> None:
    """Refuse ``a`` unless it has ``ndim`` dims, naming ``source``, the ``field``, its
    ``layout`` (e.g. ``"[m, T, N]"``) and maybe a ``hint`` (``"; ..."``) on the fix."""
    if a.ndim != ndim:
        raise ValueError(f"{source}: field '{field}' must have {ndim} dims {layout}, got "
                         f"shape {a.shape}{hint}.")


def refuse_first(bad: np.ndarray, message: Callable[..., str]) -> None:
    """Raise ``ValueError(message(*index))`` at the first True entry of ``bad`` (C order;
    its index as ints), if any: how a check names the first offending entry."""
    hits = np.argwhere(bad)
    if len(hits):
        raise ValueError(message(*(int(v) for v in hits[0])))


def check_lengths(lengths: np.ndarray, m: int, horizon: int, source: str, unit: str) -> None:
    """Refuse ``lengths`` unless it holds ``[m]`` ints in ``[1, horizon]``: the steps each
    of ``m`` trajectories took (``unit``: what messages call one, e.g. ``"episode"``)."""
    if not np.issubdtype(lengths.dtype, np.integer) or lengths.shape != (m,):
        raise ValueError(
            f"{source}: field 'lengths' must be an integer array of shape ({m},) (one "
            f"length per {unit} of 'states'), got dtype {lengths.dtype} shape "
            f"{lengths.shape}; store `lengths.astype(np.int64)`.")
    refuse_first((lengths < 1) | (lengths > horizon), lambda k: (
        f"{source}: field 'lengths' holds {int(lengths[k])} for {unit} {k}, outside "
        f"[1, T={horizon}]; a length counts the steps the {unit} took. Fix the length, or "
        f"drop a {unit} without steps."))


def check_seeds(seeds: ArrayLike | None, m: int, source: str, unit: str) -> None:
    """Refuse ``seeds`` unless it is None or ``[m]`` non-negative ints: the reset seed of
    each of ``m`` trajectories (``unit``: what messages call one)."""
    if seeds is None:
        return
    seeds = np.asarray(seeds)
    if not np.issubdtype(seeds.dtype, np.integer) or seeds.shape != (m,) or (seeds < 0).any():
        raise ValueError(
            f"{source}: field 'seeds' must be non-negative ints of shape ({m},) (one reset "
            f"seed per {unit}), got dtype {seeds.dtype} shape {seeds.shape}; store "
            f"`seeds.astype(np.int64)` or leave it out.")


def save_archive(path: str | os.PathLike[str], demos: Any, kind: type, *, writer: str,
                 how: str, fields: Callable[[Any], Mapping[str, np.ndarray | None]]) -> Path:
    """Write ``demos``, which must be a ``kind``, to ``path`` as the compressed ``.npz``
    of ``fields(demos)`` (a None field is left out), atomically (:func:`atomic_savez`: no
    suffix is appended, parent directories are created).

    Args:
        writer, how: the public function that saves a ``kind`` and how to make one, for
            the refusal of anything else.

    Returns:
        The path written.

    Raises:
        TypeError: ``demos`` is not a ``kind``.
    """
    if not isinstance(demos, kind):
        raise TypeError(f"{writer} expects a {kind.__name__}, got {type(demos).__name__}; "
                        f"{how}.")
    return atomic_savez(path, {f: a for f, a in fields(demos).items() if a is not None})


@contextmanager
def open_archive(path: Path, *, source: str, required: Sequence[str],
                 optional: Sequence[str] = (), version: int, fix: str, generate: str
                 ) -> Iterator[np.lib.npyio.NpzFile]:
    """Open ``path`` as an ``.npz`` of layout ``version`` holding ``required`` (and maybe
    ``optional``) fields; ``format_version`` is read before any other field
    (:func:`check_version`).

    Args:
        path: the file.
        source: how messages name it, e.g. ``"demonstrations file 'x.npz'"``.
        required, optional: the schema's field names.
        version: the ``format_version`` this code reads.
        fix: the function that writes a good file.
        generate: what to do when the file is missing.

    Raises:
        FileNotFoundError: ``path`` is not a file.
        ValueError: not an ``.npz`` archive, missing / unknown fields, or another
            ``format_version``.
    """
    if not path.is_file():
        raise FileNotFoundError(f"No {source}: it does not exist or is not a file. "
                                f"{generate}, or fix the path.")
    # Open the file ourselves so it is closed on every path: np.load leaks its handle
    # when the archive turns out unreadable.
    with open(path, "rb") as fh:
        try:
            archive = np.load(fh, allow_pickle=False)
        except READ_ERRORS as e:
            # numpy's own text for a non-array file suggests unpickling it; do not echo it.
            why = "not an array file" if "pickle" in str(e) else f"{type(e).__name__}: {e}"
            raise ValueError(
                f"{source} cannot be opened as an .npz archive ({why}); it is truncated, "
                f"corrupt or not an .npz. Regenerate it with {fix}.") from e
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise ValueError(f"{source} holds a single .npy array, not an .npz archive with "
                             f"fields {list(required)}; re-save it with {fix}.")
        with archive:
            names = set(archive.files)
            missing = [f for f in required if f not in names]
            if missing:
                raise ValueError(f"{source}: missing field(s) {missing}; the file needs "
                                 f"{list(required)}. Re-save it with {fix}.")
            unknown = sorted(names - set(required) - set(optional))
            if unknown:
                raise ValueError(f"{source}: unknown field(s) {unknown}; the file holds only "
                                 f"{list(required) + list(optional)}. Re-save it with {fix}.")
            check_version(archive, version, source, fix)
            yield archive


def read_field(archive: np.lib.npyio.NpzFile, field: str, source: str, fix: str) -> np.ndarray:
    """``archive[field]``, refusing object (pickled) arrays and damaged members."""
    try:
        return archive[field]
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise ValueError(
                f"{source}: field '{field}' is an object (pickled) array, which is never "
                f"loaded for safety; store it as a numeric array and re-save with {fix}."
            ) from e
        raise ValueError(f"{source}: field '{field}' cannot be read ({e}); the file is "
                         f"corrupt. Regenerate it with {fix}.") from e
    except READ_ERRORS as e:
        raise ValueError(
            f"{source}: field '{field}' cannot be read ({type(e).__name__}: {e}); the file "
            f"is truncated or corrupt. Regenerate it with {fix}.") from e


def read_scalar(archive: np.lib.npyio.NpzFile, field: str, source: str, fix: str,
                kind: type = int) -> int | float:
    """A 0-d ``int`` (or ``float``) field."""
    a = read_field(archive, field, source, fix)
    want = np.integer if kind is int else np.floating
    if a.ndim != 0 or not np.issubdtype(a.dtype, want):
        what = "an integer" if kind is int else "a float"
        raise ValueError(f"{source}: field '{field}' must be {what} scalar, got dtype "
                         f"{a.dtype} shape {a.shape}. Re-save the file with {fix}.")
    return kind(a)


def check_version(archive: np.lib.npyio.NpzFile, version: int, source: str, fix: str) -> None:
    """Read ``format_version`` first: a newer layout could make every other check
    misleading."""
    found = read_scalar(archive, "format_version", source, fix)
    if found != version:
        raise ValueError(f"{source}: field 'format_version' is {found}, but this code reads "
                         f"only version {version}; regenerate the file with this version of "
                         f"dicrl_torch.")


def check_expected(source: str, found: Mapping[str, object],
                   expected: Mapping[str, object | None]) -> None:
    """Each ``expected`` value that is not None must equal ``found``'s."""
    for name, want in expected.items():
        if want is not None and found[name] != want:
            raise ValueError(
                f"{source}: field '{name}' is {found[name]} in the file but {want} was "
                f"expected; the file was made for a different configuration. Regenerate "
                f"the demonstrations for this configuration or point to the matching file.")


def subset_indices(indices, n: int) -> np.ndarray:
    """Validated int64 indices ``[k]`` into ``n`` trajectories (or pairs), from 1-D ints
    (in that order; negative ones count from the end) or a ``[n]`` bool mask."""
    idx = np.asarray(indices)
    if idx.dtype == np.bool_:
        if idx.shape != (n,):
            raise ValueError(f"A boolean subset mask must have shape ({n},), got {idx.shape}.")
        idx = np.flatnonzero(idx)
    if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
        raise ValueError(f"subset indices must be a 1-D sequence of ints, got dtype "
                         f"{idx.dtype} shape {idx.shape}.")
    if idx.size and (idx.min() < -n or idx.max() >= n):
        raise ValueError(f"subset indices must lie in [0, {n}), got [{idx.min()}, "
                         f"{idx.max()}].")
    return idx.astype(np.int64)


def shard_indices(m: int, sizes: Sequence[int], rng: np.random.Generator | None,
                  unit: str) -> list[np.ndarray]:
    """Indices of consecutive, disjoint shards of ``m`` items (shuffled first when
    ``rng`` is given); ``unit`` names the items in messages."""
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator or None, got "
                        f"{type(rng).__name__}; pass np.random.default_rng(seed).")
    sizes = tuple(sizes)
    if not sizes:
        raise ValueError("sizes is empty; give one positive shard size per learner.")
    bad = [s for s in sizes if isinstance(s, bool | np.bool_) or not isinstance(s, int | np.integer)
           or s <= 0]
    if bad:
        raise ValueError(f"Shard sizes must be positive ints, got {list(sizes)} (bad: {bad}).")
    if sum(sizes) != m:
        raise ValueError(f"Shard sizes {list(sizes)} sum to {sum(sizes)}, but there are {m} "
                         f"{unit}; make the sizes sum to {m}.")
    order = rng.permutation(m) if rng is not None else np.arange(m)
    bounds = np.cumsum((0,) + sizes)
    return [order[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
