"""Fixed feature bases of the drone arena (docs/design.md §7, paper §6.2).

A basis is an ``nn.Module`` without trainable parameters mapping batched joint states
``[..., 2, 4]`` (positions ``x, y`` and velocities of the two drones; optionally the
commands ``[..., 2, 2]``, unused by the bases here) to features ``[..., l]`` in
``[0, max_value]`` (the paper's ``φ ∈ [0, d]^l``), checked on every call. All of them
are functions of the state only, so they can be evaluated on solver rollouts and on
demonstrations alike, on numpy or torch input, CPU or GPU.

Cost bases (``true_constraints()`` gives the ground-truth constraint set ``[l]`` bool):

- :class:`CellOccupancyCostBasis` (default): per drone a one-hot of its 1 m cell of the
  10 x 10 grid, plus one shared proximity indicator: ``l = 2 * 100 + 1 = 201``.
- :class:`RBFCostBasis`: per drone Gaussian bumps centred on an ``n x n`` grid, plus a
  smooth proximity bump: ``l = 2 n^2 + 1``.

Reward bases:

- :class:`DoorLocationRewardBasis` (default): per drone its position projected on the
  direction of its door and its closeness to the door: ``l = 4``.
- :class:`FourierRewardBasis`: per drone a cosine basis of its position:
  ``l = 2 (order + 1)^2``.
"""

from __future__ import annotations

import numpy as np
import torch

from dicrl_torch.checks import check_int, check_positive
from dicrl_torch.envs.drones import (
    CELL_SIZE,
    GRID_CELLS,
    N_DRONES,
    NOMINAL_STARTS,
    PROXIMITY_RADIUS,
    ROOM_SIZE,
    door_centres,
    in_obstacle,
    in_own_door,
    obstacle_cell_mask,
)
from dicrl_torch.features.continuous import ContinuousFeatureBasis


