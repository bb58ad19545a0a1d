"""What the D-ICRL trainer needs from a learner's model of the experts.

The trainer (:class:`dicrl_torch.algos.dicrl.DICRL`) owns the loops of Algorithms 1–2;
everything that depends on the environment — the feature bases, the policy class and
the inner solver — sits behind one small interface, :class:`LearnerModel`. Two
implementations ship:

- :class:`TabularLearnerModel`: the exact factored soft-Bellman solver of the grid
  world (deterministic, stateless: every learner shares it).
- :class:`SACLearnerModel`: one SAC-style solver
  (:class:`~dicrl_torch.solvers.sac.SACConstrainedSolver`) per local learner for a
  continuous game such as the drone arena (stochastic estimates from rollouts,
  warm-started across calls, so each learner keeps its own, and its state is part of a
  checkpoint).

A new environment needs only a new ``LearnerModel``; the trainer does not change.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
import torch

from dicrl_torch.algos.icrl import LocalStatistics, log_likelihood, model_reward
from dicrl_torch.envs.grid import encode_joint
from dicrl_torch.features.bases import FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman, SoftBellmanSolution

if TYPE_CHECKING:  # imported where used: SB3 is slow to import and the grid world never
    # needs it
    from dicrl_torch.solvers.sac import SACConstrainedSolver, SACSolution


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
    stateful: bool
    """False when every learner shares one stateless, exact solver (tabular: identical
    inner processes may be computed once); True when each learner owns a solver whose
    state changes with every solve (SAC, warm-started)."""

    def inner_solver(self, learner: int) -> Any:
        """The solver learner ``learner`` solves with (the shared one when stateless)."""
        ...

    def state_dict(self) -> dict:
        """The solvers' state, as tensors and plain values (empty when stateless)."""
        ...

    def load_state_dict(self, sd: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        ...

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

    # Optional: ``solve_all(etas [n, l_r + 1], cost_weights [n, l_c]) -> list`` solves
    # every local learner at once, with the numbers of n calls of solve (the trainer
    # uses it where it has one; SACLearnerModel trains its learners as one ensemble).

    def describe(self) -> str:
        """Shapes and settings a checkpoint of a trainer over this model must match."""
        ...

    def start_features(self) -> torch.Tensor:
        """``[l_c]`` bool: the cost features P0 gives mass to (accrued at a start state
        whatever the action). With budget 0 none of them can be a constraint: the trainer
        keeps their ω_c at 0 (the learner knows P0; this is no ground truth)."""
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

    @property
    def policy_at(self) -> Callable[..., torch.Tensor]:
        """The policy ``(t, cells) -> [B, A1^N]`` (:meth:`SoftBellmanSolution.policy_at`)."""
        return self.soft_bellman.policy_at


class TabularLearnerModel:
    """The grid world's learner model: the exact factored soft-Bellman solver, shared
    by every learner (stateless: a solve depends only on its arguments).

    Args:
        solver: the solver of the learners' (nominal) model.
        reward_basis, cost_basis: feature bases ``φ_r`` and ``φ_c``.
    """

    stateful = False

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

    def inner_solver(self, learner: int) -> FactoredSoftBellman:
        """The shared solver (every learner's)."""
        return self.solver

    def start_features(self) -> torch.Tensor:
        """``[l_c]`` bool: the cost features positive at some start state ``s`` with
        ``P0(s) > 0`` whatever the joint action (``min_a φ_j(s, a) > 0``): accrued with
        positive probability by any policy, so with budget 0 none is a constraint.

        ``φ(s, a) = Σ_i local[i, s_i, a_i] + joint[s]`` with each expert's action free, so
        ``min_a φ_j(s, a) = Σ_i min_{a_i} local[i, s_i, a_i, j] + joint[s, j]`` exactly:
        ``[K, l_c]`` over P0's K support states, never ``K × A1^N`` pairs (3 experts with
        varied starts have K in the ten thousands and 729 joint actions)."""
        m, fc = self.model, self.fc
        support = m.start_support()  # [K, N]
        lowest = fc.local.amin(dim=2)  # [N, S1, l]: each expert's least over its actions
        phi = sum(lowest[i, support[:, i]] for i in range(m.n_experts))  # [K, l]
        if fc.joint is not None:
            flat = encode_joint(support, m.n_cells)
            phi = phi.index_add(1, fc.joint_columns, fc.joint[flat].to(phi.dtype))
        return (phi > 0).any(0)

    def state_dict(self) -> dict:
        """Empty: the exact solver has no state."""
        return {}

    def load_state_dict(self, sd: dict) -> None:
        """Nothing to load; ``sd`` must be the empty :meth:`state_dict`."""
        if sd:
            raise ValueError(f"A tabular learner model has no state, but this one holds "
                             f"{sorted(sd)[:4]} (a stateful model's?); resume with the "
                             f"learner model that saved it.")

    def describe(self) -> str:
        m = self.model
        return f"T={m.horizon} S1={m.n_cells} N={m.n_experts}"


class SACLearnerModel:
    """The continuous learners' model: one
    :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` per local learner (stateful).

    Each local learner owns one solver: SAC is warm-started across calls, so a solver's
    state is that learner's policy. Every :meth:`solve` continues training for
    ``timesteps`` env steps on the new ``(η, ω_c)`` and then estimates ``μ_r``, ``μ_c``
    from ``n_eval_episodes`` rollouts; the estimates are noisy, which the trainer's
    diminishing steps average out.

    Args:
        solvers: one solver per local learner (same bases, discount and game).
        timesteps: env steps of SAC training per solve (per inner step).
        n_eval_episodes: rollouts per estimate (default each solver's own).
        start_states: ``[P, N, d_s]`` joint states spanning the support of the game's
            start distribution P0 (e.g. :func:`dicrl_torch.envs.drones.start_support`),
            for :meth:`start_features`; None: P0 is not known to pin any feature.
    """

    stateful = True

    def __init__(self, *, solvers: Sequence[SACConstrainedSolver], timesteps: int,
                 n_eval_episodes: int | None = None, start_states: Any = None) -> None:
        from dicrl_torch.solvers.sac import SACConstrainedSolver

        solvers = list(solvers)
        if not solvers or not all(isinstance(s, SACConstrainedSolver) for s in solvers):
            raise ValueError("solvers must be a non-empty list of SACConstrainedSolver, one "
                             "per local learner.")
        first = solvers[0]
        for s in solvers[1:]:
            if (s.l_r, s.l_c, s.gamma, s.absorbing, s.spec) != (
                    first.l_r, first.l_c, first.gamma, first.absorbing, first.spec):
                raise ValueError("All learners' solvers must share the feature bases' "
                                 "widths, gamma, the absorbing convention and the game.")
        if not _is_int(timesteps) or timesteps < 0:
            raise ValueError(f"timesteps must be an int >= 0, got {timesteps!r}.")
        if n_eval_episodes is not None and (not _is_int(n_eval_episodes)
                                            or n_eval_episodes < 1):
            raise ValueError(f"n_eval_episodes must be a positive int, got {n_eval_episodes!r}.")
        self.solvers, self.timesteps, self.n_eval_episodes = solvers, int(timesteps), \
            n_eval_episodes
        self.reward_dim, self.cost_dim = first.l_r, first.l_c
        self.dtype = None
        self.start_states = None if start_states is None else torch.as_tensor(start_states)

    def inner_solver(self, learner: int) -> SACConstrainedSolver:
        """Learner ``learner``'s own solver (its policy is the solver's state)."""
        if not _is_int(learner) or not 0 <= learner < len(self.solvers):
            raise ValueError(f"learner {learner} has no solver: this model holds "
                             f"{len(self.solvers)}; give one solver per local learner.")
        return self.solvers[learner]

    def start_features(self) -> torch.Tensor:
        """The cost features positive anywhere on the support of P0 (``start_states``):
        the solver's features count next states, so the demonstrations never accrue
        these. All False without ``start_states``."""
        if self.start_states is None:
            return torch.zeros(self.cost_dim, dtype=torch.bool)
        phi = self.solvers[0].cost_basis(self.start_states)
        return (phi > 0).any(0)

    def statistics(self, demos: Any) -> LocalStatistics:
        """``μ̂_r``, the cost accrual and ``m`` of a learner's episodes, counted as the
        solver counts its rollouts (next-state features, absorbing end). ``demos``:
        ``ContinuousDemonstrations`` of the solvers' game (or with ``to_continuous()``,
        e.g. ``DroneDemonstrations``)."""
        from dicrl_torch.solvers.sac import discounted_demo_feature_sums
        from dicrl_torch.solvers.sac.protocol import as_continuous

        s = self.solvers[0]
        demos = as_continuous(demos, s.spec)  # refused, naming the fix, if it does not fit

        def mean(basis: torch.nn.Module) -> torch.Tensor:
            return discounted_demo_feature_sums(demos, basis, s.gamma,
                                                absorbing=s.absorbing).mean(0)

        return LocalStatistics(m=demos.n_episodes, mu_r_hat=mean(s.reward_basis),
                               cost_accrual=mean(s.cost_basis))

    def solve(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor
              ) -> SACSolution:
        return self.inner_solver(learner).solve(eta, cost_weights, self.timesteps,
                                                n_eval_episodes=self.n_eval_episodes)

    def solve_all(self, etas: torch.Tensor, cost_weights: torch.Tensor) -> list[SACSolution]:
        """Every local learner's :meth:`solve` (``etas`` ``[n, l_r + 1]``, ``cost_weights``
        ``[n, l_c]``), their SAC trained as one ensemble: the same numbers as solving
        them one by one (:meth:`SACConstrainedSolver.solve_together`)."""
        from dicrl_torch.solvers.sac import SACConstrainedSolver

        if len(etas) != len(self.solvers) or len(cost_weights) != len(self.solvers):
            raise ValueError(f"solve_all needs one η and one ω_c per local learner "
                             f"({len(self.solvers)}), got {len(etas)} and {len(cost_weights)}.")
        return SACConstrainedSolver.solve_together(self.solvers, etas, cost_weights,
                                                   self.timesteps,
                                                   n_eval_episodes=self.n_eval_episodes)

    def log_likelihood(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor,
                       demos: Any) -> float:
        """Trains on ``(η, ω_c)`` for ``timesteps`` first (the policy IS the solver's
        state), then scores ``demos`` under it."""
        solver = self.inner_solver(learner)
        solver.solve(eta, cost_weights, self.timesteps, n_eval_episodes=1)
        return solver.log_likelihood(demos)

    def state_dict(self) -> dict:
        """Every learner's solver state (:meth:`SACConstrainedSolver.state_dict`), in
        learner order: tensors and plain values only."""
        return {"solvers": [s.state_dict() for s in self.solvers]}

    def load_state_dict(self, sd: dict) -> None:
        """Continue every learner's solver from a :meth:`state_dict` (all are checked
        before any is changed)."""
        states = sd.get("solvers") if isinstance(sd, dict) else None
        if not isinstance(states, list) or len(states) != len(self.solvers):
            found = len(states) if isinstance(states, list) else "no"
            raise ValueError(f"This SAC learner-model state holds {found} solver states, the "
                             f"model {len(self.solvers)} solvers (one per local learner); "
                             f"resume with the same learners.")
        for k, (solver, state) in enumerate(zip(self.solvers, states, strict=True)):
            try:
                solver.check_state(state)
            except ValueError as e:
                raise ValueError(f"learner {k}'s solver: {e}") from None
        for solver, state in zip(self.solvers, states, strict=True):
            solver.load_state_dict(state)

    def describe(self) -> str:
        s = self.solvers[0]
        return (f"SAC x{len(self.solvers)} steps={self.timesteps} gamma={s.gamma} "
                f"ent={s.ent_coef} absorbing={s.absorbing}")


def _is_int(x: Any) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool)
