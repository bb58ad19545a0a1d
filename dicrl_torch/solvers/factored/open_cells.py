"""Hard-max solves on the cells a constraint set leaves open.

Where hard constraints forbid a cell outright for every expert (every pair there is
``-inf``, and so is the terminal value), ``V_t = -inf`` at every joint state with an
expert in it, at every step: those states carry no information and need not be
computed. The identifiability classification and the learners' certificate
(:mod:`dicrl_torch.algos.identifiability`) forbid every undemonstrated feature but one,
which closes about half of the grid's cells, and a solve on the ``K`` open cells costs
``(K / S1)^N`` of the full one: the saving grows with the number of experts.

The open cells keep their moves; a move into a closed cell leads to one extra *closed*
cell, forbidden at every step and absorbing, so ``-inf`` reaches the values exactly as
the closed cells' ``-inf`` does in the full model. The hard step is elementwise
arithmetic and maxima, and the per-step centre is taken over the same finite values, so
the values (and the hard-max policy) at open states are the full solve's bit for bit on
the eager path (``tests/test_open_cells.py``).
"""

from __future__ import annotations

import math

import torch

from dicrl_torch.envs.grid import TabularGridModel
from dicrl_torch.features.bases import FactoredReward
from dicrl_torch.solvers.factored.solution import SoftBellmanSolution
from dicrl_torch.solvers.factored.solver import COMPILE_MIN_PAIRS, FactoredSoftBellman

__all__ = ["OpenCellsModel", "OpenCellsSolution", "closed_cells", "solve_hard"]


def closed_cells(reward: FactoredReward, terminal: torch.Tensor | None) -> torch.Tensor:
    """``[S1]`` bool: the cells where every expert is forbidden at every step, i.e. every
    action of every expert there is ``-inf`` and so is the terminal value of every joint
    state with an expert there. None closed without a ``-inf`` terminal value (the last
    move may then enter any cell).

    Args:
        reward: ``local [N, S1, A1]`` (``-inf``: forbidden), ``joint`` ignored.
        terminal: ``[S1]*N`` ``V_T`` or None (0).
    """
    local = reward.local
    N, S1 = local.shape[0], local.shape[1]
    if terminal is None:
        return torch.zeros(S1, dtype=torch.bool)
    closed = torch.isneginf(local).all(-1).all(0).cpu()  # [S1]
    terminal = terminal.cpu()
    for i in range(N):
        top = terminal.movedim(i, 0).reshape(S1, -1).amax(1)
        closed &= torch.isneginf(top)
    return closed


class OpenCellsModel(TabularGridModel):
    """``model``'s dynamics on its open cells plus one closed, absorbing cell (index
    ``n_cells - 1``) that every move into a closed cell leads to.

    Sizes, :attr:`state_shape` and :meth:`expert_transition` are the parent's, on the
    ``K + 1`` cells; it has no layout, so start states and P0 are the full model's
    business.

    Attributes:
        base: the full model.
        cells: ``[K]`` int64, the open cells (ascending), full indexing.
        index: ``[S1]`` int64, full cell -> open index (``K`` for a closed cell).
    """

    def __init__(self, model: TabularGridModel, open_cells: torch.Tensor) -> None:
        # The parent's constructor builds from a layout; this model is derived instead.
        self.base = model
        self.layout = None
        self.horizon, self.gamma, self.p_success = model.horizon, model.gamma, model.p_success
        self.n_experts, self.n_actions = model.n_experts, model.n_actions
        self.cells = torch.nonzero(open_cells.cpu()).flatten()
        K = len(self.cells)
        self.n_cells = K + 1
        self.index = torch.full((model.n_cells,), K, dtype=torch.int64)
        self.index[self.cells] = torch.arange(K)
        nxt = self.index[model.next_cell[self.cells]]  # [K, A1]
        self.next_cell = torch.cat([nxt, torch.full((1, model.n_actions), K)])

    def restrict(self, x: torch.Tensor, closed_value: float) -> torch.Tensor:
        """``[S1]*N`` -> ``[K+1]*N``: ``x`` at the open joint states, ``closed_value``
        wherever an expert is in the closed cell."""
        N, K = self.n_experts, self.n_cells - 1
        pick = torch.cat([self.cells, self.cells[:1]]).to(x.device)
        for axis in range(N):
            x = x.index_select(axis, pick)
        for axis in range(N):
            x.narrow(axis, K, 1).fill_(closed_value)
        return x

    def restrict_reward(self, reward: FactoredReward) -> FactoredReward:
        """The reward on the open cells; every action in the closed cell is ``-inf``."""
        local = reward.local[:, self.cells.to(reward.local.device)]
        closed = torch.full_like(local[:, :1], -math.inf)
        joint = None
        if reward.joint is not None:
            shape = (self.base.n_cells,) * self.n_experts
            # 0 beside the closed cell: its -inf rewards already forbid those states.
            joint = self.restrict(reward.joint.reshape(shape), 0.0).reshape(-1)
        return FactoredReward(local=torch.cat([local, closed], 1), joint=joint)


