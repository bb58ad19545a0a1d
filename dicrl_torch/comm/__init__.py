"""Communication between learners: mixing schedules W(k), W̄(n), assumption checks and
communicators."""

from dicrl_torch.comm import graphs
from dicrl_torch.comm.communicator import (
    ALLOWED_FIELDS,
    MessageRecord,
    SimulatedCommunicator,
    fixed_order_mix,
)
from dicrl_torch.comm.distributed import (
    ConfigMismatchError,
    DistributedCommunicator,
    LearnerProcessError,
    LearnerProcesses,
    PeerFailureError,
    shard_for_rank,
    spawn_learners,
)

# The mixing schedules and the checks of Assumptions 1-3: graphs' whole public API, named
# once, by its __all__.
from dicrl_torch.comm.graphs import *  # noqa: F403

__all__ = [
    "ALLOWED_FIELDS",
    "ConfigMismatchError",
    "DistributedCommunicator",
    "LearnerProcessError",
    "LearnerProcesses",
    "MessageRecord",
    "PeerFailureError",
    "shard_for_rank",
    "spawn_learners",
    "SimulatedCommunicator",
    "fixed_order_mix",
]
__all__ += graphs.__all__
