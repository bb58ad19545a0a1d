"""Fixed feature bases and linear heads (docs/design.md §2–3).

A basis is an ``nn.Module`` without trainable parameters whose ``forward()`` returns
:class:`FactoredFeatures`: the feature vector of a joint state-action pair is

    φ(s, a) = Σ_i local[i, s_i, a_i, :] + joint[s, :]

i.e. a sum of per-expert terms plus an optional joint-*state* term (collision). This is
exactly the structure the factored solver exploits: a weighted feature vector becomes
a per-expert reward table plus a joint-state table, never a 387M-entry array.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dicrl_torch.envs.grid import GridLayout, TabularGridModel, check_regions, encode_joint
from dicrl_torch.features.base import EnvKind


@dataclass(frozen=True)
class FactoredFeatures:
    """Features in factored form.

    Attributes:
        local: ``[N, S1, A1, l]`` per-expert contribution.
        joint: ``[S, lj]`` joint-state contribution to the columns ``joint_columns``,
            or ``None``. ``S = S1**N`` (flattened, expert 1 most significant).
        joint_columns: ``[lj]`` int64, which of the ``l`` features ``joint`` feeds.
    """

    local: torch.Tensor
    joint: torch.Tensor | None = None
    joint_columns: torch.Tensor | None = None

    @property
    def dim(self) -> int:
        return self.local.shape[-1]

    def weighted(self, weights: torch.Tensor) -> FactoredReward:
        """Contract with a weight vector ``[l]`` into a :class:`FactoredReward`."""
        if weights.shape != (self.dim,):
            raise ValueError(f"weights must have shape ({self.dim},), got {tuple(weights.shape)}.")
        w = weights.to(self.local.dtype)
        local = self.local @ w
        joint = None
        if self.joint is not None:
            joint = self.joint @ w[self.joint_columns]
        return FactoredReward(local=local, joint=joint)

    def expectation(self, local_occupancy: torch.Tensor,
                    state_occupancy: torch.Tensor | None) -> torch.Tensor:
        """Feature expectation ``[l]`` from per-expert marginal occupancies
        ``[N, S1, A1]`` and the joint state occupancy ``[S]`` (needed when ``joint``)."""
        mu = torch.einsum("nsa,nsal->l", local_occupancy.to(self.local.dtype), self.local)
        if self.joint is not None:
            if state_occupancy is None:
                raise ValueError("These features have a joint-state part: pass state_occupancy.")
            mu = mu.index_add(0, self.joint_columns,
                              state_occupancy.reshape(-1).to(self.joint.dtype) @ self.joint)
        return mu

    def at(self, cells: torch.Tensor, actions: torch.Tensor, n_cells: int) -> torch.Tensor:
        """Features of joint pairs: cells, actions ``[..., N]`` int64 -> ``[..., l]``."""
        N = self.local.shape[0]
        phi = sum(self.local[i, cells[..., i], actions[..., i]] for i in range(N))
        if self.joint is not None:
            flat = encode_joint(cells, n_cells)
            phi = phi.index_add(-1, self.joint_columns, self.joint[flat]) if phi.ndim == 1 \
                else phi.index_add(phi.ndim - 1, self.joint_columns, self.joint[flat])
        return phi

    def dense(self) -> torch.Tensor:
        """``[S, A, l]`` dense features, for brute-force checks on tiny instances."""
        N, S1, A1, l = self.local.shape
        phi = torch.zeros((S1,) * N + (A1,) * N + (l,), dtype=self.local.dtype)
        for i in range(N):
            shape = [1] * (2 * N) + [l]
            shape[i], shape[N + i] = S1, A1
            phi = phi + self.local[i].reshape(shape)
        phi = phi.reshape(S1**N, A1**N, l)
        if self.joint is not None:
            phi[:, :, self.joint_columns] += self.joint.unsqueeze(1)
        return phi


@dataclass(frozen=True)
class FactoredReward:
    """A reward ``r(s, a) = Σ_i local[i, s_i, a_i] + joint[s]``.

    Attributes:
        local: ``[N, S1, A1]``.
        joint: ``[S]`` or ``None``.
    """

    local: torch.Tensor
    joint: torch.Tensor | None = None

    def __add__(self, other: FactoredReward) -> FactoredReward:
        joint = self.joint if other.joint is None else (
            other.joint if self.joint is None else self.joint + other.joint)
        return FactoredReward(local=self.local + other.local, joint=joint)

    def scale(self, c: float) -> FactoredReward:
        return FactoredReward(local=self.local * c,
                              joint=None if self.joint is None else self.joint * c)

    def dense(self) -> torch.Tensor:
        """``[S, A]`` dense reward, for brute-force checks on tiny instances."""
        N, S1, A1 = self.local.shape
        r = torch.zeros((S1,) * N + (A1,) * N, dtype=self.local.dtype)
        for i in range(N):
            shape = [1] * (2 * N)
            shape[i], shape[N + i] = S1, A1
            r = r + self.local[i].reshape(shape)
        r = r.reshape(S1**N, A1**N)
        if self.joint is not None:
            r = r + self.joint.reshape(-1, 1)
        return r


class FeatureBasis(nn.Module):
    """Base class: a fixed basis over a :class:`TabularGridModel` (a
    :class:`~dicrl_torch.features.base.Basis` of kind ``"grid"``).

    Subclasses set ``self.names`` (one label per feature), register their tables as
    buffers in ``__init__`` and implement :meth:`build`. ``forward()`` returns the
    (cached) :class:`FactoredFeatures`, checked to lie in ``[0, max_value]``."""

    max_value: float = 1.0
    names: list[str]
    # The kind of environment the basis serves: "grid", the tabular grid world (it is
    # built on a TabularGridModel). experiments/config_checks.py refuses a basis whose
    # kind is not the configured env's.
    env_kind: EnvKind = "grid"
    # Cells that each *region* feature (one covering several cells) marks, by feature
    # name, so that constraint maps can draw a learned region; single-cell features are
    # recognised by their ``cell(x,y)`` names.
    region_cells: Mapping[str, tuple[int, ...]] = {}

    def __init__(self, model: TabularGridModel) -> None:
        super().__init__()
        self.model = model
        self._cache: FactoredFeatures | None = None

    @property
    def dim(self) -> int:
        return len(self.names)

    def build(self) -> FactoredFeatures:  # pragma: no cover - abstract
        raise NotImplementedError

    def forward(self) -> FactoredFeatures:
        if self._cache is None:
            feats = self.build()
            self._validate(feats)
            self._cache = feats
        return self._cache

    def _validate(self, f: FactoredFeatures) -> None:
        m = self.model
        want = (m.n_experts, m.n_cells, m.n_actions, self.dim)
        if tuple(f.local.shape) != want:
            raise ValueError(f"{type(self).__name__} produced local features of shape "
                             f"{tuple(f.local.shape)}, expected {want}.")
        parts = [f.local] + ([f.joint] if f.joint is not None else [])
        for p in parts:
            if not torch.isfinite(p).all():
                raise ValueError(f"{type(self).__name__} produced non-finite features.")
        # φ_j(s, a) sums N local terms and the joint term: bound it column by column.
        lo = min(float(p.min()) for p in parts)
        hi_col = f.local.amax(dim=(1, 2)).sum(0)
        if f.joint is not None:
            hi_col = hi_col.index_add(0, f.joint_columns, f.joint.amax(0))
        hi = float(hi_col.max())
        if lo < 0 or hi > self.max_value + 1e-9:
            raise ValueError(
                f"{type(self).__name__} features leave [0, {self.max_value}] (min {lo:.3g}, "
                f"max {hi:.3g}); the paper assumes bounded non-negative features "
                f"(φ ∈ [0, d]^l): rescale the basis or raise its max_value.")

    def features(self) -> FactoredFeatures:
        return self()


# ------------------------------------------------------------------------ reward bases
class GoalClosenessRewardBasis(FeatureBasis):
    """Per-expert reward features of the expert's own cell (docs/design.md §3):
    ``[closeness = 1 - cheb(s_i, g_i)/(G-1), at_goal]``, so ``l_r = 2 N``; block
    ``i`` of the weight vector is expert ``i``'s ``ω_r^[i]``."""

    FEATURES = ("closeness", "at_goal")

    def __init__(self, model: TabularGridModel) -> None:
        super().__init__(model)
        N = model.n_experts
        self.names = [f"expert{i}/{n}" for i in range(N) for n in self.FEATURES]

    def build(self) -> FactoredFeatures:
        m = self.model
        layout = m.layout
        N, S1, A1, k = m.n_experts, m.n_cells, m.n_actions, len(self.FEATURES)
        cheb = torch.from_numpy(layout.chebyshev_to_goal()).to(torch.float64)  # [N, S1]
        per = torch.stack([1.0 - cheb / (layout.size - 1), (cheb == 0).to(torch.float64)], -1)
        local = torch.zeros(N, S1, A1, N * k, dtype=torch.float64)
        for i in range(N):
            local[i, :, :, i * k:(i + 1) * k] = per[i].unsqueeze(1)
        return FactoredFeatures(local=local)

    def true_weights(self, per_expert: tuple[float, ...] = (1.0, 2.0)) -> torch.Tensor:
        """Ground-truth ``ω_rE``: the same ``per_expert`` weights for every expert."""
        return torch.tensor(list(per_expert) * self.model.n_experts, dtype=torch.float64)


