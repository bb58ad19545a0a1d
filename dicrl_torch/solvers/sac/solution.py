"""Rollout estimates of the SAC solver's policy (see :mod:`dicrl_torch.solvers.sac`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from dicrl_torch.solvers.sac.checks import _weights
from dicrl_torch.solvers.sac.features import _agent_shares

if TYPE_CHECKING:
    from dicrl_torch.solvers.sac.solver import SACConstrainedSolver

__all__ = ["SACSolution"]


def _mean_se(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard error over dim 0 (SE is NaN with one sample)."""
    n = x.shape[0]
    mean = x.mean(0)
    if n < 2:
        return mean, torch.full_like(mean, float("nan"))
    return mean, x.std(0, correction=1) / math.sqrt(n)


def _over_episodes(sums: str, doc: str, *, se: bool = False) -> property:
    """A read-only property: the mean over episodes (dim 0) of the ``[n, l]`` field
    ``sums``, or with ``se`` its standard error (:func:`_mean_se`)."""
    if se:
        return property(lambda self: _mean_se(getattr(self, sums))[1], doc=doc)
    return property(lambda self: getattr(self, sums).mean(0), doc=doc)


@dataclass(frozen=True)
class SACSolution:
    """Rollout estimates of the current SAC policy (the grid solver's counterpart).

    Attributes:
        reward_sums: ``[n, l_r]`` float64 per-episode discounted ``Σ_t γ^t φ_r(s_{t+1})``.
        cost_sums: ``[n, l_c]`` float64, the same for ``φ_c``.
        lengths: ``[n]`` int64 episode lengths.
        reached: ``[n, N]`` bool, agent reached its goal in the episode (the env's
            ``info["reached"]``).
        violated: ``[n, N]`` bool, agent violated a constraint of the game in the
            episode (``info["violated"]``).
        eta: ``[l_r + 1]`` float64 ``[ω_r, λ]`` the policy was trained for (or None).
        cost_weights: ``[l_c]`` float64 ``ω_c`` (or None).
        timesteps: env steps the SAC model had taken when evaluated.
        paths: per episode the joint states ``[L+1, N, d_s]`` (with
            ``evaluate(trajectories=True)``), else None.
    """

    reward_sums: torch.Tensor
    cost_sums: torch.Tensor
    lengths: torch.Tensor
    reached: torch.Tensor
    violated: torch.Tensor
    eta: torch.Tensor | None
    cost_weights: torch.Tensor | None
    timesteps: int
    solver: SACConstrainedSolver | None = field(default=None, repr=False, compare=False)
    paths: list[np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def n_episodes(self) -> int:
        return int(self.reward_sums.shape[0])

    mu_r = _over_episodes("reward_sums", "``[l_r]`` discounted reward-feature expectation "
                                         "``μ_r(π)``.")
    mu_r_se = _over_episodes("reward_sums", "``[l_r]`` standard error of :attr:`mu_r`.", se=True)
    mu_c = _over_episodes("cost_sums", "``[l_c]`` discounted cost-feature expectation "
                                       "``μ_c(π)``.")
    mu_c_se = _over_episodes("cost_sums", "``[l_c]`` standard error of :attr:`mu_c`.", se=True)

    def cost_value(self, cost_weights: Any = None) -> tuple[float, float]:
        """``J_ωc = ω_c · μ_c`` and its standard error over episodes.

        Args:
            cost_weights: ``[l_c]``; default the ``ω_c`` the policy was trained for.
        """
        w = self.cost_weights if cost_weights is None else cost_weights
        if w is None:
            raise ValueError("No cost_weights stored in this solution; pass cost_weights.")
        w = torch.as_tensor(_weights(w, "cost_weights", self.cost_sums.shape[1]))
        mean, se = _mean_se(self.cost_sums @ w)
        return float(mean), float(se)

    def penalised_return(self) -> tuple[float, float]:
        """The learned objective ``ω_r · μ_r + λ ω_c · μ_c`` under the weights the policy
        was trained for (the discounted return of its reward, without the entropy), and
        its standard error over episodes."""
        if self.eta is None or self.cost_weights is None:
            raise ValueError("This solution stores no (eta, cost_weights): it was not "
                             "trained for a reward; use solver.solve(...) first.")
        per = (self.reward_sums @ self.eta[:-1]
               + self.eta[-1] * (self.cost_sums @ self.cost_weights))  # [n]
        mean, se = _mean_se(per)
        return float(mean), float(se)

    def success_rate_under(self, constraints: Any) -> float:
        """SR in the game whose constraints are ``constraints`` (``[l_c]`` bool over the
        cost features, e.g. a learner's learned set): the fraction of agents that reached
        their goal without accruing any of those features that are theirs (per the cost
        basis's ``agent_shares()``; a shared one, e.g. a proximity, counts for every
        agent). Computed from this solution's rollouts (the solver's game: nominal by
        default)."""
        if self.solver is None:
            raise ValueError("This solution has no solver (its cost basis is needed).")
        mask = torch.as_tensor(np.asarray(constraints, dtype=bool).reshape(-1))
        if mask.shape != (self.cost_sums.shape[1],):
            raise ValueError(f"constraints must be [{self.cost_sums.shape[1]}] bool, got "
                             f"shape {tuple(mask.shape)}.")
        owned = torch.as_tensor(_agent_shares(self.solver.cost_basis, "cost_basis",
                                              self.reached.shape[1]) > 0)
        entered = (self.cost_sums > 0)[:, :, None] & (mask[:, None] & owned)[None]
        return float((self.reached & ~entered.any(1)).double().mean())

    @property
    def success_rate(self) -> float:
        """Fraction of agents that reached their goal without a violation (SR)."""
        return float((self.reached & ~self.violated).double().mean())

    @property
    def violation_rate(self) -> float:
        """Mean over episodes of the fraction of agents that violated (CVR)."""
        return float(self.violated.double().mean())

    def feature_expectation(self, features: Any) -> torch.Tensor:
        """``[l]`` discounted expectation of ``features``: the solver's reward or cost
        basis (the object itself, like the grid solver's accessor) or ``"reward"`` /
        ``"cost"``."""
        name = features if isinstance(features, str) else None
        if name == "reward" or (self.solver is not None
                                and features is self.solver.reward_basis):
            return self.mu_r
        if name == "cost" or (self.solver is not None and features is self.solver.cost_basis):
            return self.mu_c
        raise ValueError(
            f"feature_expectation takes the solver's reward_basis or cost_basis (or "
            f"'reward' / 'cost'), got {type(features).__name__}; other bases are not "
            f"recorded in the rollouts."
        )
