"""Checkpoints of a run: every trained method's state (and a greedy baseline's progress)
by name in one file, written atomically, loaded with ``torch.load(weights_only=True)``,
and refused on resume when the run's training config differs (docs/design.md §8).

The command line merges a method trained in a job of its own into the run it belongs to::

    python -m dicrl_torch.runs.checkpoints merge SOURCE INTO --method C-ICRL
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import signal
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from dicrl_torch.io import atomic_write

# What a checkpoint's training state depends on. Left out: how the run is started,
# logged, evaluated or stopped (resume, logger, eval_episodes, eval_every, threshold, the
# planner of eval_policy=plan, ...), and algo.outer_iterations, so that a finished run can
# be resumed to train for longer or to be evaluated again.
# The history's metrics (FPR/FNR/RFD every outer iteration, CR/CVR every eval_every) are
# evaluations: each was taken with the settings of the run that computed its iteration,
# and the same overrides on resume give the uninterrupted run's history exactly.
CHECKPOINT_KEYS = ("seed", "n_demonstrations", "split", "expert_temperature", "env", "features",
                   "solver", "graph", "algo")
# env.task names the function that builds the task from the config's other keys: how the
# run was assembled, not what it trains (runs checkpointed before it existed resume).
CHECKPOINT_IGNORED = ("env.task", "solver.progress", "solver.planner", "algo.outer_iterations",
                      "algo.threshold",
                      "algo.prune_min_gain", "algo.constraint_rule", "algo.certificate",
                      "algo.run_c_icrl", "algo.run_d_icrl", "algo.c_icrl_beside_learners")
# Keys added since checkpoints were first written, with the value that gives the training
# of the releases before them: an older checkpoint reads as holding that value.
CHECKPOINT_ADDED = {"algo.merge_stateful_inner": False}


def _ignored(key: str) -> bool:
    """Whether a flattened config key is, or lies under, a :data:`CHECKPOINT_IGNORED` path."""
    return any(key == path or key.startswith(path + ".") for path in CHECKPOINT_IGNORED)


def training_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """The flattened ``key -> value`` config that a checkpoint must match to resume.

    Args:
        config: the run's whole config as plain nested dicts (the entry point's resolved
            Hydra config, ``OmegaConf.to_container(cfg, resolve=True)``).
    """
    flat: dict[str, Any] = {}

    def walk(node, path):
        if path in CHECKPOINT_IGNORED:  # a leaf or a whole node (algo.certificate)
            return
        if isinstance(node, Mapping):
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k))
        else:
            flat[path] = node

    walk({k: config[k] for k in CHECKPOINT_KEYS if k in config}, "")
    if config.get("shard_files") is not None:
        # Own demonstrations: the state depends on the files' contents, not on their paths.
        flat["shard_files.sha256"] = [hashlib.sha256(Path(f).read_bytes()).hexdigest()[:16]
                                      if Path(f).is_file() else None
                                      for f in config["shard_files"]]
    return flat


def config_diff(a: dict, b: dict, a_is: str, b_is: str) -> str:
    """The first keys in which two :func:`training_config` dicts differ, for a message."""
    keys = sorted(k for k in set(a) | set(b) if a.get(k, "<unset>") != b.get(k, "<unset>"))
    return "; ".join(f"{k}: {a.get(k, '<unset>')!r} {a_is}, {b.get(k, '<unset>')!r} {b_is}"
                     for k in keys[:6]) + ("; ..." if len(keys) > 6 else "")


# A trained method's evaluated table rows are saved as "<method>:evaluated": evaluating
# prunes each learner's constraint set, one solve per candidate (minutes per learner on
# the 3-expert problem), and a run stopped after that point must not do it again.
EVALUATED = ":evaluated"


def progress_of(state: dict) -> str:
    """How far a saved state is: a trainer's outer iterations, a greedy baseline's
    candidates (its ``greedy`` progress record, ``dicrl_torch.algos.greedy``)."""
    if "greedy" not in state:
        return f"after outer iteration {state['outer_iteration']}"
    record = state["greedy"]
    return (f"at {record['evaluated']} candidates evaluated"
            f"{', finished' if record['finished'] else ''}")


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
            latest = {k: v for k, v in self.saved.items()
                      if not k.endswith((":previous", EVALUATED))}
            done = {k: v["outer_iteration"] for k, v in latest.items() if "greedy" not in v}
            greedy = "".join(f"; {k} {progress_of(v)}" for k, v in latest.items() if "greedy" in v)
            print(f"resuming from {path} (outer iterations done: {done}{greedy})")
        elif resume:
            print(f"resume=true but no checkpoint {path.name} in {path.parent}; starting "
                  f"from scratch")

    def _check_config(self, saved: dict | None) -> None:
        if self.config is None or saved is None:
            return
        # A checkpoint of an older release may hold keys ignored since (solver.planner).
        saved = {k: v for k, v in saved.items() if not _ignored(k)}
        saved = {**{k: v for k, v in CHECKPOINT_ADDED.items() if k in self.config}, **saved}
        if saved == self.config:
            return
        raise ValueError(
            f"{self.path} was written with a different configuration "
            f"({config_diff(saved, self.config, 'in the checkpoint', 'now')}). Resume with "
            f"the overrides of the interrupted run, or start a new run without resume=true "
            f"(in another hydra.run.dir).")

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

    def evaluated_rows(self, name: str, outer_iteration: int,
                       settings: dict[str, Any]) -> list[dict] | None:
        """The rows of ``name`` saved by :meth:`save_rows` after ``outer_iteration`` under
        the evaluation ``settings``; None if there are none (or they are of another state
        or settings)."""
        saved = self.saved.get(name + EVALUATED)
        if (saved is None or saved["outer_iteration"] != outer_iteration
                or saved["evaluation"] != settings):
            return None
        return copy.deepcopy(saved["rows"])

    def save_rows(self, name: str, outer_iteration: int, settings: dict[str, Any],
                  rows: list[dict]) -> None:
        """Save the table ``rows`` of ``name``'s local learners, evaluated after
        ``outer_iteration`` under ``settings`` (:func:`evaluation_settings`)."""
        # Through JSON: plain Python values, which torch.load(weights_only=True) reads back,
        # and exactly what results.json holds.
        plain = json.loads(json.dumps(rows))
        self.save_state(name + EVALUATED, {"outer_iteration": outer_iteration,
                                           "evaluation": settings, "rows": plain})

    def save(self, name: str, trainer) -> None:
        """Save a trainer's ``state_dict()`` as ``name``."""
        self.save_state(name, trainer.state_dict())

    def save_state(self, name: str, state: dict) -> None:
        """Save ``state`` as ``name``; ``state["outer_iteration"]`` counts its progress
        (a trainer's outer iterations, a greedy baseline's candidates evaluated)."""
        n = state["outer_iteration"]
        last = self.saved.get(name)
        if self.keep_previous and last is not None and last["outer_iteration"] != n:
            self.saved[f"{name}:previous"] = last
        # A copy: the trainer goes on changing its history list and, when pruning, ω_c in
        # place, and this state may be written again (with another name's save).
        self.saved[name] = {**copy.deepcopy(state), "run_config": self.config}
        atomic_write(self.path, lambda f: torch.save(self.saved, f))
        crash = os.environ.get("DICRL_CRASH_AFTER")  # fault injection for tests
        if not self.crashed and crash in {f"{tag}:{n}" for tag in (name, *self.crash_tags)}:
            self.crashed = True
            sig = getattr(signal, "SIG" + os.environ.get("DICRL_CRASH_SIGNAL", "KILL"))
            os.kill(os.getpid(), sig)


