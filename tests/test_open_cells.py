"""Hard-max solves on the open cells (``dicrl_torch.solvers.factored.open_cells``) against
the full model's solve: the same values and policies at every open state, bit for bit on
the eager path, and the same identifiability classes and probabilities."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import dicrl_torch.algos.identifiability as identifiability
from dicrl_torch.algos.accrual import AllButOne, Positive
from dicrl_torch.algos.greedy import cost_features_of
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    FactoredReward,
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman
from dicrl_torch.solvers.factored.open_cells import (
    OpenCellsModel,
    closed_cells,
    solve_hard,
)


def masked_problem(n_experts: int, size: int, dtype, seed: int, basis=SharedIndicatorCostBasis):
    """A random reward with every feature of a random half of the basis forbidden (as the
    classification forbids ``U \\ {j}``), collision included where drawn."""
    gen = torch.Generator().manual_seed(seed)
    starts = ((0, 0), (size - 1, 0), (0, size - 1))[:n_experts]
    goals = ((size - 1, size - 1), (0, size - 1), (size - 1, 0))[:n_experts]
    model = TabularGridModel(layout=GridLayout(size=size, starts=starts, goals=goals),
                             horizon=6, gamma=0.95, p_success=0.8)
    solver = FactoredSoftBellman(model=model, dtype=dtype, compile=False)
    reward = FactoredReward(local=torch.randn(model.n_experts, model.n_cells,
                                              model.n_actions, generator=gen,
                                              dtype=torch.float64))
    features, _ = cost_features_of(basis(model), model)
    unseen = torch.rand(features.dim, generator=gen) < 0.5
    start_cells = set(model.start_state)
    pos = Positive(features)
    for j in range(features.dim):  # P0's cells are never forbidden (they are demonstrated)
        if pos.state[j] and any(bool(pos.cell[i, c, j]) for i in range(n_experts)
                                for c in start_cells):
            unseen[j] = False
    j = int(torch.nonzero(unseen)[0])
    mask, terminal = AllButOne(features, unseen, pos, model)(j)
    return model, solver, reward + mask, terminal


@pytest.mark.parametrize("n_experts,size,seed,basis", [
    (1, 4, 0, SharedIndicatorCostBasis), (2, 3, 1, SharedIndicatorCostBasis),
    (2, 4, 2, SharedIndicatorCostBasis), (2, 4, 4, PerExpertIndicatorCostBasis),
    (3, 3, 3, SharedIndicatorCostBasis)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_open_cells_give_the_full_values_and_policy(n_experts, size, seed, basis, dtype):
    model, solver, reward, terminal = masked_problem(n_experts, size, dtype, seed, basis)
    closed = closed_cells(reward, terminal)
    assert closed.any() and not closed.all()
    full = solver.solve(reward, temperature=0.0, forward=False, terminal_value=terminal)
    open_ = solve_hard(solver, reward, terminal)
    assert open_.index is not None
    small = open_.solution.solver.model
    assert isinstance(small, OpenCellsModel) and small.n_cells == int((~closed).sum()) + 1
    # Every joint state with an expert in a closed cell is -inf in the full solve.
    cells = torch.cartesian_prod(*[torch.arange(model.n_cells)] * n_experts).reshape(
        -1, n_experts)
    at_closed = closed[cells].any(1)
    flat_v = full.values.reshape(full.values.shape[0], -1)
    assert torch.isneginf(flat_v[:, at_closed]).all()
    # The open states: the same values (about the same baseline) and policies, bitwise.
    open_cells = cells[~at_closed]
    idx = small.index[open_cells]
    assert torch.equal(open_.solution.baseline, full.baseline)
    for t in range(model.horizon + 1):
        assert torch.equal(open_.solution.values[t][tuple(idx.t())],
                           full.values[t][tuple(open_cells.t())])
    for t in range(model.horizon):
        assert torch.equal(open_.policy_at(t, open_cells), full.policy_at(t, open_cells))
    assert torch.equal(open_.start_values(open_cells),
                       flat_v[0][~at_closed].double() + float(full.baseline[0]))


def test_a_cell_one_expert_may_enter_stays_open():
    model, _, reward, terminal = masked_problem(2, 3, torch.float64, 1,
                                                basis=PerExpertIndicatorCostBasis)
    local = reward.local.clone()
    closed = closed_cells(FactoredReward(local=local), terminal)
    c = int(torch.nonzero(closed)[0])
    local[1, c] = 0.0  # expert 2 may now be there
    assert not closed_cells(FactoredReward(local=local), terminal)[c]
    assert not closed_cells(reward, None).any()  # no terminal -inf: the last move enters


def test_nothing_closed_solves_the_full_model():
    model, solver, reward, _ = masked_problem(2, 3, torch.float64, 1)
    sol = solve_hard(solver, reward, None)
    assert sol.index is None and sol.solution.solver is solver


def full_only(solver, reward, terminal):
    return solve_hard(solver, reward, terminal, open_cells=False)


def test_the_certificate_is_the_full_models(monkeypatch):
    """Every candidate's probability, certified or not, equals the full model's."""
    model = TabularGridModel(layout=GridLayout.scobee(n_experts=2), horizon=20, gamma=0.99)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    reward = rb().weighted(rb.true_weights())
    experts = expert_solution(solver=solver, reward_features=rb(),
                              reward_weights=rb.true_weights(), temperature=0.0)
    demos = sample_trajectories(experts, 8, np.random.default_rng(0))

    def certify():
        return identifiability.certify_constraints(solver=solver, reward=reward,
                                                   cost_basis=cb, demonstrations=demos)

    fast = certify()
    monkeypatch.setattr(identifiability, "solve_hard", full_only)
    slow = certify()
    assert fast.n_solves == slow.n_solves > 10
    assert torch.equal(fast.required, slow.required) and fast.required.any()
    assert torch.equal(torch.nan_to_num(fast.probability, nan=-1.0),
                       torch.nan_to_num(slow.probability, nan=-1.0))
    assert torch.equal(fast.infeasible, slow.infeasible)
    assert math.isfinite(float(fast.probability[fast.required].min()))
