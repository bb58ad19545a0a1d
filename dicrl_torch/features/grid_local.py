"""The deep cost basis of the grid world: local ReLU units over positions, moves and
separations (docs/design.md §6.2).

The grid's indicator bases are hand-made: one feature per cell, per action and for the
collision. :class:`GridLocalReLUBasis` builds its features the way the continuous games'
deep basis does (:class:`~dicrl_torch.features.local.LocalReLUBasis`, the same frozen
network), from nothing but the grid's size and the number of experts:

- **position units** read an expert's cell as a point ``(x, y)`` of the square
  ``[0, G-1]²``: ``ReLU(1 - ν(x - c_k) / ρ)``, exactly 0 outside a polygon round a centre
  ``c_k`` drawn by farthest-point sampling, at one or more scales; a unit's support is
  the set of cells inside its polygon (one cell, or a block of them);
- **move units** read an action as its displacement ``(dx, dy)`` in ``[-1, 1]²``, the same
  units over that square: an action constraint is a region of moves;
- **separation rings** read each pair of experts' separation ``ν(x_i - x_j)``: the ring at
  0 is two experts in one cell.

Units whose support holds no cell (no move, no separation the lattice has) are dropped:
they are the zero feature. Nothing is read from the layout's obstacles, forbidden actions
or collision rule (tests/test_grid_local.py moves them and compares the state_dict).

What it can express: a cell, a move or a separation inside the support of a unit that no
demonstration and no start state makes positive; a unit straddling an obstacle and a
demonstrated cell cannot become a constraint, so the obstacles next to the experts'
routes are expressible only through the fine units that hold them alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from dicrl_torch.checks import check_int, check_positive
from dicrl_torch.envs.grid import ACTIONS, TabularGridModel
from dicrl_torch.features.bases import FactoredFeatures, FeatureBasis
from dicrl_torch.features.local import LocalReLUBasis

__all__ = ["GridLocalReLUBasis"]


def _support_any(values: torch.Tensor) -> torch.Tensor:
    """``[l]`` bool: the columns of ``values`` ``[..., l]`` positive somewhere."""
    return (values > 0).flatten(0, -2).any(0)


class GridLocalReLUBasis(FeatureBasis):
    """Local ReLU units over the grid (module docstring), shared by the experts (a unit
    counts the experts in its support): ``l = K' + M' + R'``, the position, move and
    ring units left after dropping empty ones, named ``local{k}``, ``move{k}``,
    ``ring{r}`` by their index before the drop.

    Args:
        model: the tabular model (its grid size, number of experts and actions).
        density: position units per cell at the finest scale (``K = density · G²``):
            at 2 a unit's support holds one cell or two.
        scales: unit sizes, as multiples of the finest (``LocalReLUBasis``' ``scales``):
            coarser units cover blocks of cells no expert enters, and the certificate
            may need one where the data say a route must be closed but not where, so
            it forbids free cells with the obstacle (docs/gridworld.md).
        move_centres: move units over ``[-1, 1]²``.
        n_rings: separation units (0: none; one expert has none anyway).
        directions: the polygonal norm's ``M`` directions.
        overlap: support radius over the centres' covering radius (>= 1).
        seed: the draw of centres and directions.
    """

    def __init__(self, model: TabularGridModel, *, density: float = 2.0,
                 scales: Sequence[int] = (1,), move_centres: int = 9, n_rings: int = 12,
                 directions: int = 6, overlap: float = 1.0, seed: int = 0) -> None:
        super().__init__(model)
        G, N = model.layout.size, model.n_experts
        self.density = check_positive("density", density)
        k = max(1, round(self.density * G * G))
        n_rings = check_int("n_rings", n_rings, 0) if N > 1 else 0
        common = dict(directions=directions, overlap=overlap, seed=seed, state_dim=2)
        self.positions = LocalReLUBasis(n_agents=N, bounds=((0, G - 1),) * 2, n_centres=k,
                                        scales=scales, n_rings=n_rings,
                                        ring_range=(G - 1) / 2, **common)
        self.moves = LocalReLUBasis(n_agents=1, bounds=((-1, 1),) * 2,
                                    n_centres=check_int("move_centres", move_centres),
                                    n_rings=0, **common)
        xy = torch.tensor([model.layout.xy(c) for c in range(model.n_cells)],
                          dtype=torch.float64)  # [S1, 2]
        moves = torch.tensor([(dx, dy) for _, dx, dy in ACTIONS], dtype=torch.float64)
        if len(moves) != model.n_actions:
            raise ValueError(f"GridLocalReLUBasis reads the grid's {len(ACTIONS)} moves, but "
                             f"the model has {model.n_actions} actions.")
        K = self.positions.n_centres
        cell_units = self.positions.compute(xy[:, None])[:, :K]  # [S1, K]: one expert per cell
        move_units = self.moves.compute(moves[:, None])  # [A1, M]
        ring_units = torch.zeros(0, 0, 0, dtype=torch.float64)
        if self.positions.n_rings:
            pairs = torch.stack(torch.broadcast_tensors(xy[:, None], xy[None, :]), 2)
            ring_units = self.positions.compute(pairs)[..., K:]  # [S1, S1, R]: two experts
        keep = [_support_any(cell_units), _support_any(move_units),
                _support_any(ring_units) if ring_units.numel() else torch.zeros(0, dtype=bool)]
        self.register_buffer("cell_units", cell_units[:, keep[0]])
        self.register_buffer("move_units", move_units[:, keep[1]])
        self.register_buffer("ring_units", ring_units[..., keep[2]] if ring_units.numel()
                             else torch.zeros(model.n_cells, model.n_cells, 0,
                                              dtype=torch.float64))
        index = [torch.nonzero(m).flatten().tolist() for m in keep]
        self.names = ([f"local{k}" for k in index[0]] + [f"move{k}" for k in index[1]]
                      + [f"ring{r}" for r in index[2]])
        # A unit counts the experts in its support; a ring the pairs at its separation.
        self.max_value = float(max(N, N * (N - 1) // 2))
        # Constraint maps draw a learned position unit as the cells of its support.
        self.region_cells = {name: tuple(torch.nonzero(col > 0).flatten().tolist())
                             for name, col in zip(self.names, self.cell_units.T, strict=False)}

    def build(self) -> FactoredFeatures:
        m = self.model
        N, S1, A1 = m.n_experts, m.n_cells, m.n_actions
        K, M, R = (self.cell_units.shape[1], self.move_units.shape[1],
                   self.ring_units.shape[-1])
        local = torch.zeros(N, S1, A1, self.dim, dtype=torch.float64)
        local[:, :, :, :K] = self.cell_units[None, :, None, :]
        local[:, :, :, K:K + M] = self.move_units[None, None, :, :]
        if not R:
            return FactoredFeatures(local=local)
        # joint[s] = Σ_{i<j} ring(s_i, s_j) over the experts' cells: [S1]*N -> [S, R]
        joint = torch.zeros((S1,) * N + (R,), dtype=torch.float64)
        for i in range(N):
            for j in range(i + 1, N):
                shape = [1] * N + [R]
                shape[i], shape[j] = S1, S1
                joint = joint + self.ring_units.reshape(shape)
        return FactoredFeatures(local=local, joint=joint.reshape(-1, R),
                                joint_columns=torch.arange(K + M, K + M + R))