# -------------------------------------------------------------------------- cost bases
def _collision_table(model: TabularGridModel) -> torch.Tensor:
    """``[S]`` float64: 1 where two experts share a cell."""
    N, S1 = model.n_experts, model.n_cells
    if N == 1:
        return torch.zeros(S1, dtype=torch.float64)
    grids = torch.meshgrid(*[torch.arange(S1)] * N, indexing="ij")
    hit = torch.zeros(grids[0].shape, dtype=torch.bool)
    for i in range(N):
        for j in range(i + 1, N):
            hit |= grids[i] == grids[j]
    return hit.reshape(-1).to(torch.float64)


class _IndicatorCostBasis(FeatureBasis):
    """Cell, action and collision indicators; ``per_expert`` decides whether the
    cell/action indicators are shared by all experts or one set per expert."""

    per_expert: bool

    def __init__(self, model: TabularGridModel) -> None:
        super().__init__(model)
        from dicrl_torch.envs.grid import ACTION_NAMES

        G = model.layout.size
        unit = [f"cell({c % G},{c // G})" for c in range(model.n_cells)]
        unit += [f"action {a}" for a in ACTION_NAMES]
        self._unit = len(unit)
        blocks = ([[f"expert{i}/{u}" for u in unit] for i in range(model.n_experts)]
                  if self.per_expert else [unit])
        self.names = [n for b in blocks for n in b] + ["collision"]
        # A shared cell indicator counts every expert standing in the cell.
        self.max_value = 1.0 if self.per_expert else float(model.n_experts)

    def _block(self, i: int) -> slice:
        start = i * self._unit if self.per_expert else 0
        return slice(start, start + self._unit)

    def build(self) -> FactoredFeatures:
        m = self.model
        N, S1, A1 = m.n_experts, m.n_cells, m.n_actions
        local = torch.zeros(N, S1, A1, self.dim, dtype=torch.float64)
        for i in range(N):
            b = self._block(i).start
            local[i, torch.arange(S1), :, b + torch.arange(S1)] = 1.0
            local[i, :, torch.arange(A1), b + S1 + torch.arange(A1)] = 1.0
        joint = _collision_table(m).unsqueeze(1)
        return FactoredFeatures(local=local, joint=joint,
                                joint_columns=torch.tensor([self.dim - 1]))

    def true_constraints(self, layout: GridLayout | None = None) -> torch.Tensor:
        """``[l]`` bool: which features are true constraints of ``layout``."""
        layout = layout or self.model.layout
        S1 = self.model.n_cells
        unit = torch.zeros(self._unit, dtype=torch.bool)
        unit[:S1] = torch.from_numpy(layout.obstacle_mask())
        unit[S1:] = torch.from_numpy(layout.forbidden_action_mask())
        mask = torch.zeros(self.dim, dtype=torch.bool)
        for i in range(self.model.n_experts if self.per_expert else 1):
            mask[self._block(i)] = unit
        mask[-1] = layout.collision_constraint and self.model.n_experts > 1
        return mask

    def true_weights(self, layout: GridLayout | None = None) -> torch.Tensor:
        """Ground-truth ``ω_cE`` in ``[0, 1]^l``: 1 on true constraints."""
        return self.true_constraints(layout).to(torch.float64)


