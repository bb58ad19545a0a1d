"""What the runner asks of an environment: :class:`Task`, the base class of every task
(:class:`~dicrl_torch.runs.grid.GridTask`, :class:`~dicrl_torch.runs.continuous.SACTask`
and its games).

A task answers five questions of its own (the abstract methods: what it is, the
learners' model, the metrics after each outer iteration, a trained learner's table row,
the settings that row depends on); everything else the runner asks is an optional hook
whose default here does nothing (no baselines, no reference rows, no figures, no
constraint map). Every call is complete in itself: what one call computes for a later
one is returned to the runner and handed back (a row's rollouts to its constraint map,
a baseline to its row), never left on the task.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from dicrl_torch.algos.dicrl import DICRL

__all__ = ["Rollouts", "Task"]

Rollouts = Sequence[np.ndarray]
"""A row's evaluation rollouts, one array per episode (the continuous games: the joint
states ``[L+1, N, d_s]`` or positions ``[L+1, N, 2]``, what the task's
:meth:`Task.constraint_map` draws); empty where none are kept (the grid world, a row
taken from a checkpoint)."""


class Task(ABC):
    """An environment as the runner sees it (module docstring).

    Attributes:
        split: trajectories per learner (public: it scales the steps).
        shards: each learner's demonstrations (None for another process's learner).
        demos: every learner's demonstrations pooled (C-ICRL's and the baselines' data).
        cost_basis: the learners' cost basis (its ``names`` label a row's constraints).
        columns: the metric columns of the printed table.
    """

    split: list[int]
    shards: list[Any]
    demos: Any
    cost_basis: Any
    columns: tuple[str, ...]

    def learned_mask(self, row: dict) -> np.ndarray:
        """``[l_c]`` bool: a row's learned constraints (its ``constraints`` names)."""
        names = list(self.cost_basis.names)
        mask = np.zeros(len(names), dtype=bool)
        mask[[names.index(n) for n in row.get("constraints") or ()]] = True
        return mask

    # ------------------------------------------------------------------ required
    @abstractmethod
    def describe(self) -> str:
        """One line on the problem (learners, demonstrations, features), printed once."""

    @abstractmethod
    def learner_model(self, local_ids: Sequence[int], shards: Sequence, stream: int):
        """The learner model of a trainer over ``local_ids`` holding ``shards`` (stream 0:
        D-ICRL, 1: C-ICRL)."""

    @abstractmethod
    def outer_metrics(self, trainer: DICRL, rollouts: bool) -> dict[str, list]:
        """This outer iteration's metrics of the trainer's local learners, each a list
        in local order (e.g. ``FPR``, ``FNR``); ``rollouts``: the iteration is one where
        the curves roll the policies out (CR, CVR), if the task has such metrics."""

    @abstractmethod
    def evaluate_learner(self, trainer: DICRL, i: int, progress: bool = True
                         ) -> tuple[dict, Rollouts]:
        """The table row of the trainer's local learner ``i`` and the rollouts it was
        measured on (:data:`Rollouts`, for :meth:`constraint_map`)."""

    @abstractmethod
    def evaluation_settings(self) -> dict[str, Any]:
        """What a trained method's rows depend on besides its state and the training
        config: a checkpointed row is reused only under the same settings."""

    # ------------------------------------------------------------------ optional hooks
    def before_evaluation(self, trainer) -> None:
        """Called on every process before its learners' rows are evaluated (a place for
        a collective the rows need, as every process of a run calls it once per method,
        whether or not its rows come from a checkpoint). Default: nothing."""
        return None

    def initial_weights(self) -> dict[str, float]:
        """``η(0)`` and ``ω_c(0)`` this task has already used (a SAC warm-up trained on
        them), as ``DICRL``'s ``init_reward_weights``, ``init_multiplier``,
        ``init_cost_weights``: the runner's trainers take them from here, so they are given
        once. Empty (default): the trainer spec's options decide."""
        return {}

    def announce(self, out: Path) -> None:
        """Once per run, by the main process, before training: here :meth:`describe`
        printed (a task also saves its demonstrations in ``out``)."""
        print(self.describe(), flush=True)

    def bind_run_dir(self, out: Path, training_config: dict, *, process: int = 0,
                     processes: int = 1) -> None:
        """The run directory, in every process of the run before it trains: a task may
        keep there what it computes once per run (the SAC warm-up), keyed by the run's
        ``training_config``, and share that work between the ``processes`` learner
        processes that reach it together (this one is ``process``). Nothing here."""
        return None

    def constraint_map(self, label: str, row: dict, rollouts: Rollouts = ()
                       ) -> np.ndarray | None:
        """A row's learned constraints as an ``H x W x 3`` uint8 image (PNG and
        TensorBoard), with ``rollouts`` the row was measured on where the task draws
        them; None (here): no map."""
        return None

    def row_scalars(self, row: dict) -> list[tuple[str, float, int]]:
        """Extra TensorBoard ``(tag, value, step)`` of a learner's row; none here."""
        return []

    def reference_rows(self) -> dict[str, dict]:
        """Rows that learn nothing (the experts), by name; none here."""
        return {}

    def annotate(self, methods: dict) -> dict | None:
        """Adds task-level metrics to the learned rows of ``methods`` (the grid:
        ``FNR_required`` and the identifiability counts); returns ``results.json``'s
        ``identifiability`` record, or None (here: nothing added)."""
        return None

    def make_baselines(self, methods: dict[str, dict], progress: bool = True) -> dict:
        """The baselines by row name, built but not run; ``methods`` holds the rows of the
        methods trained so far (a baseline may build on them, e.g. the continuous games'
        greedy on D-ICRL's learned reward). None here."""
        return {}

    def baseline_row(self, name: str, greedy, result) -> tuple[dict, list[dict], Rollouts]:
        """The table row of the finished baseline ``greedy`` (of :meth:`make_baselines`,
        ``result`` its run's), its per-step history and the row's rollouts. Only asked
        of a task whose :meth:`make_baselines` builds some."""
        raise NotImplementedError(f"{type(self).__name__}.make_baselines built {name!r} "
                                  f"but the task gives no baseline_row for it.")

    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """The run's figures by tag (``H x W x 3`` uint8), drawn after ``results.json``
        from the table ``methods`` and ``results.json``'s ``histories``; none here."""
        return {}
