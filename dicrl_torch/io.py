"""Atomic file writes, the one helper every writer of results, checkpoints and
demonstrations uses: a reader (or a resumed run) sees the old file or the new one, never
half of one (docs/design.md §2)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

_HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM recorded inside, raised again (in order) on leaving.

    A handler that raises (the runs' ``Interrupted``) inside ``torch.save`` raises in the
    middle of torch's zip writer, which reports it as ``RuntimeError: ... unexpected pos``:
    the run then exits 1 with a traceback instead of 130/143 with its resume command.
    Held, the signal is handled once the file is in place. The Python handlers are swapped
    rather than the signal mask set: a mask is per thread, and torch's worker threads
    would still take the signal. Python runs handlers, and lets them be set, in the main
    thread only; elsewhere nothing is held. A write that hangs is then stopped by SIGKILL
    only (writes here take seconds at most)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    # getsignal() None: a handler not set from Python, which could not be put back.
    held = [sig for sig in _HELD_SIGNALS if signal.getsignal(sig) is not None]
    previous = {sig: signal.signal(sig, lambda signum, frame: caught.append(signum))
                for sig in held}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for signum in caught:
            signal.raise_signal(signum)


def atomic_write(path: str | os.PathLike[str], write: Callable[[BinaryIO], Any]) -> Path:
    """Call ``write(f)`` on a new binary file next to ``path``, flush it to disk, then
    move it onto ``path`` (``os.replace``). An exception removes the temporary file and
    leaves ``path`` as it was. SIGINT and SIGTERM arriving meanwhile (in the main thread)
    are handled once the new file is in place. Parent directories are created; ``path``
    is used as given.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A unique name: two writers of one path (e.g. learner processes) never share it.
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    # Mode 0o666 lets the umask decide the permissions, as for open(); O_EXCL never
    # clobbers anything.
    try:
        with _signals_held():
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            with os.fdopen(fd, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _key(key: Any) -> str:
    """A dict key as ``json.dumps`` writes it (bools and None as JSON literals)."""
    if isinstance(key, str):
        return key
    if key is None or isinstance(key, bool | int | float):
        return json.dumps(key)
    raise TypeError(f"keys must be str, int, float, bool or None, not {type(key).__name__}")


def dumps_compact(obj: Any, indent: int = 1) -> str:
    """``obj`` as JSON indented like ``json.dumps(obj, indent=indent)``, except that a list
    of scalars stays on one line: a learner's 201 cost weights per outer iteration are one
    line each, not 201. ``json.loads`` gives back what ``json.dumps`` would have."""

    def dump(value: Any, depth: int) -> str:
        if isinstance(value, dict) and value:
            pad = " " * (indent * (depth + 1))
            items = (f"{pad}{json.dumps(_key(k))}: {dump(v, depth + 1)}"
                     for k, v in value.items())
            return "{\n" + ",\n".join(items) + "\n" + " " * (indent * depth) + "}"
        if isinstance(value, list | tuple) and value and not all(
                v is None or isinstance(v, str | int | float) for v in value):
            pad = " " * (indent * (depth + 1))
            items = (pad + dump(v, depth + 1) for v in value)
            return "[\n" + ",\n".join(items) + "\n" + " " * (indent * depth) + "]"
        return json.dumps(value)

    return dump(obj, 0)


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """``obj`` as indented JSON (UTF-8; lists of scalars on one line,
    :func:`dumps_compact`), atomically; serialised before anything is opened, so a value
    JSON cannot hold writes nothing."""
    data = dumps_compact(obj).encode()
    return atomic_write(path, lambda f: f.write(data))
