"""Expert policies and trajectory sampling (docs/design.md §3).

The experts follow the optimal policy of the *true* CMG: the hard-max DP of the
factored solver with every constrained pair masked (``-inf`` reward), ties broken
uniformly; an optional temperature makes them soft-optimal. The *nominal* experts
solve the same game without the mask. Each learner's local estimates from the sampled
trajectories are :mod:`dicrl_torch.demos.features`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import GridLayout, TabularGridModel, decode_joint, encode_joint
from dicrl_torch.features.bases import FactoredFeatures, FactoredReward, _collision_table
from dicrl_torch.solvers.factored import FactoredSoftBellman, SoftBellmanSolution


def hard_constraint_reward(model: TabularGridModel, layout: GridLayout) -> FactoredReward:
    """``-inf`` on every pair that violates ``layout``'s true constraints, 0 elsewhere:
    obstacle cells and forbidden actions (per expert), and collisions (joint)."""
    N, S1, A1 = model.n_experts, model.n_cells, model.n_actions
    local = torch.zeros(N, S1, A1, dtype=torch.float64)
    local[:, torch.from_numpy(layout.obstacle_mask()), :] = -math.inf
    local[:, :, torch.from_numpy(layout.forbidden_action_mask())] = -math.inf
    joint = None
    if layout.collision_constraint and N > 1:
        joint = torch.where(_collision_table(model) > 0, -math.inf, 0.0).to(torch.float64)
    return FactoredReward(local=local, joint=joint)


def forbidden_state_value(model: TabularGridModel, layout: GridLayout) -> torch.Tensor:
    """``[S1]*N`` terminal value: ``-inf`` where an expert stands on an obstacle or
    two experts share a cell, 0 elsewhere (see ``FactoredSoftBellman.solve``)."""
    N, S1 = model.n_experts, model.n_cells
    bad = torch.zeros(model.state_shape, dtype=torch.bool)
    obstacle = torch.from_numpy(layout.obstacle_mask())
    for i in range(N):
        shape = [1] * N
        shape[i] = S1
        bad |= obstacle.reshape(shape)
    if layout.collision_constraint and N > 1:
        bad |= (_collision_table(model) > 0).reshape(model.state_shape)
    return torch.where(bad, -math.inf, 0.0).to(torch.float64)


def expert_solution(*, solver: FactoredSoftBellman, reward_features: FactoredFeatures,
                    reward_weights: torch.Tensor, layout: GridLayout | None = None,
                    constrained: bool = True, temperature: float = 0.0
                    ) -> SoftBellmanSolution:
    """Solve for the experts' policy.

    Args:
        solver: the factored solver of the game.
        reward_features: reward basis output; ``reward_weights`` ``[l_r]`` its ``ω_rE``.
        layout: the true constraints (defaults to the solver model's layout).
        constrained: mask the true constraints (True CMG) or not (nominal game).
        temperature: 0 for optimal experts (uniform over ties), > 0 soft-optimal.
    """
    reward = reward_features.weighted(reward_weights)
    terminal = None
    if constrained:
        layout = layout or solver.model.layout
        reward = reward + hard_constraint_reward(solver.model, layout)
        terminal = forbidden_state_value(solver.model, layout)
    sol = solver.solve(reward, temperature=temperature, forward=False,
                       terminal_value=terminal)
    # Every start state P0 gives mass to must be safe, not only the nominal one: a
    # trajectory drawn from a doomed start would violate a true constraint.
    m = solver.model
    support = m.start_support()  # [K, N]
    v0 = sol.V[0].reshape(-1)[encode_joint(support, m.n_cells).to(sol.V.device)]
    doomed = torch.nonzero(~torch.isfinite(v0.double().cpu())).flatten()
    if doomed.numel():
        cells = [m.layout.xy(int(c)) for c in support[int(doomed[0])]]
        what = ("the start state" if support.shape[0] == 1 else
                f"{doomed.numel()} of the {support.shape[0]} start states P0 gives mass to, "
                f"e.g.")
        raise ValueError(f"The experts cannot avoid violating a constraint from {what} "
                         f"{cells} in this layout/horizon; change the layout (its starts or "
                         f"start sets) or the horizon.")
    return sol


def _to_torch_generator(rng: np.random.Generator | torch.Generator | int) -> torch.Generator:
    if isinstance(rng, torch.Generator):
        return rng
    if isinstance(rng, np.random.Generator):
        return torch.Generator().manual_seed(int(rng.integers(2**62)))
    if isinstance(rng, int):
        return torch.Generator().manual_seed(rng)
    raise TypeError(f"rng must be a np.random.Generator, torch.Generator or int seed; "
                    f"got {type(rng).__name__}.")


def sample_trajectories(solution: SoftBellmanSolution, n: int,
                        rng: np.random.Generator | torch.Generator | int) -> Demonstrations:
    """Sample ``n`` trajectories of the solution's policy in the learner's model (the
    nominal dynamics; an expert that never violates never freezes, so this equals the
    true CMG for constrained experts), each from a start drawn from the model's P0
    (:meth:`~dicrl_torch.envs.grid.TabularGridModel.sample_starts`) with ``rng``.

    Returns:
        :class:`Demonstrations` with states ``[n, T+1, N]`` and actions ``[n, T, N]``.
    """
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}.")
    g = _to_torch_generator(rng)
    m = solution.solver.model
    N, A1, T = m.n_experts, m.n_actions, m.horizon
    nxt = m.next_cell
    # each trajectory's start drawn from P0 (no draw with fixed starts)
    cells = m.sample_starts(n, g)
    states = torch.empty(n, T + 1, N, dtype=torch.int64)
    actions = torch.empty(n, T, N, dtype=torch.int64)
    states[:, 0] = cells
    for t in range(T):
        pi = solution.policy_at(t, cells).cpu()  # [n, A1^N]
        joint = torch.multinomial(pi, 1, generator=g).squeeze(1)
        a = decode_joint(joint, A1, N)  # joint action -> per expert
        move = torch.rand(n, N, generator=g, dtype=torch.float64) < m.p_success
        cells = torch.where(move, nxt[cells, a], cells)
        actions[:, t], states[:, t + 1] = a, cells
    return Demonstrations(states=states.numpy(), actions=actions.numpy(), n_cells=m.n_cells,
                          n_actions=A1)
