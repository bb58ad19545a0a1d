"""The tiny D-ICRL instance shared by the trainer and backend tests (rebuilt
identically in every process of a distributed test)."""

from __future__ import annotations

import numpy as np
import torch

from dicrl_torch.algos.dicrl import DICRL, StepSizes
from dicrl_torch.comm import CompleteSchedule, SimulatedCommunicator, TimeVaryingSchedule
from dicrl_torch.demos import partition_demonstrations
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

SPLIT = [2, 3, 5]


def build_tiny():
    """(solver, reward basis, cost basis, shards) of a 3x3 two-expert grid, T = 5."""
    layout = GridLayout(size=3, starts=((0, 2), (2, 0)), goals=((2, 2), (0, 0)),
                        obstacles=((1, 1),), forbidden_actions=("NE",))
    model = TabularGridModel(layout=layout, horizon=5, gamma=0.95)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    experts = expert_solution(solver=solver, reward_features=rb(),
                              reward_weights=rb.true_weights())
    demos = sample_trajectories(experts, sum(SPLIT), np.random.default_rng(0))
    return solver, rb, cb, partition_demonstrations(demos, SPLIT)


def make_trainer(tiny, *, shards=None, communicator=None, init_cost=None, inner=None,
                 **kw) -> DICRL:
    """A trainer over ``tiny``; defaults: all shards in-process, distinct initial ω_c."""
    solver, rb, cb, all_shards = tiny
    n = len(SPLIT)
    if init_cost is None:
        init_cost = torch.linspace(0.2, 0.4, n, dtype=torch.float64).unsqueeze(1).expand(
            n, cb.dim).clone()
    settings = dict(steps=StepSizes(alpha_bar=0.02), inner_steps=3, lsca_curvature=10.0)
    model = {} if "learner_model" in kw else dict(solver=solver, reward_basis=rb, cost_basis=cb)
    return DICRL(**model,
                 shards=all_shards if shards is None else shards,
                 trajectory_counts=SPLIT,
                 communicator=communicator or SimulatedCommunicator(n),
                 inner_schedule=inner or TimeVaryingSchedule(n_learners=n, period=2),
                 outer_schedule=CompleteSchedule(n_learners=n),
                 init_cost_weights=init_cost, **(settings | kw))
