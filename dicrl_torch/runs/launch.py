"""Launching a run: every learner in this process, one spawned process per learner, or the
processes torchrun started; the resume hints and exit codes a user sees when a run stops.

The entry point (``experiments/train.py``) hands the launcher an :class:`Experiment`, the
object that builds the run's pieces in whichever process needs them, and exits with the
code :func:`launch` returns:

- 0: the run finished and wrote ``results.json``;
- 1: a learner failed or a value went NaN/inf (the message names where; no results);
- 128 + n: signal n stopped the run after a checkpoint; the message prints the command
  that resumes it.

Library code here never reads a config: the :class:`Experiment` does.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import traceback
import uuid
from pathlib import Path
from typing import Any, Protocol

import torch

from ..algos.dicrl import NonFiniteError
from ..comm import SimulatedCommunicator
from ..comm.distributed import (
    ConfigMismatchError,
    LearnerProcessError,
    LearnerProcesses,
    PeerFailureError,
)
from .checkpoints import Checkpoints
from .runner import (
    RunSettings,
    TrainerSpec,
    agree_on_run_dir,
    finish,
    merge_learner_rows,
    run_all_in_one,
    run_c_icrl,
    run_learner,
)
from .signals import Interrupted, StopOnSignal, interrupt_on_signals


class Experiment(Protocol):
    """What the launcher needs from an entry point. It must pickle (a spawned learner
    process rebuilds its pieces from it) and build the same pieces in every process.

    Attributes:
        n_learners: the number of D-ICRL learners (one process each when distributed).
        distributed: one process per learner (spawned, or started by torchrun).
        c_icrl_beside_learners: the spawning process trains C-ICRL while the learner
            processes run (else after them).
        config_text: the run's resolved configuration; learner processes check they agree.
    """

    n_learners: int
    distributed: bool
    c_icrl_beside_learners: bool
    config_text: str

    def task(self, rank: int | None = None) -> Any:
        """The run's task as process ``rank`` sees it (None: the process holding every
        shard)."""

    def settings(self) -> RunSettings: ...

    def trainer(self) -> TrainerSpec: ...

    def logger(self, out: Path) -> Any: ...

    def communicator(self, **objects: Any) -> Any:
        """The configured communicator, built with ``objects`` (``n_learners`` when
        simulated; ``rank``, ``world_size``, ``init_method`` when distributed)."""

    def resume_command(self, out: Path) -> str:
        """The command line that continues the run in ``out`` from its checkpoints."""


def resume_hint(experiment: Experiment, out: Path) -> str:
    return (f"The last checkpoints (checkpoint_rank<r>.pt) are in {out}; continue with the "
            f"same overrides plus resume=true hydra.run.dir={out}:\n  "
            f"{experiment.resume_command(out)}")


def launch(experiment: Experiment, out: Path, *, t_start: float) -> int:
    """Run ``experiment`` into ``out`` as its config says; the process's exit code."""
    if not experiment.distributed:
        return run_simulated(experiment, out, t_start)
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        return run_torchrun(experiment, out, t_start)
    return run_spawned(experiment, out, t_start)


def run_simulated(experiment: Experiment, out: Path, t_start: float) -> int:
    """Every learner in this process (``comm=simulated``)."""
    try:
        run_all_in_one(experiment.task(), experiment.settings(), experiment.trainer(),
                       out=out, t_start=t_start, logger=experiment.logger(out),
                       communicator=lambda n: experiment.communicator(n_learners=n))
    except Interrupted as e:
        what = (f"checkpoint {e.saved}" if e.saved else
                "stopped at once; the last checkpoint written stays valid")
        print(f"\ninterrupted by {e} ({what}). Checkpoints are in {out / 'checkpoint.pt'}; "
              f"no results.json was written. Resume with:\n  "
              f"{experiment.resume_command(out)}", file=sys.stderr, flush=True)
        return 128 + e.signum  # the shell's convention for "killed by a signal"
    except NonFiniteError as e:
        # The checkpoints hold only finite states; rerun with the changes it suggests.
        print(f"error: {e}\nno results.json was written.", file=sys.stderr, flush=True)
        return 1
    return 0


def finish_here(experiment: Experiment, task, out: Path, d_icrl: dict, t_start: float, *,
                ckpt: Checkpoints | None = None, logger=None, c_icrl: dict | None = None
                ) -> None:
    """C-ICRL (unless it ran beside the learners: ``c_icrl``), the baselines and the
    reference rows in this process, after the learner processes have written their rows."""
    settings = experiment.settings()
    if ckpt is None:
        ckpt = Checkpoints(out / "checkpoint.pt", settings.resume,
                           config=settings.training_config)
    finish(task, settings, experiment.trainer(), out=out, d_icrl=d_icrl,
           logger=experiment.logger(out) if logger is None else logger, ckpt=ckpt,
           t_start=t_start, c_icrl_comm=SimulatedCommunicator(n_learners=1), c_icrl=c_icrl)


def spawned_learner(rank: int, world_size: int, init_method: str, experiment: Experiment,
                    out_dir: str, run_id: str, sharing: int) -> None:
    """Body of a learner process started by :func:`run_spawned`."""
    from tqdm import tqdm

    # tqdm's default lock, a named semaphore here, leaks at os._exit: a thread lock will do.
    tqdm.set_lock(threading.RLock())
    interrupt_on_signals()
    comm = experiment.communicator(init_method=init_method, rank=rank,
                                   world_size=world_size)
    comm.check_same_config(experiment.config_text)
    run_learner(comm, experiment.task(rank), experiment.settings(), experiment.trainer(),
                out=Path(out_dir), run_id=run_id, logger=experiment.logger(Path(out_dir)),
                sharing=sharing)
    comm.close()


