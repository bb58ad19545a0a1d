"""The local gradient approximation against finite differences of the local
log-likelihood, and the dual gradient against its definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dicrl_torch.algos.icrl import (
    LocalStatistics,
    dual_gradient,
    local_gradient,
    log_likelihood,
    model_reward,
)
from dicrl_torch.algos.models import LearnerModel, TabularLearnerModel, TabularSolution
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.solvers.experts import sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman


@pytest.mark.parametrize("cost_basis", [SharedIndicatorCostBasis, PerExpertIndicatorCostBasis])
@pytest.mark.parametrize("lam", [-3.0, 2.0])
def test_lga_matches_finite_difference_of_local_log_likelihood(cost_basis, lam):
    # Deterministic dynamics: the LGA is then the exact partial gradient at fixed η.
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=4, gamma=0.9,
                             p_success=1.0)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    fr, fc = GoalClosenessRewardBasis(model)(), cost_basis(model)()
    g = torch.Generator().manual_seed(0)
    w_r = torch.randn(fr.dim, generator=g, dtype=torch.float64)
    w_c = torch.rand(fc.dim, generator=g, dtype=torch.float64)
    demo_policy = solver.solve(model_reward(fr, fc, w_r, -1.0, torch.rand(
        fc.dim, generator=g, dtype=torch.float64)), forward=False)
    demos = sample_trajectories(demo_policy, 25, np.random.default_rng(0))
    stats = LocalStatistics.from_demonstrations(demos, fr, fc, model.gamma)

    def F(wc):
        return log_likelihood(solver.solve(model_reward(fr, fc, w_r, lam, wc), forward=False),
                              demos)

    lga = local_gradient(TabularSolution(solver.solve(model_reward(fr, fc, w_r, lam, w_c)), fr, fc),
                         stats, lam)
    h = 1e-5
    fd = torch.zeros(fc.dim, dtype=torch.float64)
    for j in range(fc.dim):
        e = torch.zeros(fc.dim, dtype=torch.float64)
        e[j] = h
        fd[j] = (F(w_c + e) - F(w_c - e)) / (2 * h)
    rel = float((lga - fd).norm() / fd.norm())
    assert rel < 1e-3, rel
    # the printed LGA without λ has the wrong scale (and, for λ < 0, the wrong sign)
    no_lambda = lga / lam
    assert float((no_lambda - fd).norm() / fd.norm()) > 0.3


def test_dual_gradient_is_moment_mismatch():
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=5, gamma=0.95)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    fr, fc = GoalClosenessRewardBasis(model)(), SharedIndicatorCostBasis(model)()
    w_r = torch.tensor([1.0, 2.0, 1.0, 2.0], dtype=torch.float64)
    w_c = torch.full((fc.dim,), 0.5, dtype=torch.float64)
    sol = solver.solve(model_reward(fr, fc, w_r, -1.0, w_c))
    # demonstrations from the same policy: the gradient is sampling noise only
    demos = sample_trajectories(sol, 3000, np.random.default_rng(1))
    stats = LocalStatistics.from_demonstrations(demos, fr, fc, model.gamma)
    grad = dual_gradient(TabularSolution(sol, fr, fc), stats, w_c)
    assert grad.shape == (fr.dim + 1,)
    assert grad.abs().max() < 0.1
    # a shifted reward weight moves the reward-moment part with the right sign
    sol_hi = solver.solve(model_reward(fr, fc, w_r * 2, -1.0, w_c))
    grad_hi = dual_gradient(TabularSolution(sol_hi, fr, fc), stats, w_c)
    assert grad_hi[: fr.dim].sum() > grad[: fr.dim].sum()


def test_tabular_learner_model_is_stateless_and_shares_its_solver():
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=4, gamma=0.9)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    lm = TabularLearnerModel(solver=solver, reward_basis=GoalClosenessRewardBasis(model),
                             cost_basis=SharedIndicatorCostBasis(model))
    assert isinstance(lm, LearnerModel) and lm.stateful is False
    # every learner solves with the one exact solver
    assert lm.inner_solver(0) is solver and lm.inner_solver(3) is solver
    assert lm.state_dict() == {}
    lm.load_state_dict({})
    with pytest.raises(ValueError, match="no state"):
        lm.load_state_dict({"solvers": []})
    eta = torch.tensor([1.0, 2.0, 1.0, 2.0, -1.0], dtype=torch.float64)
    sol = lm.solve(0, eta, torch.full((lm.cost_dim,), 0.5, dtype=torch.float64))
    # the policy without unwrapping the soft-Bellman solution
    cells = torch.tensor([model.start_state])
    assert sol.policy_at == sol.soft_bellman.policy_at
    torch.testing.assert_close(sol.policy_at(0, cells), sol.soft_bellman.policy_at(0, cells),
                               rtol=0, atol=0)
