"""A deep cost basis whose features can be constraints: local ReLU units.

With a budget of 0 the constraint set of a feature is its support, ``C_j = {φ_j > 0}``
(paper §3). A feature positive everywhere (a sigmoid network's) forbids the whole space
and can never be a constraint; a feature with exact zeros outside a small region can.
:class:`LocalReLUBasis` is a frozen two-layer ReLU network built so that every output
unit is *local*:

- hidden units ``ReLU(±u_m · (x - c_k))`` along ``M`` directions ``u_m`` (evenly spaced,
  randomly rotated) give ``Σ_m |u_m · (x - c_k)|``, a polygonal norm of ``x - c_k``
  (a ``2M``-gon; scaled, within a few per cent of the Euclidean norm);
- the output ``φ_k(x) = ReLU(1 - ν(x - c_k) / ρ)`` is 1 at its centre ``c_k`` and exactly
  0 outside the polygon of radius ``ρ`` round it.

The centres spread over the box an agent can reach by farthest-point sampling of a
seeded uniform pool (no two close, no region left out), and ``ρ`` is the pool's covering
radius in that norm (plus the pool's spacing) times ``overlap``: every reachable position
lies in some feature's support. Pairs of agents get units of their separation
``ν(x_i - x_j)`` instead, rings ``ReLU(1 - |ν - c_r| / w_r)`` at separations from 0 to
``ring_range``, spaced quadratically: a minimum distance is a region of the separation, and
the short range is where pairwise constraints live, so they are fine there and coarse far
out. Nothing is read from the game but the box and the number of agents: moving an
obstacle leaves every weight as it was (tests/test_local_basis.py).

What it can and cannot express (docs/design.md §6, "Deep cost features"): a forbidden
region is recovered where it is covered by the supports of features that no
demonstration and no start state enters; the part of the region within ``ρ`` of where the
experts fly is not (those features are used by the experts), nor is any constraint on
velocities or actions (the units read positions only).
:func:`~dicrl_torch.region.recall_bound` measures it per learner before training.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import numpy as np
import torch

from dicrl_torch.checks import check_int, check_positive
from dicrl_torch.features.continuous import (
    ContinuousFeatureBasis,
    _optional_int,
    check_bounds,
    check_position_columns,
)

__all__ = ["LocalReLUBasis", "farthest_points"]


def farthest_points(pool: np.ndarray, k: int, rng: np.random.Generator
                    ) -> tuple[np.ndarray, float]:
    """``k`` points of ``pool`` ``[P, d]`` chosen greedily, each the farthest from those
    chosen before (the first at random), and the pool's covering radius: the largest
    distance from a pool point to its nearest chosen point."""
    if not 1 <= k <= len(pool):
        raise ValueError(f"farthest_points needs 1 <= k <= {len(pool)} pool points, got "
                         f"k={k}.")
    chosen = [int(rng.integers(len(pool)))]
    nearest = np.linalg.norm(pool - pool[chosen[0]], axis=1)
    for _ in range(k - 1):
        j = int(np.argmax(nearest))
        chosen.append(j)
        nearest = np.minimum(nearest, np.linalg.norm(pool - pool[j], axis=1))
    return pool[chosen], float(nearest.max())


class LocalReLUBasis(ContinuousFeatureBasis):
    """Local ReLU units over each agent's position and the agents' separations (module
    docstring): ``l = K (N if per_agent else 1) + R``, values in ``[0, max_value]``.

    Args:
        n_agents: ``N``.
        bounds: ``((x_lo, x_hi), (y_lo, y_hi))``, the box an agent can reach.
        n_centres: ``K`` position units at the finest scale.
        scales: unit sizes, as multiples of the finest: at scale ``m``, ``K / m²`` units
            spread and sized as the finest are (so ``m`` times wider). Evidence that a
            policy entered part of a forbidden region then reaches as far as the
            experts' data allows: a coarse unit no expert enters is learned whole.
        n_rings: ``R`` separation units (0: none, a game without pairwise constraints).
        ring_range: the largest separation they cover (default: half the box's shorter
            side); their centres lie at ``ring_range (r / R)²``, finer near 0.
        directions: ``M`` directions of the polygonal norm (``2M``-gon supports).
        overlap: the support radius over the centres' covering radius (>= 1: every
            reachable position lies in some support; larger: more overlap, coarser).
        per_agent: one set of units per agent, named ``f"{agent_prefix}{i}/local{k}"``
            (the agent's own), or (False) shared units ``local{k}`` counting the agents
            in them.
        agent_prefix: how per-agent names start (the drones' bases say ``"drone"``).
        seed: the pool, the first centre and the directions' rotation.
        position_columns: the state components holding ``x`` and ``y``.
        state_dim: when given, inputs must have this ``d_s``.
    """

    def __init__(self, *, n_agents: int, bounds: Sequence[Sequence[float]],
                 n_centres: int = 144, scales: Sequence[int] = (1,), n_rings: int = 24,
                 directions: int = 6,
                 ring_range: float | None = None, overlap: float = 1.0,
                 per_agent: bool = False, agent_prefix: str = "agent",
                 seed: int = 0, position_columns: Sequence[int] = (0, 1),
                 state_dim: int | None = None) -> None:
        super().__init__()
        self.n_agents = check_int("n_agents", n_agents)
        self.state_dim = _optional_int("state_dim", state_dim)
        b = check_bounds(bounds)
        self.bounds = tuple(tuple(float(v) for v in row) for row in b)
        k = check_int("n_centres", n_centres)
        r = check_int("n_rings", n_rings, 0)
        m = check_int("directions", directions)
        self.overlap = check_positive("overlap", overlap)
        if self.overlap < 1.0:
            raise ValueError(f"overlap must be >= 1 (below it some reachable positions lie "
                             f"in no feature's support), got {overlap!r}.")
        if not isinstance(per_agent, bool):
            raise ValueError(f"per_agent must be a bool, got {per_agent!r}.")
        self.per_agent, self.agent_prefix = per_agent, str(agent_prefix)
        self.position_columns = check_position_columns(position_columns, self.state_dim)
        rng = np.random.default_rng([check_int("seed", seed, 0), 52])
        pool = rng.uniform(b[:, 0], b[:, 1], size=(max(64 * k, 4096), 2))
        scales = tuple(check_int("scales", m) for m in scales)
        if not scales or len(set(scales)) != len(scales):
            raise ValueError(f"scales must be distinct positive ints, got {scales!r}.")
        per_scale = [farthest_points(pool, max(1, round(k / m**2)), rng)[0] for m in scales]
        angle = rng.uniform(0.0, math.pi / m) + math.pi * np.arange(m) / m
        # π / (2M) Σ_m |u_m · v| is |v| on average over v's direction (E|cos| = 2/π).
        scale = math.pi / (2 * m)
        directions_ = scale * np.stack([np.cos(angle), np.sin(angle)], 1)  # [M, 2]
        # Per scale: the covering radius in the units' own norm, plus the pool's spacing
        # (a position between pool points): every reachable position lies in a support.
        spacing = math.sqrt(float(np.prod(b[:, 1] - b[:, 0])) / len(pool))
        centres, radii = [], []
        for c in per_scale:
            # in blocks of the pool: [P, K, M] at once is gigabytes for fine units
            gap = np.concatenate([
                np.abs((part[:, None, :] - c[None]) @ directions_.T).sum(-1).min(1)
                for part in np.array_split(pool, max(1, len(pool) * len(c) // 2**20))])
            centres.append(c)
            radii.append(np.full(len(c), self.overlap * (float(gap.max()) + spacing)))
        centres, radii = np.concatenate(centres), np.concatenate(radii)
        k = len(centres)
        self.scales = scales
        reach = 0.5 * float((b[:, 1] - b[:, 0]).min()) if ring_range is None \
            else check_positive("ring_range", ring_range)
        # Centres at reach (r/R)²: fine where separations are small (a minimum distance,
        # a collision), coarse far out; each ring's half-width is its spacing there.
        grid = reach * (np.arange(r + 1) / max(r, 1)) ** 2
        rings, widths = grid[:-1], np.diff(grid)
        self.ring_range = reach
        self.register_buffer("centres", torch.tensor(centres))
        self.register_buffer("radii", torch.tensor(radii))
        self.register_buffer("directions", torch.tensor(directions_))
        self.register_buffer("rings", torch.tensor(rings))
        self.register_buffer("ring_widths", torch.tensor(widths))
        self.register_buffer("_columns", torch.tensor(self.position_columns), persistent=False)
        self.n_centres, self.n_rings = k, r
        self.unit_margin = self.ring_margin = 0.0  # grown by dilated()
        n_pairs = self.n_agents * (self.n_agents - 1) // 2
        self.max_value = float(max(1 if per_agent else self.n_agents, n_pairs if r else 0, 1))
        if per_agent:
            self.names = [f"{self.agent_prefix}{i}/local{j}" for i in range(self.n_agents)
                          for j in range(k)]
        else:
            self.names = [f"local{j}" for j in range(k)]
        self.names += [f"ring{j}" for j in range(r)]

    @property
    def radius(self) -> float:
        """The finest units' support radius ``ρ`` (grown by :meth:`dilated`)."""
        return float(self.radii.min()) + self.unit_margin

    def _norm(self, v: torch.Tensor) -> torch.Tensor:
        """The polygonal norm ``[...]`` of vectors ``[..., 2]``: the hidden ReLU layer
        ``ReLU(u_m · v) + ReLU(-u_m · v)`` summed."""
        a = v @ self.directions.to(v.dtype).T  # [..., M]
        return (torch.relu(a) + torch.relu(-a)).sum(-1)

    def _norm_numpy(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """:meth:`_norm` of vectors given by their components ``dx``, ``dy`` (same shape),
        for the planner's numpy path: written out over the ``M`` directions, since a
        matmul over a last axis of 2 costs several times more."""
        total = np.zeros(np.shape(dx))
        for ux, uy in self.directions.numpy():
            total += np.abs(ux * dx + uy * dy)
        return total

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        if max(self.position_columns) >= states.shape[-1]:
            raise ValueError(f"{self.label}: position_columns {self.position_columns} do not "
                             f"fit states with d_s={states.shape[-1]} components; set "
                             f"position_columns to the columns of x and y.")
        pos = states.index_select(-1, self._columns)  # [..., N, 2]
        centres = self.centres.to(states.dtype)
        radii = self.radii.to(states.dtype) + self.unit_margin
        local = torch.relu(1.0 - self._norm(pos.unsqueeze(-2) - centres) / radii)
        local = local.flatten(-2) if self.per_agent else local.sum(-2)  # [..., N K] / [..., K]
        if not self.n_rings:
            return local
        n = states.shape[-2]
        i, j = torch.triu_indices(n, n, 1, device=states.device)
        separation = self._norm(pos[..., i, :] - pos[..., j, :])  # [..., P]
        gap = (separation.unsqueeze(-1) - self.rings.to(states.dtype)).abs()
        width = self.ring_widths.to(states.dtype) + self.ring_margin
        rings = torch.relu(1.0 - gap / width).sum(-2)  # [..., R]
        return torch.cat([local, rings], -1)

    # ---- what a planner asks of a cost basis -----------------------------------------
    dilatable = True

    def dilated(self, margin: float) -> LocalReLUBasis:
        """The same units, each support grown by ``margin`` (its radius, and a ring's
        half-width; values inside rescaled to the wider unit): where a learned unit
        fires within ``margin`` of where it fires here."""
        margin = float(margin)
        if not np.isfinite(margin) or margin < 0:
            raise ValueError(f"margin must be a finite number >= 0, got {margin!r}.")
        grown = copy.deepcopy(self)
        grown.unit_margin, grown.ring_margin = self.unit_margin + margin, \
            self.ring_margin + margin
        return grown

    def dot(self, states: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """``[...]`` the features of joint states ``[..., N, d_s]`` times ``weights
        [l]``, equal to ``numpy_features(states) @ weights`` up to the order of the sum.

        A planner calls it on ten thousand states per model step: each position is
        compared only with the units of nonzero weight whose support can reach its bin
        of a grid over the box (the others are exactly 0 there), a handful instead of
        all ``K``."""
        w = np.asarray(weights, dtype=np.float64)
        states = np.asarray(states, dtype=np.float64)
        n, k, first_ring = self.n_agents, self.n_centres, len(self.names) - self.n_rings
        w_units = w[:first_ring].reshape(n if self.per_agent else 1, k)  # [N or 1, K]
        out = np.zeros(states.shape[:-2])
        pos = states[..., list(self.position_columns)]  # [..., N, 2]
        live = np.flatnonzero((w_units != 0).any(0))
        if len(live):
            cand, lo, size, shape = self._candidates(live)
            flat = pos.reshape(-1, n, 2)
            cell = np.clip(((flat - lo) / size).astype(np.int64), 0, np.array(shape) - 1)
            idx = cand[cell[..., 0] * shape[1] + cell[..., 1]]  # [P, N, C], -1: none
            near = idx[..., 0] >= 0  # [P, N]: some unit can reach (rows fill from the left)
            if near.any():
                position, agent = np.nonzero(near)  # [Q] each
                units = idx[near]  # [Q, C]
                units = units[:, :int((units >= 0).sum(1).max())]
                safe = np.maximum(units, 0)
                centres = self.centres.numpy()
                nu = self._norm_numpy(flat[near, 0, None] - centres[safe, 0],
                                      flat[near, 1, None] - centres[safe, 1])
                radii = self.radii.numpy()[safe] + self.unit_margin
                phi = np.maximum(1.0 - nu / radii, 0.0) * (units >= 0)
                row = agent[:, None] if self.per_agent else 0  # the agent's weights
                value = (phi * w_units[row, safe]).sum(-1)  # [Q]
                out += np.bincount(position, weights=value,
                                   minlength=len(flat)).reshape(out.shape)
        w_rings = w[first_ring:]
        if self.n_rings and w_rings.any():
            keep = np.flatnonzero(w_rings)
            i, j = np.triu_indices(n, 1)
            diff = pos[..., i, :] - pos[..., j, :]  # [..., pairs, 2]
            sep = self._norm_numpy(diff[..., 0], diff[..., 1])
            gap = np.abs(sep[..., None] - self.rings.numpy()[keep])
            width = self.ring_widths.numpy()[keep] + self.ring_margin
            out += (np.maximum(1.0 - gap / width, 0.0) @ w_rings[keep]).sum(-1)
        return out

    def _candidates(self, live: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, tuple]:
        """For the units ``live``: a grid over the box (bins as wide as the largest
        support), and per bin the units whose support can reach it, ``[bins, C]`` padded
        with -1; cached per set of units and margin."""
        key = (live.tobytes(), self.unit_margin)
        cache = self.__dict__.setdefault("_candidate_cache", {})
        if key not in cache:
            b = np.asarray(self.bounds)
            radii = self.radii.numpy()[live] + self.unit_margin
            # ν >= 0.97 |v| for these directions (a 2M-gon, M >= 3): a generous reach
            reach = radii / 0.95
            size = float(reach.max()) / 4  # fine bins: few candidates, most bins none
            shape = tuple(int(np.ceil((b[d, 1] - b[d, 0]) / size)) + 1 for d in range(2))
            lo = b[:, 0]
            gx, gy = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
            cells_lo = lo + size * np.stack([gx.ravel(), gy.ravel()], -1)  # [bins, 2]
            centres = self.centres.numpy()[live]
            # distance from each centre to each bin's rectangle (0 inside)
            d = np.maximum(cells_lo[:, None] - centres[None], 0) + np.maximum(
                centres[None] - (cells_lo[:, None] + size), 0)
            near = np.linalg.norm(d, axis=-1) <= reach[None]  # [bins, live]
            width = max(1, int(near.sum(1).max()))
            cand = np.full((len(cells_lo), width), -1, dtype=np.int64)
            for c, row in enumerate(near):
                units = live[np.flatnonzero(row)]
                cand[c, :len(units)] = units
            cache[key] = (cand, lo, size, shape)
        return cache[key]
