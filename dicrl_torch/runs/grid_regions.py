"""Region scores and expressivity of the grid world: :class:`GridRegionScoring`, a mixin
of :class:`~dicrl_torch.runs.grid.GridTask` (docs/design.md §6.1, "Regions").

The grid's truth is a function of the joint state (an expert on an obstacle, two in one
cell) and of the move (a forbidden action), whatever the cost basis. Every learned set is
scored against it, exactly, over all ``S = S1^N`` joint states (no sampling):

- a joint state is *predicted forbidden* when the learned cost on the learned set is
  positive there for every joint action (budget 0: ``C_j = {φ_j > 0}``), i.e.
  ``min_a Σ_{j∈L} φ_j(s, a) > 0``, computed in factored form;
- a cell is predicted forbidden for expert ``i`` when every joint state with expert ``i``
  there is (the rule the obstacle scores use: an expert standing there accrues learned
  cost whatever it and the others do); a move when every expert taking it anywhere
  accrues learned cost (action constraints, scored apart);
- a free joint state is *undetermined* when an expert stands farther than one
  demonstrated move from every cell the demonstrations enter, or two experts are closer
  (Chebyshev) than the demonstrations ever bring them: the band comes from the
  demonstrations, never from the truth.

The obstacle scores count (expert, cell) pairs: recall over the obstacles, over the
*required* ones (those the demonstrations make required, classified with the shared cell
basis and the true reward: evaluation only), and FPR over the free cells, counting the
undetermined ones (farther than a demonstrated move from every cell the demonstrations
enter) or setting them apart.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.identifiability import classify_features, demonstrated_mask
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    FactoredFeatures,
    SharedIndicatorCostBasis,
    _collision_table,
)
from dicrl_torch.region import region_scores

__all__ = ["POOLED_SCORES", "GridRegionScoring", "grid_forbidden", "grid_undetermined",
           "predicted_cost_floor"]

POOLED_SCORES = ("region_precision_determined", "region_undetermined",
                 "obstacle_FPR_determined")
"""The scores that set undetermined states apart: the band comes from every
demonstration, so a process without them (torchrun on private files) reports them null."""


def _joint_grid(tables: list[torch.Tensor], n_cells: int) -> torch.Tensor:
    """``[S1]*N``: the sum of per-expert tables ``[S1]``, expert 1 most significant."""
    n = len(tables)
    out = torch.zeros((n_cells,) * n, dtype=torch.float64)
    for i, t in enumerate(tables):
        shape = [1] * n
        shape[i] = n_cells
        out = out + t.reshape(shape)
    return out


def predicted_cost_floor(features: FactoredFeatures, learned: Any, n_cells: int
                         ) -> torch.Tensor:
    """``[S1]*N`` the least learned cost over joint actions at each joint state,
    ``min_a Σ_{j∈L} φ_j(s, a) = Σ_i min_{a_i} c_i(s_i, a_i) + c_joint(s)`` with the
    learned set ``L`` ``[l]`` bool (weight 1 on each: only positivity matters)."""
    w = torch.as_tensor(np.asarray(learned, dtype=np.float64))
    cost = features.weighted(w)
    floor = _joint_grid(list(cost.local.amin(dim=2)), n_cells)
    if cost.joint is not None:
        floor = floor + cost.joint.reshape(floor.shape)
    return floor


def grid_forbidden(model: TabularGridModel) -> torch.Tensor:
    """``[S1]*N`` bool: the joint states a true constraint of ``model.layout`` forbids (an
    expert on an obstacle; two in one cell where the layout forbids collisions)."""
    layout, N = model.layout, model.n_experts
    obstacle = torch.from_numpy(layout.obstacle_mask()).to(torch.float64)
    out = _joint_grid([obstacle] * N, layout.n_cells) > 0
    if layout.collision_constraint:
        out |= (_collision_table(model) > 0).reshape(out.shape)
    return out


def _chebyshev(layout: GridLayout, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    G = layout.size
    return torch.maximum((a % G - b % G).abs(), (a // G - b // G).abs())


def grid_undetermined(layout: GridLayout, free: torch.Tensor, states: np.ndarray
                      ) -> tuple[torch.Tensor, dict]:
    """Which free joint states no demonstration speaks about (module docstring).

    Args:
        free: ``[S1]*N`` bool.
        states: the demonstrations' joint cells ``[n, T+1, N]`` int.

    Returns:
        ``[S1]*N`` bool and the band ``{"step", "min_separation"}`` (Chebyshev cells)
        with ``near`` ``[S1]`` bool, the cells within ``step`` of a demonstrated one.
    """
    S1, N = layout.n_cells, free.ndim
    cells = torch.from_numpy(np.array(states, dtype=np.int64))
    step = int(_chebyshev(layout, cells[:, 1:], cells[:, :-1]).max()) if cells.shape[1] > 1 \
        else 0
    seen = torch.zeros(S1, dtype=torch.bool)
    seen[cells.reshape(-1)] = True
    everyone = torch.arange(S1)
    near = (_chebyshev(layout, everyone[:, None], everyone[seen][None, :]) <= step).any(1)
    far = _joint_grid([(~near).to(torch.float64)] * N, S1) > 0
    separation = float("inf")
    close = torch.zeros_like(free)
    if N > 1:
        pairs = [(i, j) for i in range(N) for j in range(i + 1, N)]
        separation = min(int(_chebyshev(layout, cells[..., i], cells[..., j]).min())
                         for i, j in pairs)
        grids = torch.meshgrid(*[everyone] * N, indexing="ij")
        for i, j in pairs:
            close |= _chebyshev(layout, grids[i], grids[j]) < separation
    return free & (far | close), {"step": step, "min_separation": separation,
                                  "near": near}


class GridRegionScoring:
    """The region machinery of :class:`~dicrl_torch.runs.grid.GridTask` (a mixin: it
    uses the task's ``layout``, ``model``, ``solver``, ``cost_basis``, ``reward_basis``,
    ``evaluation``, ``demos``, ``shards``, ``expert_temperature`` and
    ``identifiability()``)."""

    def region_test(self) -> dict[str, Any]:
        """Computed once: the truth ``forbidden`` ``[S1]*N``, the ``undetermined`` free
        states and the band (None when this process does not hold every demonstration:
        a learner of a distributed run on its own file), and the cost ``features``."""
        if not hasattr(self, "_region_test"):
            forbidden = grid_forbidden(self.model)
            undetermined, band = (None, None) if self.demos is None else \
                grid_undetermined(self.layout, ~forbidden, self.demos.states)
            self._region_test = {"forbidden": forbidden, "undetermined": undetermined,
                                 "band": band, "features": self.cost_basis()}
        return self._region_test

    def required_obstacles(self) -> torch.Tensor | None:
        """``[S1]`` bool: the obstacle cells the pooled demonstrations make required,
        classified with the shared cell basis under the true reward (evaluation only;
        one solve per undemonstrated obstacle); None without every demonstration."""
        if not hasattr(self, "_required_obstacles"):
            self._required_obstacles = None
            if type(self.cost_basis) is SharedIndicatorCostBasis:
                # the evaluation's own classification asked the same question of these
                ident = self.identifiability()
                if ident is not None:
                    self._required_obstacles = ident.required[:self.model.n_cells].clone()
            elif self.demos is not None:
                basis = SharedIndicatorCostBasis(self.model)
                only = torch.zeros(basis.dim, dtype=torch.bool)
                only[:self.model.n_cells] = torch.from_numpy(self.layout.obstacle_mask())
                reward = self.reward_basis().weighted(self.evaluation.true_reward_weights)
                ident = classify_features(solver=self.solver, reward=reward,
                                          cost_basis=basis, demonstrations=self.demos,
                                          temperature=self.expert_temperature, only=only)
                self._required_obstacles = ident.required[:self.model.n_cells].clone()
        return self._required_obstacles

    def _cells(self, learned: Any) -> torch.Tensor:
        """``[N, S1]`` bool: cell ``c`` is forbidden for expert ``i`` by the learned set
        ``[l_c]`` when every joint state with ``i`` at ``c`` is."""
        return _cells_of(self._predicted(learned))

    def _predicted(self, learned: Any) -> torch.Tensor:
        """``[S1]*N`` bool: the joint states the learned set ``[l_c]`` forbids."""
        return predicted_cost_floor(self.region_test()["features"], learned,
                                    self.model.n_cells) > 0

    def region_rates(self, learned: Any) -> dict[str, float | None]:
        """The learned set ``[l_c]`` bool as a classifier of joint states
        (``region_*``, :func:`~dicrl_torch.region.region_scores`), of (expert, cell)
        pairs (``obstacle_*`` but the required ones: :meth:`required_rates`) and of moves
        (``move_*``); a score that needs every demonstration is None in a process
        without them."""
        test = self.region_test()
        feats, forbidden = test["features"], test["forbidden"]
        predicted = self._predicted(learned)
        undetermined = test["undetermined"]
        scores = region_scores(forbidden.reshape(-1).numpy(), predicted.reshape(-1).numpy(),
                               np.zeros(forbidden.numel(), dtype=bool) if undetermined is None
                               else undetermined.reshape(-1).numpy())
        out = {f"region_{k}": v for k, v in scores.items()}
        if undetermined is None:
            out.update(region_precision_determined=None, region_undetermined=None)
        cells = _cells_of(predicted)
        obstacle = torch.from_numpy(self.layout.obstacle_mask())
        w = torch.as_tensor(np.asarray(learned, dtype=np.float64))
        move_cost = feats.weighted(w).local  # [N, S1, A1]: the joint part reads no move
        moves = (move_cost > 0).all(1).all(0)  # [A1]
        truth = torch.from_numpy(self.layout.forbidden_action_mask())
        band = test["band"]
        out.update(obstacle_recall=_share(cells, obstacle),
                   obstacle_FPR=_share(cells, ~obstacle),
                   obstacle_FPR_determined=None if band is None
                   else _share(cells, ~obstacle & band["near"]),
                   move_recall=_share(moves, truth), move_FPR=_share(moves, ~truth))
        return out

    def required_rates(self, learned: Any, shard: Any = None) -> dict[str, float | None]:
        """``obstacle_recall_required`` of the learned set ``[l_c]`` bool and, given the
        learner's ``shard``, ``obstacle_recall_required_bound`` (learning every feature
        it leaves unused): the recall over :meth:`required_obstacles`, asked once per run
        by the process that annotates the rows (one solve per undemonstrated obstacle:
        minutes at 3 experts, not repeated in every learner process)."""
        required = self.required_obstacles()
        where = None if required is None else \
            required & torch.from_numpy(self.layout.obstacle_mask())
        out = {"obstacle_recall_required": None if where is None
               else _share(self._cells(learned), where)}
        if shard is not None:
            out["obstacle_recall_required_bound"] = None if where is None else _share(
                self._cells(self.usable_features(shard).numpy()), where)
        return out

    def usable_features(self, shard) -> torch.Tensor:
        """``[l_c]`` bool: the cost features a learner holding ``shard`` can learn at all:
        neither its demonstrations nor P0 make them positive (budget 0)."""
        return ~demonstrated_mask(cost_basis=self.cost_basis, model=self.model,
                                  demonstrations=shard,
                                  initial_distribution=self.model.initial_distribution())

    def recall_bound(self, shard) -> float:
        """The most of the forbidden joint states a learner holding ``shard`` can recover
        with this cost basis, before training: the region recall of learning every
        :meth:`usable_features` (an upper bound)."""
        return self.region_rates(self.usable_features(shard).numpy())["region_recall"]

    def check_expressive(self) -> None:
        """Refuse a cost basis of which no held shard can learn any feature (every one
        positive on its demonstrations or at a start state: e.g. a network ending in a
        sigmoid, positive everywhere), naming the fix, before training."""
        held = [s for s in self.shards if s is not None]
        if held and not any(bool(self.usable_features(s).any()) for s in held):
            basis = self.cost_basis
            raise ValueError(
                f"The cost basis {type(basis).__name__} can express no constraint: every "
                f"one of its {basis.dim} features is positive on every learner's "
                f"demonstrations or at a start state, and with budget 0 a feature's "
                f"constraint set is where it is positive (paper §3), so none can be learned "
                f"(a network ending in a sigmoid is positive everywhere). Use features with "
                f"exact zeros: features/cost=local_relu_grid (GridLocalReLUBasis), an "
                f"indicator basis (shared, per_expert, regions), or end your network with "
                f"a ReLU clipped to max_value (torch.clamp(x, 0, max_value)).")

    def _held(self) -> list[tuple[str, Any]]:
        """The shards this process holds, labelled, then C-ICRL's (all of them)."""
        held = [(f"learner {v + 1}", s) for v, s in enumerate(self.shards) if s is not None]
        if self.demos is not None and len(self.shards) > 1:
            held.append(("C-ICRL", self.demos))
        return held

    def expressivity(self) -> list[float]:
        """Per held shard, then C-ICRL, the region recall bound (as ``SACTask``'s)."""
        return [self.recall_bound(s) for _, s in self._held()]

    def print_expressivity(self) -> None:
        """One line: each held shard's :meth:`recall_bound`, then C-ICRL's."""
        print("the most of the forbidden joint states each learned set can cover with this "
              "cost basis (an upper bound on region recall): "
              + ", ".join(f"{who} {self.recall_bound(s):.2f}" for who, s in self._held()),
              flush=True)

    def predicted_cells(self, learned: Any) -> list[int]:
        """The cells some expert's learned set forbids (for maps)."""
        return torch.nonzero(self._cells(learned).any(0)).flatten().tolist()


def _cells_of(predicted: torch.Tensor) -> torch.Tensor:
    """``[N, S1]`` bool from predicted joint states ``[S1]*N``: expert ``i``'s cell ``c``
    where every joint state with ``i`` at ``c`` is predicted."""
    S1 = predicted.shape[0]
    return torch.stack([predicted.movedim(i, 0).reshape(S1, -1).all(1)
                        for i in range(predicted.ndim)])


def _share(hit: torch.Tensor, where: torch.Tensor) -> float | None:
    """The share of ``where`` (the last dimension of ``hit``) that ``hit`` marks."""
    return float(hit[..., where].float().mean()) if bool(where.any()) else None
