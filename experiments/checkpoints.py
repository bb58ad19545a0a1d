"""Checkpoints and signals of the entry points: trainer states written atomically,
refused on resume when the run's training config differs, and SIGINT/SIGTERM turned
into a checkpointed stop (:class:`StopOnSignal`) or an immediate one
(:func:`interrupt_on_signals`)."""

from __future__ import annotations

import copy
import hashlib
import os
import signal
import sys
from pathlib import Path
from typing import Any

import torch
from common import atomic_write
from omegaconf import OmegaConf

from dicrl_torch.algos.dicrl import DICRL

# What a checkpoint's training state depends on. Left out: how the run is started,
# logged, evaluated or stopped (resume, logger, eval_episodes, eval_every, threshold, ...),
# and algo.outer_iterations, so that a finished run can be resumed to train for longer.
# The history's metrics (FPR/FNR/RFD every outer iteration, CR/CVR every eval_every) are
# evaluations: each was taken with the settings of the run that computed its iteration,
# and the same overrides on resume give the uninterrupted run's history exactly.
CHECKPOINT_KEYS = ("seed", "n_demonstrations", "split", "expert_temperature", "env", "features",
                   "solver", "graph", "algo")
CHECKPOINT_IGNORED = ("solver.progress", "algo.outer_iterations", "algo.threshold",
                      "algo.prune_min_gain", "algo.run_c_icrl")


def training_config(cfg) -> dict[str, Any]:
    """The flattened ``key -> value`` config that a checkpoint must match to resume."""
    flat: dict[str, Any] = {}

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif path not in CHECKPOINT_IGNORED:
            flat[path] = node

    container = OmegaConf.to_container(cfg, resolve=True)
    walk({k: container[k] for k in CHECKPOINT_KEYS if k in container}, "")
    if container.get("shard_files") is not None:
        # Own demonstrations: the state depends on the files' contents, not on their paths.
        flat["shard_files.sha256"] = [hashlib.sha256(Path(f).read_bytes()).hexdigest()[:16]
                                      if Path(f).is_file() else None
                                      for f in container["shard_files"]]
    return flat


class Checkpoints:
    """Trainer states by name in one file, written atomically (to a temporary file, then
    renamed: a crash leaves the previous checkpoint intact).

    Args:
        path: the checkpoint file.
        resume: load ``path`` if it exists.
        keep_previous: also keep each name's previous save (``<name>:previous``), so that
            learner processes whose last saves are one save apart can agree on a state.
        crash_tags: extra names for the ``DICRL_CRASH_AFTER=<name>:<n>`` fault injection
            (tests): the process sends itself SIGKILL (or ``DICRL_CRASH_SIGNAL``, e.g.
            ``TERM``) right after saving ``n``, once.
        config: :func:`training_config` of this run; a checkpoint written under another one
            is refused on resume (its state would silently continue another problem).

    Raises:
        ValueError: the checkpoint cannot be read, or was written under another config.
    """

    def __init__(self, path: Path, resume: bool, *, keep_previous: bool = False,
                 crash_tags: tuple[str, ...] = (), config: dict | None = None) -> None:
        self.path, self.keep_previous, self.crash_tags = path, keep_previous, crash_tags
        self.config, self.crashed = config, False
        self.saved: dict = {}
        if resume and path.exists():
            self.saved = self._load(path)
            for state in self.saved.values():
                self._check_config(state.get("run_config"))
            done = {k: v["outer_iteration"] for k, v in self.saved.items()
                    if not k.endswith(":previous")}
            print(f"resuming from {path} (outer iterations done: {done})")
        elif resume:
            print(f"resume=true but no checkpoint {path.name} in {path.parent}; starting "
                  f"from scratch")

    def _check_config(self, saved: dict | None) -> None:
        if self.config is None or saved is None or saved == self.config:
            return
        keys = sorted(k for k in set(saved) | set(self.config)
                      if saved.get(k, "<unset>") != self.config.get(k, "<unset>"))
        diff = "; ".join(f"{k}: {saved.get(k, '<unset>')!r} in the checkpoint, "
                         f"{self.config.get(k, '<unset>')!r} now" for k in keys[:6])
        raise ValueError(
            f"{self.path} was written with a different configuration ({diff}"
            f"{'; ...' if len(keys) > 6 else ''}). Resume with the overrides of the "
            f"interrupted run, or start a new run without resume=true (in another "
            f"hydra.run.dir).")

    @staticmethod
    def _load(path: Path) -> dict:
        try:
            # weights_only: tensors and plain containers, never arbitrary pickled objects
            saved = torch.load(path, weights_only=True)
        except Exception as e:
            raise ValueError(
                f"{path} cannot be read as a checkpoint ({type(e).__name__}: "
                f"{str(e).strip().splitlines()[0] if str(e).strip() else ''}); it is not one "
                f"this program wrote. Delete it to start over, or point hydra.run.dir at the "
                f"run it belongs to.") from e
        if not (isinstance(saved, dict) and all(isinstance(v, dict) and "outer_iteration" in v
                                                for v in saved.values())):
            raise ValueError(f"{path} holds no trainer states ({type(saved).__name__}), so it "
                             f"is not a checkpoint of this program; delete it to start over.")
        return saved

    def states(self, name: str) -> list[dict]:
        """The saved states of ``name``, newest first."""
        return [self.saved[k] for k in (name, f"{name}:previous") if k in self.saved]

    def save(self, name: str, trainer: DICRL) -> None:
        n = trainer.state.outer_iteration
        last = self.saved.get(name)
        if self.keep_previous and last is not None and last["outer_iteration"] != n:
            self.saved[f"{name}:previous"] = last
        # A copy: the trainer goes on changing its history list and, when pruning, ω_c in
        # place, and this state may be written again (with another name's save).
        self.saved[name] = {**copy.deepcopy(trainer.state_dict()), "run_config": self.config}
        atomic_write(self.path, lambda tmp: torch.save(self.saved, tmp))
        crash = os.environ.get("DICRL_CRASH_AFTER")  # fault injection for tests
        if not self.crashed and crash in {f"{tag}:{n}" for tag in (name, *self.crash_tags)}:
            self.crashed = True
            sig = getattr(signal, "SIG" + os.environ.get("DICRL_CRASH_SIGNAL", "KILL"))
            os.kill(os.getpid(), sig)


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

    The first signal during training lets the current outer iteration finish (a state
    in the middle of one is no consistent checkpoint; an iteration takes seconds), then
    :func:`train` checkpoints it and raises :class:`Interrupted`. A second signal, or one
    outside training, raises at once: every checkpoint is written atomically, so the
    last one stays valid, and everything after training is recomputed on resume.
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
                  f"iteration, with a checkpoint (send it again to stop at once)",
                  file=sys.stderr, flush=True)
            return
        raise Interrupted(signum)


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


