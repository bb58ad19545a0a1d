"""What the tests of the demonstrations' ``.npz`` readers share (grid, drone and
continuous alike, all on :mod:`dicrl_torch.demos.npz`): a malformed or non-archive file is
refused with a ``ValueError`` naming the file, then the field."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest


def rejects(path: Path, field: str) -> str:
    """Regex requiring the file name and then the field name in the message."""
    return re.escape(path.name) + r".*" + re.escape(field)


def assert_file_refused(load: Callable[[Path], Any], path: Path,
                        fields: Mapping[str, np.ndarray], field: str) -> None:
    """``fields`` written to ``path`` by plain ``np.savez`` (not the library's writer,
    which would refuse them) make ``load(path)`` raise, naming the file and ``field``."""
    np.savez(path, **fields)
    with pytest.raises(ValueError, match=rejects(path, field)):
        load(path)


def assert_not_an_archive(load: Callable[[Path], Any], tmp_path: Path) -> None:
    """A file of bytes that are no zip archive is refused as such, naming it."""
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="junk.npz.*(not an .npz|corrupt)"):
        load(path)
