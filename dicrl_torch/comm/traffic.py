"""What the learners send each other, counted (docs/design.md §5.3).

Every communicator keeps a :class:`Traffic`: per local learner, per phase and direction,
the messages, scalars and bytes. A message is one payload from one learner to one
recipient, and its bytes are those that cross the backend: an all-gather of ``s``
float64 values among ``N_L`` learners sends ``N_L - 1`` messages of ``8 s`` bytes (what
gloo's ring all-gather moves per process); a compressed message counts its encoded
bytes plus the 4-byte length that precedes it on the wire.

Counters are cheap (a few integer additions per exchange), always on, and travel with
the trainer's checkpoints, so a resumed run reports its whole traffic.
"""

from __future__ import annotations

from collections.abc import Iterable

# The algorithm's rounds (inner: η and the inner tracker; outer: ω_c and the tracker),
# the run's coordination (checkpoints, run directory) and the diagnostics (consensus
# distances for TensorBoard), which are reported apart and can be turned off.
PHASES = ("inner", "outer", "control", "diagnostics")
ALGORITHM_PHASES = ("inner", "outer")
FIELD_PHASE = {"eta": "inner", "inner_tracker": "inner", "cost_weights": "outer",
               "tracker": "outer", "lsca_target": "outer", "demonstrated": "outer",
               "run_directory": "control",
               "checkpointed_iterations": "control", "config_fingerprint": "control"}
COUNTS = ("messages", "scalars", "bytes")
DIRECTIONS = ("sent", "received")


def phase_of(field: str, phase: str | None) -> str:
    """``phase`` if given (checked), else the phase ``field`` belongs to."""
    phase = FIELD_PHASE.get(field) if phase is None else phase
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {PHASES}, got {phase!r} (field {field!r}).")
    return phase


class Traffic:
    """Counters of the local learners ``learners``.

    ``counts[v][direction][phase]`` is ``{"messages", "scalars", "bytes"}`` (ints).
    """

    def __init__(self, learners: Iterable[int]) -> None:
        self.counts = {int(v): {d: {p: dict.fromkeys(COUNTS, 0) for p in PHASES}
                                for d in DIRECTIONS} for v in learners}

    def add(self, learner: int, direction: str, phase: str, *, messages: int, scalars: int,
            nbytes: int) -> None:
        c = self.counts[learner][direction][phase]
        c["messages"] += int(messages)
        c["scalars"] += int(scalars)
        c["bytes"] += int(nbytes)

    def bytes_sent(self, learner: int, phases: Iterable[str] = ALGORITHM_PHASES) -> int:
        """Bytes ``learner`` has sent in ``phases`` (default: the algorithm's rounds)."""
        return sum(self.counts[learner]["sent"][p]["bytes"] for p in phases)

    def report(self, learner: int) -> dict:
        """``learner``'s counters as results.json holds them: ``{"sent": {phase: counts},
        "received": .., "algorithm_bytes_sent": int, "algorithm_bytes_received": int}``."""
        c = self.counts[learner]
        out: dict = {d: {p: dict(c[d][p]) for p in PHASES} for d in DIRECTIONS}
        for d in DIRECTIONS:
            out[f"algorithm_bytes_{d}"] = sum(c[d][p]["bytes"] for p in ALGORITHM_PHASES)
        return out

    def state_dict(self) -> dict:
        return {"counts": {v: {d: {p: dict(x) for p, x in per.items()}
                               for d, per in c.items()} for v, c in self.counts.items()}}

    def load_state_dict(self, sd: dict) -> None:
        """Add a checkpoint's counters to this process's: the resumed run's traffic is
        the checkpointed run's plus what this process has exchanged since it started."""
        for v, c in sd["counts"].items():
            if int(v) not in self.counts:
                continue
            for d, per in c.items():
                for p, x in per.items():
                    self.add(int(v), d, p, messages=x["messages"], scalars=x["scalars"],
                             nbytes=x["bytes"])