@contextlib.contextmanager
def stop_when_a_learner_fails(learners: LearnerProcesses):
    """Inside, a learner process that fails sends this process SIGTERM (once), so that
    work beside the learners stops at its next checkpoint instead of running on alone."""
    done = threading.Event()

    def watch() -> None:
        while not done.wait(1.0):
            if learners.failed():
                print("\na learner process failed: stopping the work beside the learners "
                      "(SIGTERM to this process)", file=sys.stderr, flush=True)
                os.kill(os.getpid(), signal.SIGTERM)
                return

    thread = threading.Thread(target=watch, name="learner-watch", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _c_icrl_beside(experiment: Experiment, task, learners: LearnerProcesses, out: Path,
                   threads: int, sharing: int) -> tuple[Checkpoints, Any, dict | None]:
    """C-ICRL in this process while the learner processes run, on their share of cores."""
    settings = experiment.settings()
    own_threads = torch.get_num_threads()
    torch.set_num_threads(threads)  # a third process on the learners' cores
    ckpt = Checkpoints(out / "checkpoint.pt", settings.resume, config=settings.training_config)
    logger = experiment.logger(out)
    task.bind_run_dir(out, settings.training_config, process=experiment.n_learners,
                      processes=sharing)
    c_icrl = None
    try:
        with StopOnSignal() as stop, stop_when_a_learner_fails(learners):
            c_icrl = run_c_icrl(task, experiment.trainer(), settings=settings, out=out,
                                logger=logger, ckpt=ckpt,
                                communicator=SimulatedCommunicator(n_learners=1), stop=stop)
    except Exception as e:  # noqa: BLE001 - re-raised unless a learner failed
        if not learners.failed():
            raise
        # A learner failed and the watcher's SIGTERM stopped C-ICRL: the learner's error
        # is the news. The signal can land inside a checkpoint write, where torch's writer
        # turns it into its own RuntimeError (the write is atomic: the last checkpoint
        # stays valid).
        if not isinstance(e, Interrupted):
            first_line = str(e).splitlines()[0] if str(e) else ""
            print(f"C-ICRL ended with {type(e).__name__} ({first_line}) while the failed "
                  f"learner stopped the run", file=sys.stderr, flush=True)
    finally:
        torch.set_num_threads(own_threads)  # the baselines run alone
    return ckpt, logger, c_icrl


def run_spawned(experiment: Experiment, out: Path, t_start: float) -> int:
    """``comm=distributed`` without torchrun: one learner process per shard, spawned here;
    with ``c_icrl_beside_learners`` this process trains C-ICRL meanwhile."""
    n = experiment.n_learners
    task = experiment.task()
    task.announce(out)
    threads = int(os.environ.get("DICRL_THREADS", max(1, torch.get_num_threads() // n)))
    sharing = n + 1 if experiment.c_icrl_beside_learners else n
    run_id = uuid.uuid4().hex
    print(f"starting {n} learner processes ({threads} thread(s) each)"
          + (", C-ICRL in this one" if experiment.c_icrl_beside_learners else ""), flush=True)
    interrupt_on_signals()  # on a signal, the learner processes are stopped on the way out
    ckpt = logger = c_icrl = None
    try:
        # No overall time limit: every wait between learners is bounded by comm.timeout_s,
        # and once one process fails the others are stopped after a grace period.
        with LearnerProcesses(spawned_learner, n, timeout_s=float("inf"), num_threads=threads,
                              args=(experiment, str(out), run_id, sharing)) as learners:
            if experiment.c_icrl_beside_learners:
                ckpt, logger, c_icrl = _c_icrl_beside(experiment, task, learners, out,
                                                      threads, sharing)
            learners.wait()
    except LearnerProcessError as e:
        first = e.tracebacks.get(e.first_failed) if e.first_failed is not None else None
        if first:
            print(first, file=sys.stderr)
        print(f"error: {e}\n{resume_hint(experiment, out)}", file=sys.stderr, flush=True)
        return 1
    except Interrupted as e:
        print(f"\ninterrupted by {e}: every learner process was stopped; no results.json "
              f"was written. {resume_hint(experiment, out)}", file=sys.stderr, flush=True)
        return 128 + e.signum
    finish_here(experiment, task, out, merge_learner_rows(out, n, run_id), t_start, ckpt=ckpt,
                logger=logger, c_icrl=c_icrl)
    return 0


def run_torchrun(experiment: Experiment, out: Path, t_start: float) -> int:
    """A process started by torchrun: learner ``RANK``; rank 0 also finishes the run."""
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    interrupt_on_signals()
    try:
        comm = experiment.communicator(rank=rank, world_size=world_size)  # env:// rendezvous
        comm.check_same_config(experiment.config_text)
        out, run_id = agree_on_run_dir(comm, out)
        task = experiment.task(rank)
        if rank == 0:
            task.announce(out)
        run_learner(comm, task, experiment.settings(), experiment.trainer(), out=out,
                    run_id=run_id, logger=experiment.logger(out))
        comm.close()
    except Exception as e:
        # Exit at once, without tearing down a process group with a dead peer (can hang).
        if not isinstance(e, PeerFailureError | ConfigMismatchError | Interrupted):
            traceback.print_exc()
        what = (f"interrupted by {e}" if isinstance(e, Interrupted)
                else f"{type(e).__name__}: {e}")
        print(f"error: learner {rank}: {what}\n{resume_hint(experiment, out)}",
              file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(128 + e.signum if isinstance(e, Interrupted) else 1)
    if rank == 0:
        finish_here(experiment, task, out, merge_learner_rows(out, world_size, run_id),
                    t_start)
    return 0
