"""The run's trainer callbacks: per-iteration evaluation, TensorBoard values and
checkpoints with a signal-safe stop (docs/design.md §2). They attach to
:meth:`dicrl_torch.algos.dicrl.DICRL.train` in that order: the metrics go into the history
entry before the checkpoint that keeps it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from dicrl_torch.algos.callbacks import TrainerCallback
from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.runs.checkpoints import Checkpoints
from dicrl_torch.runs.signals import Interrupted, StopOnSignal

RunOf = Callable[[int], str]  # learner id -> TensorBoard run name
# History keys logged after every outer iteration (CR and CVR only where rolled out).
HISTORY_TAGS = (("outer/multiplier", "multiplier"), ("outer/lga_norm", "lga_norm"),
                ("eval/FPR", "FPR"), ("eval/FNR", "FNR"), ("eval/RFD", "RFD"),
                ("eval/CR", "CR"), ("eval/CVR", "CVR"), ("comm/bytes_sent", "bytes_sent"))


class OuterMetrics(TrainerCallback):
    """Adds the task's metrics of the local learners to each history entry (lists in
    local order, as ``multiplier``: a distributed run's per-rank histories merge by
    concatenation). Rollouts (CR, CVR) after the first iteration, every ``eval_every``-th
    and the last (``outer_iterations``)."""

    def __init__(self, task, eval_every: int, outer_iterations: int) -> None:
        self.task, self.eval_every, self.last = task, eval_every, outer_iterations

    def rollouts_due(self, done: int) -> bool:
        return done == 1 or done % self.eval_every == 0 or done == self.last

    def on_outer_end(self, trainer: DICRL, info: dict[str, Any]) -> None:
        info.update(self.task.outer_metrics(
            trainer, self.rollouts_due(trainer.state.outer_iteration)))


def log_history_entry(logger, run_of: RunOf, local: list[int], info: dict,
                      learners: list[int] | None = None) -> None:
    """The ``outer/`` and ``eval/`` values of the history entry ``info`` for the local
    learners ``local`` (or those of them in ``learners``)."""
    n = info["outer_iteration"]
    for i, v in enumerate(local):
        if learners is not None and v not in learners:
            continue
        for tag, key in HISTORY_TAGS:
            if info.get(key) is not None and info[key][i] is not None:
                logger.scalar(run_of(v), tag, info[key][i], n)


def log_disagreement(logger, trainer: DICRL, n: int) -> None:
    """The network run's ``consensus/`` distances after outer iteration ``n``: of ω_c
    and of η̄. Gathers from every learner, so every learner process must call it;
    ``logger`` None: take part without logging (the processes that do not own
    ``network``)."""
    gaps = {tag: trainer.disagreement(field)
            for tag, field in (("consensus/max_pairwise_cost_distance", "cost_weights"),
                               ("consensus/max_pairwise_eta_distance", "eta"))}
    if logger is not None:
        for tag, gap in gaps.items():
            logger.scalar("network", tag, gap, n)


class TensorBoardValues(TrainerCallback):
    """``outer/`` and ``eval/`` values of each history entry, and (with several learners)
    the ``consensus/`` distances, logged by the process that owns the network run."""

    def __init__(self, logger, run_of: RunOf, log_network: bool) -> None:
        self.logger, self.run_of, self.log_network = logger, run_of, log_network

    def replay(self, trainer: DICRL) -> None:
        """Write a resumed trainer's checkpointed history into the learner runs that have
        no values yet: a checkpoint carried to another directory, checkout or machine
        arrives without its event files, and its curves would otherwise start where it
        resumed. The inner/ values and the network's distances are not in the history."""
        fresh = [v for v in trainer.local if not self.logger.has_run(self.run_of(v))]
        for info in trainer.history if fresh else ():
            log_history_entry(self.logger, self.run_of, trainer.local, info, learners=fresh)

    def on_outer_end(self, trainer: DICRL, info: dict[str, Any]) -> None:
        log_history_entry(self.logger, self.run_of, trainer.local, info)
        if trainer.n_learners > 1 and getattr(trainer.comm, "diagnostics", True):
            log_disagreement(self.logger if self.log_network else None, trainer,
                             info["outer_iteration"])


class CheckpointEvery(TrainerCallback):
    """Saves the trainer as ``name`` every ``every`` outer iterations; after a first
    SIGINT/SIGTERM caught by ``stop``, saves the iteration just finished and raises
    :class:`~dicrl_torch.runs.signals.Interrupted`."""

    def __init__(self, checkpoints: Checkpoints, name: str, every: int,
                 stop: StopOnSignal | None = None) -> None:
        self.checkpoints, self.name, self.every, self.stop = checkpoints, name, every, stop

    def on_outer_end(self, trainer: DICRL, info: dict[str, Any]) -> None:
        n = trainer.state.outer_iteration
        if n % self.every == 0:
            self.checkpoints.save(self.name, trainer)
        if self.stop is not None and self.stop.signum is not None:
            self.stop.training = False  # a further signal now interrupts the save: still safe
            self.checkpoints.save(self.name, trainer)
            raise Interrupted(self.stop.signum, f"{self.name} saved after outer iteration {n}")