class OpenCellsSolution:
    """A hard-max solution read at joint states of the full model.

    Attributes:
        solution: the solve on the open cells (or on the full model).
        solver: the full model's solver (``solver.model`` is the full model).
        index: ``[S1]`` full cell -> the solution's cell, or None (the full model's).
    """

    def __init__(self, solution: SoftBellmanSolution, solver: FactoredSoftBellman,
                 index: torch.Tensor | None) -> None:
        self.solution, self.solver = solution, solver
        self.index = None if index is None else index.to(solution.values.device)

    def _cells(self, cells: torch.Tensor) -> torch.Tensor:
        return cells if self.index is None else self.index[cells]

    def policy_at(self, t: int, cells: torch.Tensor, tie_tol: float = 1e-6) -> torch.Tensor:
        """``π_t(·|s)`` ``[B, A1**N]`` at joint states ``cells`` ``[B, N]`` (full
        indexing; uniform over the maximising joint actions)."""
        return self.solution.policy_at(t, self._cells(cells), tie_tol)

    def start_values(self, cells: torch.Tensor) -> torch.Tensor:
        """``[B]`` ``V_0`` at joint states ``cells`` ``[B, N]`` (``-inf`` where closed)."""
        idx = self._cells(cells.to(self.solution.values.device))
        return self.solution.values[0][tuple(idx.t())].double() + float(
            self.solution.baseline[0])


def solve_hard(solver: FactoredSoftBellman, reward: FactoredReward,
               terminal: torch.Tensor | None, open_cells: bool = True) -> OpenCellsSolution:
    """The hard-max (temperature 0) backward solve of ``reward`` with ``V_T = terminal``,
    on the open cells where :func:`closed_cells` closes any, else (or with ``open_cells``
    False: the reference the benchmark and tests compare with) on the full model.

    The open-cell solver compiles its kernels where ``solver`` does and the open model
    is large enough to pay for it (:data:`~.solver.COMPILE_MIN_PAIRS`); one compilation
    per number of open cells, and a classification sees two or three. Eager, its chunks
    of expert-1 cells hold no more pairs than the full solver's (no more memory).
    """
    closed = closed_cells(reward, terminal) if open_cells else None
    if closed is None or not closed.any() or closed.all():
        sol = solver.solve(reward, temperature=0.0, forward=False, terminal_value=terminal)
        return OpenCellsSolution(sol, solver, None)
    model = solver.model
    small = OpenCellsModel(model, ~closed)
    N, A1 = model.n_experts, model.n_actions
    budget = max(solver.chunk_cells * A1 ** N * model.n_cells ** (N - 1), 1 << 18)
    chunk = max(1, min(small.n_cells, budget // (A1 ** N * small.n_cells ** (N - 1))))
    compile = solver.use_compile and small.n_pairs >= COMPILE_MIN_PAIRS
    twin = FactoredSoftBellman(model=small, device=solver.device, dtype=solver.dtype,
                               compile=compile, chunk_cells=chunk)
    term = small.restrict(terminal.to(solver.device), -math.inf)
    sol = twin.solve(small.restrict_reward(reward), temperature=0.0, forward=False,
                     terminal_value=term)
    return OpenCellsSolution(sol, solver, small.index)
