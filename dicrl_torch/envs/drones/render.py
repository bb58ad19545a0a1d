"""The picture of the drone arena (:mod:`dicrl_torch.envs.drones`): walls, doors,
obstacle, starts, trajectories, drones and (learned) constraint cells, on a private Agg
canvas; the env's ``render`` and the runs' figures both draw with it."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.patches import Circle, Rectangle

from dicrl_torch.envs.drones.geometry import (
    CELL_SIZE,
    DOORS,
    GRID_CELLS,
    N_DRONES,
    NOMINAL_STARTS,
    OBSTACLES,
    PROXIMITY_RADIUS,
    ROOM_SIZE,
)
from dicrl_torch.envs.parallel import agg_axes, axes_image

# Per-drone colours (tab10 blue, orange), as in the grid world's plots.
DRONE_COLOURS: tuple[str, ...] = ("#1f77b4", "#ff7f0e")


def constraint_cell_mask(cells: Any) -> np.ndarray:
    """Normalise a set of constraint cells to a ``[N, GRID_CELLS**2]`` bool mask.

    Args:
        cells: one of: an iterable of cell indices ``iy * GRID_CELLS + ix`` (shared by
            both drones); a bool array ``[GRID_CELLS**2]`` (shared), ``[N,
            GRID_CELLS**2]`` (per drone), or ``[N * GRID_CELLS**2 + 1]`` (a
            :class:`~dicrl_torch.features.drone.CellOccupancyCostBasis` constraint mask;
            its proximity entry is ignored).

    Returns:
        ``[N, GRID_CELLS**2]`` bool.
    """
    n = GRID_CELLS**2
    if isinstance(cells, torch.Tensor):
        cells = cells.detach().cpu().numpy()
    arr = np.asarray(cells) if isinstance(cells, np.ndarray) else None
    if arr is not None and arr.dtype == np.bool_:
        if arr.shape == (n,):
            return np.tile(arr, (N_DRONES, 1))
        if arr.shape == (N_DRONES, n):
            return arr.copy()
        if arr.shape == (N_DRONES * n + 1,):
            return arr[:-1].reshape(N_DRONES, n).copy()
        raise ValueError(
            f"A boolean constraint mask must have shape [{n}], [{N_DRONES}, {n}] or "
            f"[{N_DRONES * n + 1}], got {list(arr.shape)}."
        )
    if not isinstance(cells, Iterable):
        raise ValueError(
            f"cells must be cell indices or a boolean mask, got {type(cells).__name__}."
        )
    idx = [c for c in cells]
    bad = [c for c in idx if isinstance(c, bool) or not isinstance(c, int | np.integer)
           or not 0 <= c < n]
    if bad:
        raise ValueError(
            f"Constraint cells must be ints in [0, {n}) (index iy * {GRID_CELLS} + ix), "
            f"got {bad[:5]}."
        )
    mask = np.zeros((N_DRONES, n), dtype=bool)
    mask[:, [int(c) for c in idx]] = True
    return mask


def render_arena(
    *,
    trajectories: Sequence[np.ndarray] | None = None,
    positions: np.ndarray | None = None,
    frozen: np.ndarray | None = None,
    constraint_cells: Any = None,
    proximity_radius: float = PROXIMITY_RADIUS,
    title: str = "",
) -> np.ndarray:
    """Draw the arena and return it as an ``H x W x 3`` uint8 image (320 x 320).

    Walls are black with each door a thick segment in its drone's colour, obstacles dark
    grey, constraint cells shaded in the drone's colour (both drones: red). Uses a
    private Agg canvas, never pyplot's global state.

    Args:
        trajectories: arrays ``[T, N, 2]`` of positions, e.g. one per demonstrated pair.
        positions: ``[N, 2]`` current positions, drawn as discs of radius
            ``proximity_radius / 2`` (they touch exactly at a collision).
        frozen: ``[N]`` bool, drones drawn with a black cross (frozen by a violation).
        constraint_cells: see :func:`constraint_cell_mask`; None draws none.
        proximity_radius: collision distance in metres.
        title: figure title.

    Returns:
        The RGB image.
    """
    ax = agg_axes((4.0, 4.0))
    if constraint_cells is not None:
        mask = constraint_cell_mask(constraint_cells)
        both = mask.all(0)
        for c in range(GRID_CELLS**2):
            if not mask[:, c].any():
                continue
            colour = "red" if both[c] else DRONE_COLOURS[int(np.argmax(mask[:, c]))]
            ix, iy = c % GRID_CELLS, c // GRID_CELLS
            corner = (ix * CELL_SIZE, iy * CELL_SIZE)
            # Shaded and hatched above the obstacles, so a learned constraint on an
            # obstacle cell (the hoped-for result) stays visible.
            ax.add_patch(Rectangle(corner, CELL_SIZE, CELL_SIZE, color=colour, alpha=0.35,
                                   lw=0, zorder=2))
            ax.add_patch(Rectangle(corner, CELL_SIZE, CELL_SIZE, fill=False, hatch="xx",
                                   ec=colour, lw=0, zorder=2))
    for x0, y0, x1, y1 in OBSTACLES:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.35", zorder=1))
    # Walls, with the doors cut out of the top wall and drawn in the drones' colours.
    ax.plot([0, 0, ROOM_SIZE, ROOM_SIZE], [ROOM_SIZE, 0, 0, ROOM_SIZE], color="k", lw=2)
    edges = sorted([0.0, ROOM_SIZE] + [v for d in DOORS for v in d])
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        ax.plot([a, b], [ROOM_SIZE, ROOM_SIZE], color="k", lw=2)
    for i, (a, b) in enumerate(DOORS):
        ax.plot([a, b], [ROOM_SIZE, ROOM_SIZE], color=DRONE_COLOURS[i], lw=5, zorder=3)
    for i, (sx, sy) in enumerate(NOMINAL_STARTS):
        ax.plot(sx, sy, "o", ms=12, mfc="none", mec=DRONE_COLOURS[i], mew=1.5, zorder=3)
    for traj in trajectories or []:
        t = np.asarray(traj, dtype=np.float64)
        if t.ndim != 3 or t.shape[1:] != (N_DRONES, 2):
            raise ValueError(
                f"Each trajectory must have shape [T, {N_DRONES}, 2], got {list(t.shape)}."
            )
        for i in range(N_DRONES):
            ax.plot(t[:, i, 0], t[:, i, 1], color=DRONE_COLOURS[i], lw=1.0, alpha=0.8,
                    zorder=4)
    if positions is not None:
        p = np.asarray(positions, dtype=np.float64)
        if p.shape != (N_DRONES, 2):
            raise ValueError(f"positions must have shape [{N_DRONES}, 2], got {list(p.shape)}.")
        for i in range(N_DRONES):
            ax.add_patch(Circle(tuple(p[i]), proximity_radius / 2, color=DRONE_COLOURS[i],
                                ec="k", zorder=5))
            if frozen is not None and bool(np.asarray(frozen)[i]):
                ax.plot(*p[i], "x", color="k", ms=9, mew=2, zorder=6)
    ax.set_xlim(-0.3, ROOM_SIZE + 0.3)
    ax.set_ylim(-0.3, ROOM_SIZE + 0.3)
    ticks = np.arange(GRID_CELLS + 1) * CELL_SIZE
    ax.set_xticks(ticks)
    ax.set_yticks(ticks)
    ax.grid(color="0.85", lw=0.5)
    ax.tick_params(length=0, labelsize=6)
    return axes_image(ax, title)
