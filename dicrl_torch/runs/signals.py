"""SIGINT/SIGTERM during a run: a checkpointed stop (:class:`StopOnSignal`, one process
holding every learner) or an immediate one (:func:`interrupt_on_signals`, a learner
process of a distributed run). docs/design.md §8 describes the exit codes."""

from __future__ import annotations

import contextlib
import signal
import sys


class Interrupted(Exception):
    """SIGINT or SIGTERM stopped the run.

    Attributes:
        signum: the signal.
        saved: what was checkpointed on the way out (None: stopped at once; the last
            atomic checkpoint stays valid).
    """

    def __init__(self, signum: int, saved: str | None = None) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum, self.saved = signum, saved


class StopOnSignal:
    """SIGINT/SIGTERM handling of the all-in-one-process run (a context manager).

    The first signal during training lets the current outer iteration (or greedy
    candidate) finish (a state in the middle of one is no consistent checkpoint), then
    ``train.train`` (or ``train.run_greedy``) checkpoints it and raises
    :class:`Interrupted`. A second signal, or one outside training, raises at once: every
    checkpoint is written atomically, so the last one stays valid, and everything after
    training is recomputed on resume.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.training = False
        self._previous: dict = {}

    def __enter__(self) -> StopOnSignal:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, frame) -> None:
        if self.training and self.signum is None:
            self.signum = signum
            print(f"\n{signal.Signals(signum).name} received: stopping after this outer "
                  f"iteration (or greedy candidate), with a checkpoint (send it again to "
                  f"stop at once)",
                  file=sys.stderr, flush=True)
            return
        raise Interrupted(signum)


@contextlib.contextmanager
def stoppable(stop: StopOnSignal | None):
    """Inside, a first signal caught by ``stop`` (if any) only sets ``stop.signum``: the
    work in progress checks it after its current unit and saves before raising."""
    if stop is None:
        yield
        return
    stop.training = True
    try:
        yield
    finally:
        stop.training = False


def interrupt_on_signals() -> None:
    """SIGINT/SIGTERM raise :class:`Interrupted` at once (learner processes of a
    distributed run). A learner cannot finish its outer iteration alone: the others
    would wait for it at the next exchange. Its checkpoints are written atomically, so
    the last one stays valid, and resume lets a learner that is one save behind catch up.
    """

    def handle(signum: int, frame) -> None:
        raise Interrupted(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handle)
