"""Callbacks of the D-ICRL trainer (the shape stable-baselines3 users know): logging,
checkpointing, evaluation and stopping attach here, never as attributes set on the
trainer from outside (docs/design.md §2).

A callback overrides the hooks it needs; :class:`~dicrl_torch.algos.dicrl.DICRL` calls
them in the order given:

- ``on_inner_gradients`` after every dual gradient of an inner process (Algorithm 2),
- ``on_outer_end`` after every outer iteration (Algorithm 1), with the history entry
  just appended (a callback may add evaluation metrics to it, in place, before a later
  callback checkpoints the trainer).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from dicrl_torch.algos.dicrl import DICRL


class TrainerCallback:
    """Hooks the trainer calls; the defaults do nothing."""

    def on_inner_gradients(self, trainer: DICRL, *, learners: Sequence[int], step: int,
                           gradients: torch.Tensor, eta: torch.Tensor) -> None:
        """After the dual gradients of one inner step.

        Args:
            learners: local learner indices whose OWN inner process this is (an inner
                process for another learner's ω_c is not theirs to log).
            step: ``outer_iteration · K + k``.
            gradients: ``[n_local, p]`` ``∇G^[v](η^[v])`` (unscaled).
            eta: ``[n_local, p]`` the η = [ω_r, λ] they were taken at.
        """

    def on_outer_end(self, trainer: DICRL, info: dict[str, Any]) -> None:
        """After outer iteration ``info["outer_iteration"]``; ``info`` is
        ``trainer.history[-1]``."""


class FunctionCallback(TrainerCallback):
    """``fn(trainer, info)`` after every outer iteration."""

    def __init__(self, fn: Callable[[DICRL, dict], None]) -> None:
        self.fn = fn

    def on_outer_end(self, trainer: DICRL, info: dict[str, Any]) -> None:
        self.fn(trainer, info)


class InnerScalars(TrainerCallback):
    """``inner/dual_gradient_norm``, ``inner/multiplier`` and ``inner/reward_weight_norm``
    of each learner's own inner process, in the run ``run_name(v)`` of ``logger``."""

    def __init__(self, logger, run_name: Callable[[int], str]) -> None:
        self.logger, self.run_name = logger, run_name

    def on_inner_gradients(self, trainer: DICRL, *, learners: Sequence[int], step: int,
                           gradients: torch.Tensor, eta: torch.Tensor) -> None:
        for i in learners:
            run = self.run_name(trainer.local[i])
            self.logger.scalar(run, "inner/dual_gradient_norm", float(gradients[i].norm()),
                               step)
            self.logger.scalar(run, "inner/multiplier", float(eta[i, -1]), step)
            self.logger.scalar(run, "inner/reward_weight_norm", float(eta[i, :-1].norm()),
                               step)
