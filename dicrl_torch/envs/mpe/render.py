"""The picture of a constrained spread game (:mod:`dicrl_torch.envs.mpe`): the arena, the
start region, the disc, the landmarks, trajectories and agents, and optionally a set of
(learned) constraint cells, on a private Agg canvas; the env's ``render`` and the runs'
figures both draw with it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.patches import Circle, Rectangle

from dicrl_torch.envs.mpe.layout import SUCCESS_RADIUS, SpreadLayout
from dicrl_torch.envs.parallel import agg_axes, axes_image

_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def render_spread(layout: SpreadLayout, *, trajectories: Sequence[np.ndarray] | None = None,
                  positions: np.ndarray | None = None, frozen: np.ndarray | None = None,
                  cells: np.ndarray | None = None, title: str = "") -> np.ndarray:
    """Draw the game as an ``H x W x 3`` uint8 image on a private Agg canvas.

    Args:
        layout: the geometry (arena, start region, disc, landmarks).
        trajectories: arrays ``[T, N, 2]`` of positions.
        cells: ``[K, 4]`` rectangles ``(x0, y0, x1, y1)`` shaded and hatched in red (e.g.
            a learned constraint set, ``PositionCellBasis.cell_rectangles()[mask]``).
        positions: ``[N, 2]`` current positions, drawn as discs of radius
            ``min_distance / 2`` (they touch exactly at the distance limit).
        frozen: ``[N]`` bool, agents drawn with a black cross.
        title: figure title.
    """
    ax = agg_axes((4.0, 4.0))
    h = layout.arena_half_width
    for x0, y0, x1, y1 in (() if cells is None else np.asarray(cells)):
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="red", alpha=0.25, lw=0,
                               zorder=2))
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, hatch="xx",
                               ec="red", lw=0, zorder=2))
    x0, y0, x1, y1 = layout.start_region
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ls="--", ec="0.5"))
    ax.add_patch(Circle(layout.disc_centre, layout.disc_radius, color="0.35", zorder=1))
    for lm in layout.landmarks:
        ax.add_patch(Circle(lm, SUCCESS_RADIUS, fill=False, ec="k", zorder=3))
        ax.plot(*lm, "kx", ms=6, zorder=3)
    for traj in trajectories or []:
        for i in range(traj.shape[1]):
            ax.plot(traj[:, i, 0], traj[:, i, 1], color=_COLOURS[i % 6], lw=1, zorder=4)
    if positions is not None:
        for i, p in enumerate(np.asarray(positions)):
            ax.add_patch(Circle(tuple(p), max(layout.min_distance / 2, 0.05),
                                color=_COLOURS[i % 6], alpha=0.7, ec="k", zorder=5))
            if frozen is not None and bool(frozen[i]):
                ax.plot(*p, "x", color="k", ms=9, mew=2, zorder=6)
    ax.set_xlim(-h, h)
    ax.set_ylim(-h, h)
    ax.tick_params(labelsize=6)
    return axes_image(ax, title)
