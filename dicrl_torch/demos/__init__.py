"""Expert demonstrations: generation, storage, validation, partitioning over learners and
their discounted feature sums (the drone arena's pairs are
:mod:`dicrl_torch.demos.drone_demos`; the constrained spread's experts are
:mod:`dicrl_torch.demos.mpe_experts`; any continuous multi-agent environment's episodes,
recorded from a PettingZoo ``ParallelEnv``, are :mod:`dicrl_torch.demos.continuous`).

All kinds of demonstrations are :class:`Trajectories`, split by the one
:func:`partition_demonstrations`.
"""

from .continuous import (
    ContinuousDemonstrations,
    load_continuous_demonstrations,
    record_demonstrations,
    save_continuous_demonstrations,
)
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
    "ContinuousDemonstrations",
    "Demonstrations",
    "Trajectories",
    "TrajectoryArrays",
    "load_continuous_demonstrations",
    "load_demonstrations",
    "partition_demonstrations",
    "record_demonstrations",
    "save_continuous_demonstrations",
    "save_demonstrations",
    "validate_arrays",
]
