"""The drone arena's geometry (:mod:`dicrl_torch.envs.drones`): the room, the grid of
cells, the obstacle, the doors, the starts and P0's support, and the true constraints'
tests on positions (obstacle, own door, outside the room, too close).

Everything here is a constant or a pure, batched function of positions (numpy or torch),
shared by the dynamics, the env, the feature bases and the demonstrations' planner.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dicrl_torch.envs.drones.arrays import const_like

__all__ = [
    "AGENTS", "CELL_SIZE", "DOORS", "DOOR_DEPTH", "GRID_CELLS", "NOMINAL_STARTS", "N_DRONES",
    "OBSTACLES", "PROXIMITY_RADIUS", "ROOM_SIZE", "START_JITTER", "door_centres",
    "in_obstacle", "in_own_door", "obstacle_cell_mask", "outside_room", "start_support",
    "too_close",
]

# ---------------------------------------------------------------------------- layout
ROOM_SIZE: float = 10.0
"""Side of the square room in metres; the room is ``[0, ROOM_SIZE]^2``."""
GRID_CELLS: int = 10
"""Cells per side of the occupancy grid (1 m cells); cell ``(ix, iy)`` has index
``iy * GRID_CELLS + ix`` (row 0 at the bottom)."""
CELL_SIZE: float = ROOM_SIZE / GRID_CELLS

OBSTACLES: tuple[tuple[float, float, float, float], ...] = (
    (4.0, 5.0, 6.0, 6.0),  # the central block, where the straight routes cross
)
"""Axis-aligned obstacle boxes ``(x_lo, y_lo, x_hi, y_hi)``; a drone inside one violates."""

DOORS: tuple[tuple[float, float], ...] = ((8.0, 9.5), (0.5, 2.0))
"""Per drone, the ``(x_lo, x_hi)`` span of its door in the top wall ``y = ROOM_SIZE``."""
DOOR_DEPTH: float = 0.3
"""A drone with ``y >= ROOM_SIZE - DOOR_DEPTH`` inside its door's span has reached it.
It is deeper than one step of travel (``dt * vel_limit = 0.15`` m by default), so no
drone can cross the wall at its door without first being counted as arrived."""

NOMINAL_STARTS: tuple[tuple[float, float], ...] = ((1.0, 1.0), (9.0, 1.0))
"""Per drone, the nominal start; ``reset`` adds uniform jitter of ``±START_JITTER``."""
START_JITTER: float = 0.25


def start_support(points_per_axis: int = 5) -> np.ndarray:
    """Joint start states spanning the support of P0: every combination of the drones'
    positions on a ``points_per_axis``² grid over their jitter boxes (corners included),
    at rest. Enough to find every feature that P0 gives mass to for features constant on
    cells (a cell the box touches holds a grid point); ``[P, N_DRONES, 4]``."""
    offsets = np.linspace(-START_JITTER, START_JITTER, points_per_axis)
    box = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), -1).reshape(-1, 2)  # [k, 2]
    per_drone = [np.asarray(start) + box for start in NOMINAL_STARTS]
    grids = np.meshgrid(*[np.arange(len(box))] * N_DRONES, indexing="ij")
    combos = np.stack([g.ravel() for g in grids], -1)  # [P, N_DRONES]
    pos = np.stack([per_drone[i][combos[:, i]] for i in range(N_DRONES)], 1)
    return np.concatenate([pos, np.zeros_like(pos)], -1)


PROXIMITY_RADIUS: float = 0.5
"""Two active drones closer than this (metres) collide."""

AGENTS: tuple[str, ...] = ("drone_0", "drone_1")
N_DRONES: int = len(AGENTS)

_OBSTACLE_ARRAY = np.asarray(OBSTACLES, dtype=np.float64)  # [K, 4]
_DOOR_ARRAY = np.asarray(DOORS, dtype=np.float64)  # [N, 2]


def door_centres() -> np.ndarray:
    """``[N, 2]`` float64: the centre of each drone's door (on the top wall)."""
    return np.stack([_DOOR_ARRAY.mean(1), np.full(N_DRONES, ROOM_SIZE)], axis=1)


def obstacle_cell_mask() -> np.ndarray:
    """``[GRID_CELLS**2]`` bool: cells overlapping an obstacle with positive area."""
    ix, iy = np.meshgrid(np.arange(GRID_CELLS), np.arange(GRID_CELLS), indexing="xy")
    x0, y0 = ix.ravel() * CELL_SIZE, iy.ravel() * CELL_SIZE  # index iy * G + ix
    o = _OBSTACLE_ARRAY
    hit = ((x0[:, None] < o[:, 2]) & (x0[:, None] + CELL_SIZE > o[:, 0])
           & (y0[:, None] < o[:, 3]) & (y0[:, None] + CELL_SIZE > o[:, 1]))
    return hit.any(1)


# ----------------------------------------------------------------- constraint checks
def in_obstacle(pos: Any) -> Any:
    """Whether positions lie in an obstacle box (closed boxes).

    Args:
        pos: ``[..., 2]`` positions ``(x, y)``, numpy or torch.

    Returns:
        ``[...]`` bool of the same array type.
    """
    o = const_like(_OBSTACLE_ARRAY, pos)
    x, y = pos[..., 0:1], pos[..., 1:2]  # [..., 1] against [K]
    return ((x >= o[:, 0]) & (x <= o[:, 2]) & (y >= o[:, 1]) & (y <= o[:, 3])).any(-1)


def in_own_door(pos: Any) -> Any:
    """Whether each drone is in the mouth of its own door.

    Args:
        pos: ``[..., N, 2]`` positions of the ``N = 2`` drones.

    Returns:
        ``[..., N]`` bool.
    """
    d = const_like(_DOOR_ARRAY, pos)
    x, y = pos[..., 0], pos[..., 1]
    return (x >= d[:, 0]) & (x <= d[:, 1]) & (y >= ROOM_SIZE - DOOR_DEPTH)


def outside_room(pos: Any) -> Any:
    """``[...]`` bool: positions ``[..., 2]`` outside the room ``[0, ROOM_SIZE]^2``."""
    return ((pos < 0.0) | (pos > ROOM_SIZE)).any(-1)


def too_close(pos: Any, radius: float = PROXIMITY_RADIUS) -> Any:
    """``[...]`` bool: the two drones of ``pos [..., 2, 2]`` are closer than ``radius``."""
    diff = pos[..., 0, :] - pos[..., 1, :]
    return (diff * diff).sum(-1) < radius * radius
