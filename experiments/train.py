"""Train D-ICRL (and C-ICRL, and the baselines) on the configured environment and report
the paper's table.

    python experiments/train.py experiment=quick [seed=1] [graph=ring] [features/cost=per_expert]
    python experiments/train.py experiment=table1      # Table 1: + ME-greedy, MCE-greedy rows
    python experiments/train.py experiment=table2      # Table 2: the drone arena
    python experiments/train.py comm=distributed       # one process per learner (spawned here)
    torchrun --standalone --nproc_per_node N_L experiments/train.py comm=distributed

Writes ``results.json``, TensorBoard runs (``tb/``), figures and the demonstrations into
the Hydra run directory and prints the table. This file only reads the config, builds the
objects (``common``) and calls the runner (:mod:`dicrl_torch.runs.runner`).

The config is checked before anything is computed (exit code 2); a first SIGINT/SIGTERM
checkpoints and exits with 128 + the signal, printing the command that resumes; a NaN or
inf exits with 1 naming where it arose (docs/design.md §8).
"""

from __future__ import annotations

import contextlib
import os
import shlex
import signal
import sys
import threading
import time
import traceback
import uuid
from pathlib import Path

import hydra
import torch
from common import (
    build,
    build_task,
    check_shard_contents,
    make_logger,
    run_settings,
    trainer_spec,
)
from config_checks import check_config, is_simulated
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.algos.dicrl import NonFiniteError
from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.comm.distributed import (
    ConfigMismatchError,
    LearnerProcessError,
    LearnerProcesses,
    PeerFailureError,
)
from dicrl_torch.runs.checkpoints import Checkpoints
from dicrl_torch.runs.runner import (
    agree_on_run_dir,
    finish,
    merge_learner_rows,
    run_all_in_one,
    run_c_icrl,
    run_learner,
)
from dicrl_torch.runs.signals import Interrupted, StopOnSignal, interrupt_on_signals


def resume_command(out: Path) -> str:
    """The exact command line that continues this run from its checkpoints."""
    try:
        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # no Hydra context (a spawned learner process)
        task = []
    keep = [o for o in task if not o.startswith(("resume=", "hydra.run.dir="))]
    return shlex.join([sys.executable, sys.argv[0], *keep, "resume=true",
                       f"hydra.run.dir={out}"])


def resume_hint(out: Path) -> str:
    return (f"The last checkpoints (checkpoint_rank<r>.pt) are in {out}; continue with the "
            f"same overrides plus resume=true hydra.run.dir={out}:\n  {resume_command(out)}")


def finish_here(cfg, task, out: Path, d_icrl: dict, t_start: float, *,
                ckpt: Checkpoints | None = None, logger=None, c_icrl: dict | None = None
                ) -> None:
    """C-ICRL (unless it ran beside the learners: ``c_icrl``), the baselines and the
    reference rows in this process, after the learner processes have written their rows."""
    settings = run_settings(cfg)
    finish(task, settings, trainer_spec(cfg), out=out, d_icrl=d_icrl,
           logger=make_logger(cfg, out) if logger is None else logger,
           ckpt=Checkpoints(out / "checkpoint.pt", cfg.resume,
                            config=settings.training_config) if ckpt is None else ckpt,
           t_start=t_start, c_icrl_comm=SimulatedCommunicator(n_learners=1), c_icrl=c_icrl)


