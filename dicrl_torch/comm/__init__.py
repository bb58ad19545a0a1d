"""Communication between learners: mixing schedules W(k), W̄(n), assumption checks,
communicators, their traffic counters and compressed messages."""

from dicrl_torch.comm import graphs
from dicrl_torch.comm.communicator import (
    ALLOWED_FIELDS,
    Communicator,
    MessageRecord,
    SimulatedCommunicator,
    fixed_order_mix,
)
from dicrl_torch.comm.compression import Compression
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
from dicrl_torch.comm.traffic import Traffic  # noqa: I001 - after graphs' star import

__all__ = [
    "ALLOWED_FIELDS",
    "Communicator",
    "Compression",
    "Traffic",
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