class SharedIndicatorCostBasis(_IndicatorCostBasis):
    """Default cost basis: one indicator per cell (``S1``), per action (9), counted for
    each expert, and one collision indicator: ``l_c = S1 + 9 + 1`` (91 on 9x9)."""

    per_expert = False


class PerExpertIndicatorCostBasis(_IndicatorCostBasis):
    """Per-expert cost basis ``φ_c^[i]`` (the paper's notation): a cell and action
    indicator set for each expert plus the shared collision indicator:
    ``l_c = N (S1 + 9) + 1``."""

    per_expert = True


class RegionIndicatorCostBasis(_IndicatorCostBasis):
    """The shared basis plus one indicator per named *region* (a set of cells), as in
    Scobee & Sastry's grid world, where each wall colour is one constraint feature:
    ``l_c = S1 + 9 + R + 1``. A region's feature counts every expert standing in one of
    its cells, like a cell's.

    A region forbids all its cells with one weight, so the demonstrations' evidence
    against any of its cells moves that one weight: a wall of cells that no single cell's
    evidence would mark can be learned as a whole.

    Ground truth. The cells of a region now have two features, so the true
    representation ``ω_cE`` must choose; it follows Scobee & Sastry: a region whose cells
    are all obstacles is a true constraint and its cells' own indicators carry
    ``ω_cE = 0`` (redundant, and counted as false if learned); every other obstacle is
    constrained by its cell's indicator; a region holding a free cell is not a
    constraint.

    Args:
        model: the tabular model.
        regions: ``name -> cells``, each cell an ``(x, y)`` pair; default the layout's
            own (``GridLayout.regions``: Scobee's two wall colours on his layout, none
            on an open grid, which leaves the shared basis).
    """

    per_expert = False

    def __init__(self, model: TabularGridModel,
                 regions: Mapping[str, Sequence[tuple[int, int]]] | None = None) -> None:
        super().__init__(model)
        layout = model.layout
        checked = check_regions(layout.regions if regions is None else regions, layout.size)
        self.region_cells = {f"region {name}": tuple(sorted({layout.cell(c) for c in cells}))
                             for name, cells in checked.items()}
        self.names = self.names[:-1] + list(self.region_cells) + ["collision"]

    def build(self) -> FactoredFeatures:
        f = super().build()  # cells, actions and collision; the region columns are 0
        first = self._unit
        for r, cells in enumerate(self.region_cells.values()):
            f.local[:, list(cells), :, first + r] = 1.0
        return f

    def true_constraints(self, layout: GridLayout | None = None) -> torch.Tensor:
        layout = layout or self.model.layout
        mask = super().true_constraints(layout)
        obstacle = torch.from_numpy(layout.obstacle_mask())
        for r, cells in enumerate(self.region_cells.values()):
            walled = bool(obstacle[list(cells)].all())
            mask[self._unit + r] = walled
            if walled:
                mask[list(cells)] = False
        return mask