def merge(source: Path, into: Path, names: list[str]) -> dict[str, int]:
    """Copy the saved states ``names`` (e.g. ``C-ICRL``, ``ME-greedy``) of ``source``
    into ``into``.

    A method trained in its own job (``algo.run_d_icrl=false``, and
    ``algo.run_c_icrl=false`` for the greedy baselines alone) thus joins the run it
    belongs to, which then resumes past it. Both files must have been written under the
    same training config, and ``into`` must not be written meanwhile (stop its run first).

    Returns:
        ``{name: outer iterations}`` of the states copied.

    Raises:
        ValueError: a file is no checkpoint, lacks a state, was written under another
            config, or ``into`` already holds the state as far or further.
    """
    src, dst = Checkpoints._load(source), Checkpoints._load(into)
    config = next((s.get("run_config") for s in dst.values()), None)
    copied = {}
    for name in names:
        if name not in src:
            raise ValueError(f"{source} holds no {name} state (it has {sorted(src)}); "
                             f"train it there first.")
        theirs = src[name].get("run_config")
        if config is not None and theirs is not None and theirs != config:
            raise ValueError(f"{source}'s {name} was trained under another configuration "
                             f"than {into}'s run ({config_diff(theirs, config, 'there', 'here')}"
                             f"); train it again with the run's overrides.")
        n, have = src[name]["outer_iteration"], dst.get(name, {}).get("outer_iteration", -1)
        if have >= n:
            raise ValueError(f"{into} already holds {name} {progress_of(dst[name])}, and "
                             f"{source} only {progress_of(src[name])}; nothing to merge.")
        for key in (name, f"{name}:previous", name + EVALUATED):
            if key in src:
                dst[key] = src[key]
            else:  # of the state replaced
                dst.pop(key, None)
        copied[name] = n
    atomic_write(into, lambda f: torch.save(dst, f))
    return copied


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m dicrl_torch.runs.checkpoints",
        description="Checkpoint tools of the runs of experiments/train.py.")
    commands = parser.add_subparsers(dest="command", required=True)
    m = commands.add_parser(
        "merge", help="copy a method's state from one run's checkpoint into another's",
        description="Copy saved states (C-ICRL trained in its own job with "
                    "algo.run_d_icrl=false, a greedy baseline's progress) from SOURCE into "
                    "INTO, so that the run of INTO resumes past them. Stop the run that "
                    "writes INTO first.")
    m.add_argument("source", type=Path, help="checkpoint.pt holding the trained method")
    m.add_argument("into", type=Path, help="checkpoint.pt of the run it joins")
    m.add_argument("--method", action="append", required=True,
                   help="state to copy (repeatable): C-ICRL, ME-greedy or MCE-greedy")
    args = parser.parse_args(argv)
    try:
        copied = merge(args.source, args.into, args.method)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    saved = Checkpoints._load(args.into)
    print(f"{args.into}: " + ", ".join(f"{k} now {progress_of(saved[k])}" for k in copied))


if __name__ == "__main__":
    main()