def spawned_learner(rank: int, world_size: int, init_method: str, cfg_yaml: str,
                    out_dir: str, run_id: str, sharing: int) -> None:
    """Body of a learner process started by :func:`run_spawned`."""
    from tqdm import tqdm

    # tqdm's default lock, a named semaphore here, leaks at os._exit: a thread lock will do.
    tqdm.set_lock(threading.RLock())
    interrupt_on_signals()
    cfg = OmegaConf.create(cfg_yaml)
    comm = build(cfg.comm, init_method=init_method, rank=rank, world_size=world_size)
    comm.check_same_config(cfg_yaml)
    run_learner(comm, build_task(cfg, rank), run_settings(cfg), trainer_spec(cfg),
                out=Path(out_dir), run_id=run_id, logger=make_logger(cfg, Path(out_dir)),
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


def run_spawned(cfg, out: Path, t_start: float) -> None:
    """``python experiments/train.py comm=distributed``: one learner process per shard;
    with ``algo.c_icrl_beside_learners`` this process trains C-ICRL meanwhile."""
    n = len(cfg.split)
    task = build_task(cfg)
    task.announce(out)
    threads = int(os.environ.get("DICRL_THREADS", max(1, torch.get_num_threads() // n)))
    beside = bool(cfg.algo.run_c_icrl and cfg.algo.c_icrl_beside_learners)
    sharing = n + 1 if beside else n
    run_id = uuid.uuid4().hex
    print(f"starting {n} learner processes ({threads} thread(s) each)"
          + (", C-ICRL in this one" if beside else ""), flush=True)
    interrupt_on_signals()  # on a signal, the learner processes are stopped on the way out
    settings = run_settings(cfg)
    ckpt = logger = c_icrl = None
    try:
        # No overall time limit: every wait between learners is bounded by comm.timeout_s,
        # and once one process fails the others are stopped after a grace period.
        with LearnerProcesses(spawned_learner, n, timeout_s=float("inf"), num_threads=threads,
                              args=(OmegaConf.to_yaml(cfg, resolve=True), str(out), run_id,
                                    sharing)) as learners:
            if beside:
                own_threads = torch.get_num_threads()
                torch.set_num_threads(threads)  # a third process on the learners' cores
                ckpt = Checkpoints(out / "checkpoint.pt", cfg.resume,
                                   config=settings.training_config)
                logger = make_logger(cfg, out)
                task.bind_run_dir(out, settings.training_config, process=n, processes=sharing)
                try:
                    with StopOnSignal() as stop, stop_when_a_learner_fails(learners):
                        c_icrl = run_c_icrl(task, trainer_spec(cfg), settings=settings,
                                            out=out, logger=logger, ckpt=ckpt,
                                            communicator=SimulatedCommunicator(n_learners=1),
                                            stop=stop)
                except Exception as e:  # noqa: BLE001 - re-raised unless a learner failed
                    if not learners.failed():
                        raise
                    # A learner failed and the watcher's SIGTERM stopped C-ICRL: the
                    # learner's error is the news. The signal can land inside a checkpoint
                    # write, where torch's writer turns it into its own RuntimeError (the
                    # write is atomic: the last checkpoint stays valid).
                    if not isinstance(e, Interrupted):
                        first_line = str(e).splitlines()[0] if str(e) else ""
                        print(f"C-ICRL ended with {type(e).__name__} ({first_line}) while "
                              f"the failed learner stopped the run", file=sys.stderr,
                              flush=True)
                torch.set_num_threads(own_threads)  # the baselines run alone, as before
            learners.wait()
    except LearnerProcessError as e:
        first = e.tracebacks.get(e.first_failed) if e.first_failed is not None else None
        if first:
            print(first, file=sys.stderr)
        sys.exit(f"error: {e}\n{resume_hint(out)}")
    except Interrupted as e:
        print(f"\ninterrupted by {e}: every learner process was stopped; no results.json "
              f"was written. {resume_hint(out)}", file=sys.stderr, flush=True)
        sys.exit(128 + e.signum)
    finish_here(cfg, task, out, merge_learner_rows(out, n, run_id), t_start, ckpt=ckpt,
                logger=logger, c_icrl=c_icrl)


def run_torchrun(cfg, out: Path, t_start: float) -> None:
    """A process started by torchrun: learner ``RANK``; rank 0 also finishes the run."""
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    interrupt_on_signals()
    try:
        comm = build(cfg.comm, rank=rank, world_size=world_size)  # init_method env://
        comm.check_same_config(OmegaConf.to_yaml(cfg, resolve=True))
        out, run_id = agree_on_run_dir(comm, out)
        task = build_task(cfg, rank)
        if rank == 0:
            task.announce(out)
        run_learner(comm, task, run_settings(cfg), trainer_spec(cfg), out=out,
                    run_id=run_id, logger=make_logger(cfg, out))
        comm.close()
    except Exception as e:
        # Exit at once, without tearing down a process group with a dead peer (can hang).
        if not isinstance(e, PeerFailureError | ConfigMismatchError | Interrupted):
            traceback.print_exc()
        what = (f"interrupted by {e}" if isinstance(e, Interrupted)
                else f"{type(e).__name__}: {e}")
        print(f"error: learner {rank}: {what}\n{resume_hint(out)}", file=sys.stderr,
              flush=True)
        sys.stdout.flush()
        os._exit(128 + e.signum if isinstance(e, Interrupted) else 1)
    if rank == 0:
        finish_here(cfg, task, out, merge_learner_rows(out, world_size, run_id), t_start)


def run_simulated(cfg, out: Path, t_start: float) -> None:
    """Every learner in this process (``comm=simulated``)."""
    try:
        run_all_in_one(build_task(cfg), run_settings(cfg), trainer_spec(cfg), out=out,
                       t_start=t_start, logger=make_logger(cfg, out),
                       communicator=lambda n: build(cfg.comm, n_learners=n))
    except Interrupted as e:
        what = (f"checkpoint {e.saved}" if e.saved else
                "stopped at once; the last checkpoint written stays valid")
        print(f"\ninterrupted by {e} ({what}). Checkpoints are in {out / 'checkpoint.pt'}; "
              f"no results.json was written. Resume with:\n  {resume_command(out)}",
              file=sys.stderr, flush=True)
        sys.exit(128 + e.signum)  # the shell's convention for "killed by a signal"
    except NonFiniteError as e:
        # The checkpoints hold only finite states; rerun with the changes it suggests.
        print(f"error: {e}\nno results.json was written.", file=sys.stderr, flush=True)
        sys.exit(1)


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    t_start = time.perf_counter()
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        check_config(cfg)
        check_shard_contents(cfg)
    except ValueError as e:  # a ConfigError, or a shard file that does not fit the run
        print(f"error: {e}", file=sys.stderr, flush=True)
        sys.exit(2)
    torch.set_num_threads(int(os.environ.get("DICRL_THREADS", torch.get_num_threads())))
    if is_simulated(cfg):
        run_simulated(cfg, out, t_start)
    elif "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        run_torchrun(cfg, out, t_start)
    else:
        run_spawned(cfg, out, t_start)


if __name__ == "__main__":
    main()
