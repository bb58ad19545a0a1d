"""What the D-ICRL trainer needs from a learner's model of the experts.

The trainer (:class:`dicrl_torch.algos.dicrl.DICRL`) owns the loops of Algorithms 1–2;
everything that depends on the environment — the feature bases, the policy class and
the inner solver — sits behind one small interface, :class:`LearnerModel`. Two
implementations ship:

- :class:`TabularLearnerModel`: the exact factored soft-Bellman solver of the grid
  world (deterministic, stateless: every learner shares it).
- :class:`dicrl_torch.solvers.sac.SACLearnerModel`: one SAC-style solver per local
  learner for the continuous drone arena (stochastic estimates from rollouts,
  warm-started across calls, so each learner keeps its own).

A new environment needs only a new ``LearnerModel``; the trainer does not change.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol, runtime_checkable

import torch

from dicrl_torch.algos.icrl import LocalStatistics, log_likelihood, model_reward
from dicrl_torch.features.bases import FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman, SoftBellmanSolution


@runtime_checkable
class ModelSolution(Protocol):
    """The policy ``π_{η, ω_c}`` a learner's model returns, with its discounted feature
    expectations ``mu_r`` ``[l_r]`` and ``mu_c`` ``[l_c]`` (float64)."""

    @property
    def mu_r(self) -> torch.Tensor: ...

    @property
    def mu_c(self) -> torch.Tensor: ...


@runtime_checkable
class LearnerModel(Protocol):
    """A learner's model of the experts: feature bases plus an inner solver.

    ``learner`` arguments index the learners *local to this process* (0 .. n-1, in the
    communicator's ``local_ids`` order): a stateful solver (SAC) keeps one policy per
    learner; a stateless one (tabular) ignores the index.
    """

    reward_dim: int  # l_r
    cost_dim: int  # l_c = d

    def statistics(self, demos: Any) -> LocalStatistics:
        """The learner's private μ̂_r ``[l_r]``, cost accrual ``[l_c]`` and count m."""
        ...

    def solve(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor
              ) -> ModelSolution:
        """The MCE policy of ``r = ω_r·φ_r + λ ω_c·φ_c`` for ``η = [ω_r, λ]`` ``[l_r + 1]``
        and ``ω_c`` ``[l_c]``."""
        ...

    def log_likelihood(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor,
                       demos: Any) -> float:
        """``Σ_ζ Σ_t γ^t ln π_{η, ω_c}(a_t | s_t)`` of ``demos``."""
        ...

    def describe(self) -> str:
        """Shapes and settings a checkpoint of a trainer over this model must match."""
        ...


@dataclass
class TabularSolution:
    """A :class:`SoftBellmanSolution` with its expectations over the model's bases.

    Attributes:
        soft_bellman: the exact solution (policy, values, occupancies).
        mu_r: ``[l_r]`` ``E_π[Σ_t γ^t φ_r]``; mu_c: ``[l_c]`` the same for ``φ_c``
            (computed on first use: the LGA needs only ``mu_c``).
    """

    soft_bellman: SoftBellmanSolution
    reward_features: Any = field(repr=False)
    cost_features: Any = field(repr=False)

    @cached_property
    def mu_r(self) -> torch.Tensor:
        return self.soft_bellman.feature_expectation(self.reward_features)

    @cached_property
    def mu_c(self) -> torch.Tensor:
        return self.soft_bellman.feature_expectation(self.cost_features)


class TabularLearnerModel:
    """The grid world's learner model: the exact factored soft-Bellman solver.

    Args:
        solver: the solver of the learners' (nominal) model.
        reward_basis, cost_basis: feature bases ``φ_r`` and ``φ_c``.
    """

    def __init__(self, *, solver: FactoredSoftBellman, reward_basis: FeatureBasis,
                 cost_basis: FeatureBasis) -> None:
        self.solver, self.model = solver, solver.model
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        self.fr, self.fc = reward_basis(), cost_basis()
        self.reward_dim, self.cost_dim = self.fr.dim, self.fc.dim
        self.dtype = getattr(solver, "dtype", None)

    def statistics(self, demos) -> LocalStatistics:
        return LocalStatistics.from_demonstrations(demos, self.fr, self.fc, self.model.gamma)

    def _reward(self, eta: torch.Tensor, cost_weights: torch.Tensor):
        return model_reward(self.fr, self.fc, eta[:-1], float(eta[-1]), cost_weights)

    def solve(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor
              ) -> TabularSolution:
        return TabularSolution(self.solver.solve(self._reward(eta, cost_weights)),
                               self.fr, self.fc)

    def log_likelihood(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor,
                       demos) -> float:
        # The likelihood needs only Q: skip the forward (occupancy) pass.
        sol = self.solver.solve(self._reward(eta, cost_weights), forward=False)
        return log_likelihood(sol, demos)

    def describe(self) -> str:
        m = self.model
        return f"T={m.horizon} S1={m.n_cells} N={m.n_experts}"
