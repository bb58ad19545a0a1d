"""Expert demonstrations: storage, validation, partitioning over learners and their
discounted feature sums (the drone arena's pairs are :mod:`dicrl_torch.demos.drone_demos`).

Both kinds of demonstrations are :class:`Trajectories`, split by the one
:func:`partition_demonstrations`.
"""

from .partition import PAPER_SPLIT, partition_demonstrations
from .storage import (
    FORMAT_VERSION,
    Demonstrations,
    load_demonstrations,
    save_demonstrations,
    validate_arrays,
)
from .trajectories import Trajectories, TrajectoryArrays

__all__ = [
    "FORMAT_VERSION",
    "PAPER_SPLIT",
    "Demonstrations",
    "Trajectories",
    "TrajectoryArrays",
    "load_demonstrations",
    "partition_demonstrations",
    "save_demonstrations",
    "validate_arrays",
]
