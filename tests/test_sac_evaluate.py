"""Evaluation rollouts through the game's batched env give the numbers of the joint envs
stepped one by one (solvers/sac/episodes.py)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from dicrl_torch.envs.drones import DroneDynamics, JointDroneEnv
from dicrl_torch.features.continuous import PositionCellBasis, RandomFourierBasis
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.runs.mpe import spread_joint_env
from dicrl_torch.solvers.sac import SACConstrainedSolver


def drone_solver(batched: bool) -> SACConstrainedSolver:
    return SACConstrainedSolver(
        env_factory=functools.partial(JointDroneEnv, max_steps=60,
                                      dynamics=DroneDynamics(max_speed=2.0)),
        reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(), seed=3,
        n_envs=2, learning_starts=50, batch_size=32, batched_env=batched)


def spread_solver(batched: bool) -> SACConstrainedSolver:
    return SACConstrainedSolver(
        env_factory=functools.partial(spread_joint_env, max_steps=20),
        reward_basis=RandomFourierBasis(n_agents=2, state_dim=4, n_features=8, seed=0),
        cost_basis=PositionCellBasis(n_agents=2, bounds=((-1.5, 1.5), (-1.5, 1.5)),
                                     proximity_radius=0.4, n_per_axis=3),
        seed=3, n_envs=2, learning_starts=50, batch_size=32, batched_env=batched)


@pytest.mark.parametrize("make", [drone_solver, spread_solver], ids=["drones", "spread"])
def test_batched_evaluation_equals_the_joint_envs(make):
    solvers = [make(batched) for batched in (True, False)]
    assert solvers[0]._eval_envs == {} and solvers[1]._eval_envs == {}
    results = []
    for solver in solvers:
        solver.set_weights(np.ones(solver.l_r + 1), np.zeros(solver.l_c))
        solver.engine.learn(100)  # a policy that is not the initial one
        results.append([solver.evaluate(5, trajectories=True),
                        solver.evaluate(3, true_game=True, deterministic=True,
                                        trajectories=True),
                        solver.evaluate(4, true_game=True, actor=functools.partial(
                            into, MIDDLE[make.__name__]))])
    assert solvers[0]._eval_envs[(False, 5)].vector is not None  # the batched path ran
    assert solvers[1]._eval_envs[(False, 5)].vector is None
    for a, b in zip(*results, strict=True):
        for name in ("reward_sums", "cost_sums", "lengths", "reached", "violated"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        if a.paths is not None:
            assert all(np.array_equal(p, q) for p, q in zip(a.paths, b.paths, strict=True))
    # Episodes ended at different steps: the ended ones were stepped on unread.
    assert len(set(results[0][2].lengths.tolist())) > 1


MIDDLE = {"drone_solver": (5.0, 5.5), "spread_solver": (0.0, 0.0)}
"""The drones' block and the spread's disc: constraints of each true game."""


def into(centre: tuple[float, float], states: np.ndarray, flying: np.ndarray,
         episodes: np.ndarray) -> np.ndarray:
    """Every agent towards ``centre``, at a speed that grows with the episode's index, so
    that the episodes end apart (an agent freezes there in the true game)."""
    heading = np.asarray(centre) - states[..., :2]  # [b, N, 2]
    heading /= np.linalg.norm(heading, axis=-1, keepdims=True) + 1e-9
    speed = (0.3 + 0.2 * np.asarray(episodes))[:, None, None]
    return (speed * heading).reshape(len(states), -1)
