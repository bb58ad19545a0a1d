"""Expert demonstrations: storage, validation and partitioning over learners."""

from .partition import PAPER_SPLIT, partition_demonstrations
from .storage import (
    FORMAT_VERSION,
    Demonstrations,
    load_demonstrations,
    save_demonstrations,
    validate_arrays,
)

__all__ = [
    "FORMAT_VERSION",
    "PAPER_SPLIT",
    "Demonstrations",
    "load_demonstrations",
    "partition_demonstrations",
    "save_demonstrations",
    "validate_arrays",
]