class DroneFeatureBasis(ContinuousFeatureBasis):
    """Base class of the drone bases: a
    :class:`~dicrl_torch.features.continuous.ContinuousFeatureBasis` (kind
    ``"continuous"``) fixed to the arena's joint states ``[..., 2, 4]`` and commands
    ``[..., 2, 2]``, whose input and output checks it uses.

    Subclasses set ``self.names`` (one label per feature, ``drone<i>/...`` for drone
    ``i``'s own) and ``self.max_value``, register their constants as (non-persistent)
    buffers and implement :meth:`compute`.
    """

    n_agents: int = N_DRONES
    state_dim: int = 4
    action_dim: int = 2
    agent_prefix: str = "drone"  # drone i's own features are named drone<i>/...
    game: str = "drones"  # built on the arena's geometry: no other game's basis

    def compute(self, states: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """``[..., 2, 4]`` checked joint states to ``[..., l]`` features."""
        raise NotImplementedError

    def drone_shares(self) -> torch.Tensor:
        """``[l, N_DRONES]`` float64: :meth:`agent_shares` of the arena's drones (a
        ``drone<i>/...`` feature is drone ``i``'s alone, the proximity is shared
        equally)."""
        return self.agent_shares()


def _proximity_indicator(pos: torch.Tensor, radius: float) -> torch.Tensor:
    """``[..., 1]`` 1.0 where the drones of ``pos [..., 2, 2]`` are closer than ``radius``."""
    diff = pos[..., 0, :] - pos[..., 1, :]
    return ((diff * diff).sum(-1, keepdim=True) < radius * radius).to(pos.dtype)


# -------------------------------------------------------------------------- cost bases
class CellOccupancyCostBasis(DroneFeatureBasis):
    """Per drone a one-hot of its grid cell, plus a shared proximity indicator.

    Feature ``i * 100 + iy * 10 + ix`` is 1 when drone ``i`` is in cell ``(ix, iy)``
    (``[ix, ix+1) x [iy, iy+1)`` metres; positions outside the room count in the nearest
    border cell); the last feature is 1 when the drones are closer than
    ``proximity_radius``. ``l = 201``, values in ``{0, 1}``, ``max_value = 1``.

    With ``margin`` δ > 0 (:meth:`dilated`) every feature fires within δ of where it
    fires without: a drone counts in each cell whose square grown by δ on every side holds
    it (up to 4 cells near a corner), and the proximity fires below ``proximity_radius +
    δ``. That basis is not a model of the constraints; it is the penalty that a last solve
    can train on so that the deployed policy keeps δ clear of its learned cells
    (docs/drones.md, "A margin round the learned cells").

    Args:
        proximity_radius: distance (m) below which the proximity feature fires; the
            env's collision radius by default.
        margin: δ in metres, in ``[0, CELL_SIZE / 2)``; 0: the exact cells.
    """

    def __init__(self, proximity_radius: float = PROXIMITY_RADIUS, margin: float = 0.0) -> None:
        super().__init__()
        self.proximity_radius = check_positive("proximity_radius", proximity_radius)
        margin = float(margin)
        if not 0.0 <= margin < CELL_SIZE / 2:
            raise ValueError(f"margin must lie in [0, {CELL_SIZE / 2}) metres (half a cell), "
                             f"got {margin!r}.")
        self.margin = margin
        G = GRID_CELLS
        self.names = [f"drone{i}/cell({c % G},{c // G})" for i in range(N_DRONES)
                      for c in range(G * G)] + ["proximity"]
        self.max_value = 1.0
        # A buffer only to follow .to(device); it carries no state worth saving.
        self.register_buffer("_offsets", torch.arange(N_DRONES) * G * G, persistent=False)

    dilatable = True

    def dilated(self, margin: float) -> CellOccupancyCostBasis:
        """The same features grown by ``margin`` metres (class docstring)."""
        return CellOccupancyCostBasis(self.proximity_radius, margin=margin)

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        G = GRID_CELLS
        pos = states[..., :2]
        onehot = torch.zeros((*states.shape[:-2], N_DRONES * G * G), dtype=states.dtype,
                             device=states.device)
        # The cells of the lowest and the highest corner of the δ-square round each drone
        # (the same cell when δ = 0), then the four combinations of their x and y.
        lo = torch.floor((pos - self.margin) / CELL_SIZE).clamp(0, G - 1).long()  # [..., 2, 2]
        hi = lo if self.margin == 0 else \
            torch.floor((pos + self.margin) / CELL_SIZE).clamp(0, G - 1).long()
        corners = [(lo, lo)] if self.margin == 0 else [(lo, lo), (hi, lo), (lo, hi), (hi, hi)]
        for x_of, y_of in corners:
            ix, iy = x_of[..., 0], y_of[..., 1]
            onehot.scatter_(-1, iy * G + ix + self._offsets, 1.0)  # [..., 2] cells
        proximity = _proximity_indicator(pos, self.proximity_radius + self.margin)
        return torch.cat([onehot, proximity], -1)

    def dot(self, states: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """``[...]`` float64 ``compute(states) @ weights`` for numpy joint states
        ``[..., 2, 4]`` and ``weights [201]``, by looking the weights up (a planner's
        thousands of states per step; no ``[..., 201]`` features built, no input checks).
        Equal bit for bit to the features' sum, term by term in the same order; each
        coordinate is floored once into an index array (no float sums over axes of two,
        which numpy reduces slowly)."""
        G, states = GRID_CELLS, np.asarray(states, dtype=np.float64)
        w = np.asarray(weights, dtype=np.float64)
        xs, ys = states[..., 0], states[..., 1]  # [..., 2]: both drones

        def cells(coordinate: np.ndarray, shift: float) -> np.ndarray:
            """The cell index along one axis of ``coordinate - shift``, clamped."""
            c = coordinate - shift
            if CELL_SIZE != 1.0:
                c /= CELL_SIZE
            np.floor(c, out=c)
            return np.clip(c, 0, G - 1, out=c).astype(np.int64)

        offsets = np.arange(N_DRONES) * G * G
        lo_x, lo_y = cells(xs, self.margin), cells(ys, self.margin)
        lo_row = lo_y * G + offsets
        total = w.take(lo_row + lo_x)  # [..., 2]
        if self.margin:
            hi_x, hi_y = cells(xs, -self.margin), cells(ys, -self.margin)
            # Each distinct cell of the δ-square once: the x and y of its two corners
            # differ only near an edge.
            x2, y2 = hi_x != lo_x, hi_y != lo_y
            hi_row = hi_y * G + offsets
            total += x2 * w.take(lo_row + hi_x)
            total += y2 * w.take(hi_row + lo_x)
            total += (x2 & y2) * w.take(hi_row + hi_x)
        gap_x, gap_y = xs[..., 0] - xs[..., 1], ys[..., 0] - ys[..., 1]
        near = gap_x * gap_x + gap_y * gap_y < (self.proximity_radius + self.margin) ** 2
        return (total[..., 0] + total[..., 1]) + near * w[-1]

    def true_constraints(self) -> torch.Tensor:
        """``[201]`` bool: for each drone the cells overlapping an obstacle, and the
        proximity feature."""
        cells = torch.from_numpy(obstacle_cell_mask())
        return torch.cat([cells.repeat(N_DRONES), torch.tensor([True])])

    def true_weights(self) -> torch.Tensor:
        """Ground-truth ``ω_cE`` in ``[0, 1]^l``: 1 on true constraints."""
        return self.true_constraints().to(torch.float64)


class RBFCostBasis(DroneFeatureBasis):
    """A smooth cost basis: per drone Gaussian bumps on an ``n x n`` grid of centres,
    plus a Gaussian proximity bump.

    Feature ``i * n^2 + ky * n + kx`` is ``exp(-|p_i - c|^2 / (2 width^2))`` with centre
    ``c = ((kx + 0.5) 10/n, (ky + 0.5) 10/n)``; the last is
    ``exp(-|p_0 - p_1|^2 / (2 r^2))``. ``l = 2 n^2 + 1``, values in ``(0, 1]``. With the
    default ``n = 10`` the centres are the cell centres of
    :class:`CellOccupancyCostBasis`, so the two bases share the true constraint set.

    Args:
        n_per_axis: centres per axis ``n``.
        width: bump width (m); default half the centre spacing.
        proximity_radius: width ``r`` (m) of the proximity bump.
    """

    def __init__(self, n_per_axis: int = GRID_CELLS, width: float | None = None,
                 proximity_radius: float = PROXIMITY_RADIUS) -> None:
        super().__init__()
        n = check_int("n_per_axis", n_per_axis)
        spacing = ROOM_SIZE / n
        self.width = check_positive("width", 0.5 * spacing if width is None else width)
        self.proximity_radius = check_positive("proximity_radius", proximity_radius)
        self.n_per_axis = n
        k = (torch.arange(n, dtype=torch.float64) + 0.5) * spacing
        cy, cx = torch.meshgrid(k, k, indexing="ij")  # index ky * n + kx
        self.register_buffer("centres", torch.stack([cx.reshape(-1), cy.reshape(-1)], -1),
                             persistent=False)
        self.names = [f"drone{i}/rbf({kx},{ky})" for i in range(N_DRONES)
                      for ky in range(n) for kx in range(n)] + ["proximity"]
        self.max_value = 1.0

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        pos = states[..., :2]
        c = self.centres.to(states.dtype)
        d2 = ((pos.unsqueeze(-2) - c) ** 2).sum(-1)  # [..., 2, n^2]
        bumps = torch.exp(-d2 / (2 * self.width**2)).flatten(-2)
        diff = pos[..., 0, :] - pos[..., 1, :]
        prox = torch.exp(-(diff * diff).sum(-1, keepdim=True) / (2 * self.proximity_radius**2))
        return torch.cat([bumps, prox], -1)

    def true_constraints(self) -> torch.Tensor:
        """``[2 n^2 + 1]`` bool: for each drone the centres inside an obstacle, and the
        proximity feature."""
        inside = in_obstacle(self.centres.cpu())
        return torch.cat([inside.repeat(N_DRONES), torch.tensor([True])])

    def true_weights(self) -> torch.Tensor:
        """Ground-truth ``ω_cE`` in ``[0, 1]^l``: 1 on true constraints."""
        return self.true_constraints().to(torch.float64)


# ------------------------------------------------------------------------ reward bases
class DoorLocationRewardBasis(DroneFeatureBasis):
    """Per drone its location times a coefficient, oriented towards its door (paper §6.2).

    For drone ``i`` with nominal start ``s_i``, door centre ``g_i`` and
    ``L_i = |g_i - s_i|``: ``progress = clip((p_i - s_i)·(g_i - s_i) / L_i^2, 0, 1)``
    (the position projected on the unit vector towards the door, in units of the
    route's length) and the closeness to the door, both times ``coefficient``. With
    ``closeness="linear"`` it is ``1 - clip(|p_i - g_i| / (10 sqrt 2), 0, 1)``; with
    ``"exponential"`` it is ``exp(-|p_i - g_i| / closeness_length)``. ``l = 4`` (drone
    0's pair, then drone 1's), values in ``[0, coefficient]``. A drone in the mouth of
    its own door has arrived: both its features are then ``coefficient``.

    Why the exponential shape exists: the linear one gives the top corner beside a door
    (progress clipped at 1, closeness 0.91) almost what the door gives, and an SAC policy
    pressed into that corner by a saturated action stays there. ``exp(-d / 1.5 m)`` gives
    the corner 0.43.

    Args:
        coefficient: the scale of the features, ``max_value``.
        closeness: ``"linear"`` (default) or ``"exponential"``.
        closeness_length: decay length in metres of the exponential closeness.
    """

    FEATURES = ("progress", "closeness")
    CLOSENESS = ("linear", "exponential")

    def __init__(self, coefficient: float = 1.0, closeness: str = "linear",
                 closeness_length: float = 1.5) -> None:
        super().__init__()
        self.coefficient = check_positive("coefficient", coefficient)
        if closeness not in self.CLOSENESS:
            raise ValueError(f"closeness must be one of {self.CLOSENESS}, got {closeness!r}.")
        self.closeness = closeness
        self.closeness_length = check_positive("closeness_length", closeness_length)
        self.max_value = self.coefficient
        self.names = [f"drone{i}/{f}" for i in range(N_DRONES) for f in self.FEATURES]
        starts = torch.tensor(NOMINAL_STARTS, dtype=torch.float64)
        doors = torch.from_numpy(door_centres())
        self.register_buffer("starts", starts, persistent=False)
        self.register_buffer("doors", doors, persistent=False)

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        pos = states[..., :2]
        s, g = self.starts.to(states.dtype), self.doors.to(states.dtype)
        axis = g - s  # [2, 2]
        progress = (((pos - s) * axis).sum(-1) / (axis * axis).sum(-1)).clamp(0.0, 1.0)
        dist = torch.linalg.vector_norm(pos - g, dim=-1)
        if self.closeness == "linear":
            closeness = 1.0 - (dist / (ROOM_SIZE * np.sqrt(2.0))).clamp(0.0, 1.0)
        else:
            closeness = torch.exp(-dist / self.closeness_length)
        # A drone in the mouth of its door has arrived: it is at its goal. Without this,
        # hovering just below the door earns (almost) what arriving earns, and an
        # entropy-regularised policy has no reason to go through.
        feats = torch.stack([progress, closeness], -1)
        feats = torch.where(in_own_door(pos)[..., None], 1.0, feats)
        return self.coefficient * feats.flatten(-2)

    def numpy_features(self, states: np.ndarray) -> np.ndarray:
        """``[..., 4]`` float64 :meth:`compute` of numpy joint states ``[..., 2, 4]``, equal
        bit for bit, ~1.5x faster on a planner's batches (no input checks). The distance
        to the door and the exponential stay torch's kernels, on tensors of the same
        layout: numpy's ``sqrt(dx² + dy²)`` differs from ``vector_norm`` in the last bit."""
        states = np.asarray(states, dtype=np.float64)
        pos = states[..., :2]
        x, y = pos[..., 0], pos[..., 1]  # [..., 2]: both drones
        s, g = self.starts.cpu().numpy(), self.doors.cpu().numpy()
        axis = g - s  # [2, 2]
        length2 = axis[:, 0] * axis[:, 0] + axis[:, 1] * axis[:, 1]
        progress = ((x - s[:, 0]) * axis[:, 0] + (y - s[:, 1]) * axis[:, 1]) / length2
        np.clip(progress, 0.0, 1.0, out=progress)
        dist = torch.linalg.vector_norm(torch.from_numpy(pos - g), dim=-1)
        if self.closeness == "linear":
            closeness = 1.0 - np.clip(dist.numpy() / (ROOM_SIZE * np.sqrt(2.0)), 0.0, 1.0)
        else:
            closeness = torch.exp(-dist / self.closeness_length).numpy()
        feats = np.where(in_own_door(pos)[..., None], 1.0,
                         np.stack([progress, closeness], -1))
        return self.coefficient * feats.reshape(*feats.shape[:-2], -1)


class FourierRewardBasis(DroneFeatureBasis):
    """A smooth reward basis: per drone ``(1 + cos(π (kx x + ky y) / 10)) / 2`` for
    ``kx, ky = 0..order``. ``l = 2 (order + 1)^2``, values in ``[0, 1]``.

    Args:
        order: highest frequency per axis.
    """

    def __init__(self, order: int = 2) -> None:
        super().__init__()
        order = check_int("order", order)
        self.order = order
        k = torch.arange(order + 1, dtype=torch.float64)
        ky, kx = torch.meshgrid(k, k, indexing="ij")
        self.register_buffer("freqs", torch.stack([kx.reshape(-1), ky.reshape(-1)], -1),
                             persistent=False)
        self.names = [f"drone{i}/cos({int(a)},{int(b)})" for i in range(N_DRONES)
                      for b in range(order + 1) for a in range(order + 1)]
        self.max_value = 1.0

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        pos = states[..., :2]
        arg = pos @ self.freqs.to(states.dtype).T * (np.pi / ROOM_SIZE)  # [..., 2, K]
        return (0.5 * (1.0 + torch.cos(arg))).flatten(-2)


__all__ = [
    "CellOccupancyCostBasis",
    "DoorLocationRewardBasis",
    "DroneFeatureBasis",
    "FourierRewardBasis",
    "RBFCostBasis",
]