# ------------------------------------------------------------------ deep / generic basis
def cell_encoding(layout: GridLayout) -> torch.Tensor:
    """``[S1, 2]`` normalised ``(x, y)`` in ``[0, 1]`` of every cell."""
    c = torch.arange(layout.n_cells)
    return torch.stack([c % layout.size, c // layout.size], 1).to(torch.float64) / (layout.size - 1)


class FrozenModuleBasis(FeatureBasis):
    """Wrap any frozen ``nn.Module`` mapping a per-expert state-action encoding
    ``[B, 2 + A1]`` (normalised x, y and a one-hot action) to ``[B, l]`` features.

    The module is applied to every ``(s_i, a_i)`` once; its parameters are frozen
    (``requires_grad_(False)``) and its outputs must lie in ``[0, max_value]`` (a
    sigmoid head does that). With ``per_expert=False`` every expert shares the
    features (summed); with ``True`` expert ``i`` gets its own block.

    Args:
        model: the tabular model.
        module: the network, e.g. a randomly initialised or pretrained MLP.
        out_dim: number of features the module returns.
        per_expert: one block per expert instead of shared features.
        max_value: bound on each module output (shared features: ``N`` times that).
    """

    def __init__(self, model: TabularGridModel, module: nn.Module, out_dim: int,
                 per_expert: bool = False, max_value: float = 1.0) -> None:
        super().__init__(model)
        if out_dim < 1:
            raise ValueError(f"out_dim must be >= 1, got {out_dim}.")
        self.net = module.requires_grad_(False).eval()
        self.out_dim, self.per_expert = out_dim, per_expert
        # Shared features are summed over the experts standing in their cells.
        self.max_value = max_value if per_expert else max_value * model.n_experts
        blocks = model.n_experts if per_expert else 1
        self.names = [f"expert{i}/f{j}" if per_expert else f"f{j}"
                      for i in range(blocks) for j in range(out_dim)]

    def build(self) -> FactoredFeatures:
        m = self.model
        N, S1, A1 = m.n_experts, m.n_cells, m.n_actions
        enc = torch.cat([
            cell_encoding(m.layout).repeat_interleave(A1, 0),
            torch.eye(A1, dtype=torch.float64).repeat(S1, 1),
        ], 1)
        with torch.no_grad():
            p = next(self.net.parameters(), None)
            dtype = p.dtype if p is not None else torch.float32
            out = self.net(enc.to(dtype)).to(torch.float64)
        if out.shape != (S1 * A1, self.out_dim):
            raise ValueError(f"The wrapped module returned shape {tuple(out.shape)} for "
                             f"{S1 * A1} inputs; expected ({S1 * A1}, {self.out_dim}). Set "
                             f"out_dim to the module's output width.")
        out = out.reshape(S1, A1, self.out_dim)
        local = torch.zeros(N, S1, A1, self.dim, dtype=torch.float64)
        for i in range(N):
            b = i * self.out_dim if self.per_expert else 0
            local[i, :, :, b:b + self.out_dim] = out
        return FactoredFeatures(local=local)


def random_mlp(out_dim: int = 16, hidden: int = 64, seed: int = 0, n_actions: int = 9) -> nn.Module:
    """A randomly initialised MLP with sigmoid outputs, for :class:`FrozenModuleBasis`."""
    g = torch.Generator().manual_seed(seed)
    net = nn.Sequential(nn.Linear(2 + n_actions, hidden), nn.Tanh(),
                        nn.Linear(hidden, out_dim), nn.Sigmoid())
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    return net


class LinearHead(nn.Module):
    """Linear weights over a basis: ``reward = head(basis())`` is a FactoredReward.

    Args:
        dim: number of features.
        init: initial weights ``[dim]`` (zeros by default).
    """

    def __init__(self, dim: int, init: torch.Tensor | np.ndarray | None = None) -> None:
        super().__init__()
        w = torch.zeros(dim, dtype=torch.float64) if init is None else torch.as_tensor(
            init, dtype=torch.float64).clone()
        if w.shape != (dim,):
            raise ValueError(f"init must have shape ({dim},), got {tuple(w.shape)}.")
        self.register_buffer("weight", w)

    def forward(self, features: FactoredFeatures) -> FactoredReward:
        return features.weighted(self.weight)
