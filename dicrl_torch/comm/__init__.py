"""Communication between learners: mixing schedules W(k), W̄(n), assumption checks and
communicators."""

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
from dicrl_torch.comm.graphs import (
    CompleteSchedule,
    DirectedCycleSchedule,
    GraphAssumptionError,
    MatrixSchedule,
    MixingSchedule,
    RingSchedule,
    TimeVaryingSchedule,
    check_inner_schedule,
    check_outer_schedule,
)

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
    "CompleteSchedule",
    "DirectedCycleSchedule",
    "GraphAssumptionError",
    "MatrixSchedule",
    "MixingSchedule",
    "RingSchedule",
    "TimeVaryingSchedule",
    "check_inner_schedule",
    "check_outer_schedule",
]
