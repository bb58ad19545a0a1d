"""Atomic file writes, the one helper every writer of results, checkpoints and
demonstrations uses: a reader (or a resumed run) sees the old file or the new one, never
half of one (docs/design.md §2)."""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO


def atomic_write(path: str | os.PathLike[str], write: Callable[[BinaryIO], Any]) -> Path:
    """Call ``write(f)`` on a new binary file next to ``path``, flush it to disk, then
    move it onto ``path`` (``os.replace``). An exception (or an interrupting signal)
    removes the temporary file and leaves ``path`` as it was. Parent directories are
    created; ``path`` is used as given.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A unique name: two writers of one path (e.g. learner processes) never share it.
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    # Mode 0o666 lets the umask decide the permissions, as for open(); O_EXCL never
    # clobbers anything.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """``obj`` as indented JSON (UTF-8), atomically; serialised before anything is
    opened, so a value JSON cannot hold writes nothing."""
    data = json.dumps(obj, indent=1).encode()
    return atomic_write(path, lambda f: f.write(data))
