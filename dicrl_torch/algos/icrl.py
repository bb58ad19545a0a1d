"""The inverse-constrained-RL quantities every learner computes (paper §3–5).

A learner's model of the experts is the constrained soft-Bellman policy of the reward

    r(s, a) = ω_r · φ_r(s, a) + λ · ω_c · φ_c(s, a),     η = [ω_r, λ]

and its local log-likelihood is ``F^[v](ω_c) = Σ_{ζ∈D^[v]} Σ_t γ^t ln π(a_t | s_t)``.

**Local gradient (LGA), derived.** With ``ln π_t(a|s) = Q_t(s,a) − V_t(s)``,
``∂V_t(s) = E_π[Σ_{k≥t} γ^{k−t} ∂r(S_k, A_k) | S_t = s]`` and ``∂r/∂ω_c = λ φ_c``, at
fixed ``η``::

    ∂F^[v]/∂ω_c = λ · ( Σ_{ζ∈D^[v]} Σ_t γ^t φ_c(s_t, a_t)  −  m^[v] · E_π[Σ_t γ^t φ_c] )
                  + Σ_ζ Σ_t γ^{t+1} ( E[∂V_{t+1}(S') | s_t, a_t] − ∂V_{t+1}(s_{t+1}) )

The last sum is zero-mean noise of the demonstrated transitions (exactly zero for
deterministic dynamics), which the LGA drops. The paper prints the LGA without the
factor ``λ``; with ``λ < 0`` (a penalty) the sign matters: a feature the model accrues but the
demonstrations do not gets a *positive* gradient, i.e. becomes more of a constraint.
The dependence of ``η*`` on ``ω_c`` adds nothing at the inner optimum, where the
global likelihood's gradient in ``η`` vanishes (moment matching).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dicrl_torch.demos.features import discounted_feature_sums
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import encode_joint
from dicrl_torch.features.bases import FactoredFeatures, FactoredReward
from dicrl_torch.solvers.factored import SoftBellmanSolution


def model_reward(reward_features: FactoredFeatures, cost_features: FactoredFeatures,
                 reward_weights: torch.Tensor, multiplier: float | torch.Tensor,
                 cost_weights: torch.Tensor) -> FactoredReward:
    """``r = ω_r · φ_r + λ ω_c · φ_c`` as a :class:`FactoredReward`."""
    lam = float(multiplier)
    return reward_features.weighted(reward_weights) + cost_features.weighted(
        cost_weights).scale(lam)


@dataclass(frozen=True)
class LocalStatistics:
    """What a learner computes once from its private demonstrations (never sent).

    Attributes:
        m: number of trajectories.
        mu_r_hat: ``[l_r]`` mean discounted reward-feature sum, ``μ̂_r^[v]``.
        cost_accrual: ``[l_c]`` mean discounted cost-feature sum; ``b̂_ωc^[v]`` is its
            dot product with ``ω_c``.
    """

    m: int
    mu_r_hat: torch.Tensor
    cost_accrual: torch.Tensor

    @classmethod
    def from_demonstrations(cls, demos: Demonstrations, reward_features: FactoredFeatures,
                            cost_features: FactoredFeatures, gamma: float) -> LocalStatistics:
        if demos.n_trajectories < 1:
            raise ValueError("A learner needs at least one demonstration; give each shard "
                             "one or more trajectories.")
        return cls(
            m=demos.n_trajectories,
            mu_r_hat=discounted_feature_sums(reward_features, demos, gamma).mean(0),
            cost_accrual=discounted_feature_sums(cost_features, demos, gamma).mean(0),
        )


def dual_gradient(solution, stats: LocalStatistics, cost_weights: torch.Tensor) -> torch.Tensor:
    """``∇_η G^[v] = [μ_r(π_η) − μ̂_r^[v], J_ωc(π_η) − b̂_ωc^[v]]``: ``[l_r + 1]``.

    ``solution``: any policy with expectations ``mu_r`` ``[l_r]`` and ``mu_c`` ``[l_c]``
    (:class:`dicrl_torch.algos.models.ModelSolution`)."""
    w = cost_weights.double()
    return torch.cat([solution.mu_r - stats.mu_r_hat,
                      (w @ (solution.mu_c - stats.cost_accrual)).reshape(1)])


def local_gradient(solution, stats: LocalStatistics, multiplier: float) -> torch.Tensor:
    """LGA ``λ (m b_acc − m E_π[Σ γ^t φ_c])``: ``[l_c]`` (see the module docstring)."""
    return float(multiplier) * stats.m * (stats.cost_accrual - solution.mu_c)


def log_likelihood(solution: SoftBellmanSolution, demos: Demonstrations) -> float:
    """``Σ_ζ Σ_t γ^t ln π_t(a_t | s_t)`` of ``demos`` under the solution's policy."""
    model = solution.solver.model
    A1 = model.n_actions
    total = 0.0
    for t in range(demos.horizon):
        cells = torch.tensor(demos.states[:, t])
        joint = encode_joint(torch.tensor(demos.actions[:, t]), A1)
        logp = torch.log_softmax(solution.q_values_at(t, cells).double(), 1)
        total += model.gamma**t * float(logp.gather(1, joint.unsqueeze(1)).sum())
    return total
