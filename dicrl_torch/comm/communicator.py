"""Communicators: how learners exchange parameter vectors (docs/design.md §5).

A communicator serves the learners that live in this process (``local_ids``); the
trainer keeps their state stacked along a leading axis. ``mix`` returns, for each
local learner ``v``, ``Σ_{v'} W[v, v'] x_{v'}``, accumulated in a fixed order
(``v' = 0, 1, ..``) so that every backend performs the same floating-point operations
and produces identical numbers.

Only the fields listed in :data:`ALLOWED_FIELDS` may be sent; every message is
recorded (field, shape) so that a test can audit what left a learner.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

# What may leave a learner: η = [ω_r, λ], ω_c and the gradient trackers (Algorithm 1's,
# and the optional gradient-tracking inner variant's).
ALLOWED_FIELDS = ("eta", "cost_weights", "tracker", "inner_tracker")
# Control values a run coordinates its learner processes with (never learner data): the
# run directory and id, and which outer iterations each learner has checkpointed.
CONTROL_FIELDS = ("run_directory", "checkpointed_iterations")


def check_control(field: str, value) -> bytes:
    """``value`` as the JSON bytes :meth:`gather_control` sends; a field not in
    :data:`CONTROL_FIELDS` or a value JSON cannot hold is refused."""
    import json

    if field not in CONTROL_FIELDS:
        raise ValueError(f"Control field {field!r} is not one a run exchanges; allowed: "
                         f"{CONTROL_FIELDS}.")
    return json.dumps(value).encode()


@dataclass
class MessageRecord:
    field: str
    shape: tuple[int, ...]
    sender: int


@dataclass
class SimulatedCommunicator:
    """All ``n_learners`` learners in one process (``local_ids = 0..N_L-1``).

    Args:
        n_learners: number of learners ``N_L``.
        record: keep a log of every message (for the privacy audit).
    """

    n_learners: int
    record: bool = False
    messages: list[MessageRecord] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not isinstance(self.n_learners, int) or self.n_learners < 1:
            raise ValueError(f"n_learners must be a positive int, got {self.n_learners!r}.")

    @property
    def local_ids(self) -> list[int]:
        return list(range(self.n_learners))

    def all_gather(self, values: torch.Tensor, field: str) -> torch.Tensor:
        """``values`` ``[n_local, ...]`` of the local learners -> ``[N_L, ...]``."""
        if field not in ALLOWED_FIELDS:
            raise ValueError(f"Field {field!r} may not leave a learner; allowed: "
                             f"{ALLOWED_FIELDS}.")
        if values.shape[0] != self.n_learners:
            raise ValueError(f"Expected values for {self.n_learners} local learners, got "
                             f"{values.shape[0]}.")
        if self.record:
            for v in self.local_ids:
                self.messages.append(MessageRecord(field, tuple(values.shape[1:]), v))
        return values

    def mix(self, values: torch.Tensor, W: torch.Tensor, field: str) -> torch.Tensor:
        """Consensus step: ``[n_local, ...]`` -> ``[n_local, ...]`` with ``W`` ``[N_L, N_L]``."""
        return fixed_order_mix(self.all_gather(values, field), W, self.local_ids)

    def gather_control(self, value, field: str) -> list:
        """Every learner's control ``value`` (JSON-able), in learner order: here all
        learners share one process, hence one value. Recorded like every message."""
        data = check_control(field, value)
        if self.record:
            self.messages.append(MessageRecord(field, (len(data),), self.local_ids[0]))
        return [value] * self.n_learners

    def close(self) -> None:
        pass


def fixed_order_mix(gathered: torch.Tensor, W: torch.Tensor, rows: list[int]) -> torch.Tensor:
    """``out[i] = Σ_{v'} W[rows[i], v'] gathered[v']``, summed in the order v' = 0, 1, ..

    (A matmul may sum rows in different orders; this keeps backends bit-identical.)"""
    W = W.to(gathered.dtype)
    out = []
    for v in rows:
        acc = W[v, 0] * gathered[0]
        for u in range(1, gathered.shape[0]):
            acc = acc + W[v, u] * gathered[u]
        out.append(acc)
    return torch.stack(out)
