"""The result of a factored solve: values, occupancies, and the policy at any state."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from dicrl_torch.features.bases import FactoredReward

if TYPE_CHECKING:
    from dicrl_torch.solvers.factored.solver import FactoredSoftBellman


@dataclass
class SoftBellmanSolution:
    """Result of :meth:`FactoredSoftBellman.solve`.

    Attributes:
        values: ``[T+1, S1, .., S1]`` the values about their per-step baseline,
            ``V_t - c_t`` (solver dtype): what the policy is computed from.
        baseline: ``[T+1]`` float64 (CPU) ``c_t``, a constant over states per step.
        V: ``[T+1, S1, .., S1]`` the values ``V_t = values_t + c_t`` (``V[T]`` the terminal
            value, default 0), in the solver dtype.
        state_occupancy: ``[S1]*N`` float64, ``Σ_t γ^t d_t(s)`` (None if not computed).
        local_occupancy: ``[N, S1, A1]`` float64, ``Σ_t γ^t ρ_t^i(s_i, a_i)`` — each
            expert's marginal of the discounted state-action occupancy.
        backup: ``"causal"`` (MCE) or ``"trajectory"`` (ME, Ziebart 2008): the model
            the values, policy and occupancies belong to.
        log_partition: causal: ``Σ_s P0(s) V_0(s)``; trajectory:
            ``τ log Σ_s P0(s) exp(V_0(s)/τ)`` (``log Z``).
    """

    values: torch.Tensor
    baseline: torch.Tensor
    reward: FactoredReward
    temperature: float
    solver: FactoredSoftBellman = field(repr=False)
    state_occupancy: torch.Tensor | None = None
    local_occupancy: torch.Tensor | None = None
    timings: dict[str, float] = field(default_factory=dict)
    backup: str = "causal"

    @property
    def V(self) -> torch.Tensor:
        """``[T+1, S1, .., S1]`` absolute values in the solver dtype (a new tensor; in
        float32 they are rounded at their own scale, so that :attr:`values` and
        :attr:`baseline` are what precise uses read)."""
        out = torch.empty_like(self.values)
        for t, c in enumerate(self.baseline.tolist()):
            out[t] = self.values[t].double() + c
        return out

    @property
    def log_partition(self) -> float:
        p0 = self.solver.model.initial_distribution().to(self.values.device)
        v0 = self.values[0].double() + float(self.baseline[0])
        if self.backup == "trajectory":
            tau = self.temperature
            return tau * float(torch.logsumexp(torch.log(p0.reshape(-1)) + v0.reshape(-1) / tau,
                                               0))
        # (states outside P0's support may have V = -inf: 0 · -inf would be NaN)
        return float((p0 * torch.where(p0 > 0, v0, 0.0)).sum())

    def feature_expectation(self, features) -> torch.Tensor:
        """``[l]`` discounted feature expectation ``E[Σ_t γ^t φ(S_t, A_t)]``."""
        if self.local_occupancy is None:
            raise ValueError("Run solve(..., forward=True) to get occupancies.")
        return features.expectation(self.local_occupancy.cpu(), self.state_occupancy.cpu())

    def q_values_at(self, t: int, cells: torch.Tensor) -> torch.Tensor:
        """``Q_t`` at a batch of joint states: cells ``[B, N]`` -> ``[B, A1**N]``
        (joint action index with expert 1 most significant)."""
        return self.solver.q_values_at(self, t, cells)

    def policy_at(self, t: int, cells: torch.Tensor, tie_tol: float = 1e-6) -> torch.Tensor:
        """``π_t(·|s)`` ``[B, A1**N]`` at joint states ``cells`` ``[B, N]``. With
        temperature 0 the policy is uniform over the maximising joint actions.

        At a state where every action is forbidden (``Q_t = -inf`` throughout: the model
        holds it unreachable) the policy is uniform, not NaN: a trajectory-backup (ME)
        policy plans with optimistic dynamics and can reach such states under the real
        ones, e.g. in ``dicrl_torch.metrics.rollout_true_cmg``."""
        q = self.q_values_at(t, cells).double()
        dead = ~torch.isfinite(q).any(1, keepdim=True)  # [B, 1]
        if dead.any():
            q = torch.where(dead, 0.0, q)
        if self.temperature == 0.0:
            best = q.amax(1, keepdim=True)
            tie = (q >= best - tie_tol * best.abs().clamp_min(1.0)) & torch.isfinite(q)
            return tie.double() / tie.sum(1, keepdim=True)
        return torch.softmax(q / self.temperature, 1)

    def policy_dense(self, t: int) -> torch.Tensor:
        """``[S, A]`` policy at step ``t`` (tiny instances only)."""
        m = self.solver.model
        if m.n_pairs > 5_000_000:
            raise ValueError(f"policy_dense on {m.n_pairs:,} pairs; use policy_at on a batch.")
        cells = torch.cartesian_prod(*[torch.arange(m.n_cells)] * m.n_experts).reshape(
            -1, m.n_experts)
        return self.policy_at(t, cells)
