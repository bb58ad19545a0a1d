"""The multi-expert grid-world constrained Markov game as a PettingZoo ``ParallelEnv``
(docs/design.md §3).

Geometry, actions and true constraints come from :mod:`dicrl_torch.envs.grid`; this
module only adds the stochastic simulation, the ground-truth reward and rendering.

Ground-truth reward of expert ``i`` at cell ``s``::

    r_i(s) = w_i[0] * (1 - cheb(s, g_i) / (size - 1)) + w_i[1] * [s == g_i]

with default weights ``w_i = (1.0, 2.0)``: it grows as the goal gets closer and is
largest at the goal, so reaching the goal early and staying there earns the most.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from matplotlib import rcParams
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PatchCollection
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.patches import Rectangle

from dicrl_torch.envs.grid import ACTION_NAMES, N_ACTIONS, GridLayout
from dicrl_torch.envs.parallel import CheckedParallelEnv, figure_image

DEFAULT_REWARD_WEIGHTS: tuple[float, float] = (1.0, 2.0)

# Fixed per-expert colours (tab10 blue, orange, green) so plots of one expert match
# across figures.
EXPERT_COLOURS: tuple[str, ...] = ("#1f77b4", "#ff7f0e", "#2ca02c")


class GridWorldCMG(CheckedParallelEnv):
    """Multi-expert grid world; the true CMG or its nominal (unconstrained) game.

    Every agent observes the joint cells of all experts (cell index ``y * size + x``)
    and picks one of the 9 actions of :data:`dicrl_torch.envs.grid.ACTIONS`. Each
    expert's action succeeds with probability ``p_success`` and otherwise it stays;
    experts move simultaneously. Expert ``i`` is paid the reward of its *pre-step*
    cell (the learner's ``r(s_t, a_t)``, ``t = 0..T-1``).

    True constraints: a forbidden action (the expert then does not move in the
    constrained game), arriving on an obstacle, and — if
    ``layout.collision_constraint`` — arriving in the same cell as another active
    expert (both violate). ``infos[agent]["violation"]`` reports these in both games.
    With ``constrained=True`` a violator keeps that step's reward, is terminated and
    removed from ``agents`` and from the board (no later collision with it). With
    ``constrained=False`` nobody is stopped. All remaining agents are truncated after
    ``horizon`` steps.

    Args:
        layout: grid geometry, starts (each episode's drawn from P0 at reset, with the
            env's seeded stream, when ``layout.start_sets`` is given), goals and true
            constraints.
        horizon: number of steps ``T`` before truncation.
        p_success: probability that an action succeeds, in ``(0, 1]``.
        constrained: True for the true CMG, False for the nominal game.
        reward_weights: ``[N, 2]`` or ``[2]`` (shared) weights of the reward features
            ``(closeness, at_goal)``; default ``(1.0, 2.0)`` for every expert.
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "gridworld_cmg_v0",
                "is_parallelizable": True}

    def __init__(
        self,
        *,
        layout: GridLayout,
        horizon: int = 40,
        p_success: float = 0.8,
        constrained: bool = True,
        reward_weights: Sequence[float] | Sequence[Sequence[float]] | np.ndarray | None = None,
        render_mode: str | None = None,
    ) -> None:
        if not isinstance(layout, GridLayout):
            raise ValueError(
                f"layout must be a GridLayout, got {type(layout).__name__}; build one with "
                f"GridLayout(...) or GridLayout.scobee(n_experts)."
            )
        # bool is an int subclass: reject it so horizon=True is not read as 1.
        if not isinstance(horizon, int | np.integer) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}.")
        if not isinstance(p_success, int | float | np.floating) or not 0.0 < p_success <= 1.0:
            raise ValueError(f"p_success must be a probability in (0, 1], got {p_success!r}.")
        if not isinstance(constrained, bool | np.bool_):
            raise ValueError(
                f"constrained must be a bool (True: true CMG, False: nominal game), "
                f"got {constrained!r}."
            )
        self._check_render_mode(render_mode)
        self.layout = layout
        self.horizon = int(horizon)
        self.p_success = float(p_success)
        self.constrained = bool(constrained)
        self.render_mode = render_mode
        n = layout.n_experts
        self.reward_weights = _check_reward_weights(reward_weights, n)  # [N, 2]

        self.possible_agents = [f"expert_{i}" for i in range(n)]
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self._next_cell = layout.next_cell_table()  # [S1, A1]
        self._obstacle = layout.obstacle_mask()  # [S1]
        self._forbidden = layout.forbidden_action_mask()  # [A1]
        # [N, S1] ground-truth reward of each expert at each cell.
        self.reward_table = np.einsum("nsk,nk->ns", self.reward_features(), self.reward_weights)
        self.state_space = spaces.MultiDiscrete([layout.n_cells] * n, dtype=np.int64)

        self.agents: list[str] = []
        self.violated: dict[str, bool] = {}
        self.timestep = 0
        self._cells: np.ndarray | None = None
        self._rng: np.random.Generator | None = None

    # ---- spaces (cached per agent by CheckedParallelEnv) ----------------------------
    def _observation_space(self) -> spaces.MultiDiscrete:
        return spaces.MultiDiscrete([self.layout.n_cells] * self.layout.n_experts,
                                    dtype=np.int64)

    def _action_space(self) -> spaces.Discrete:
        return spaces.Discrete(N_ACTIONS)

    # ---- ground truth -------------------------------------------------------------
    def reward_features(self) -> np.ndarray:
        """``[N, S1, 2]`` float64 reward features ``(closeness, at_goal)`` per expert."""
        lay = self.layout
        closeness = 1.0 - lay.chebyshev_to_goal() / (lay.size - 1)
        at_goal = np.zeros((lay.n_experts, lay.n_cells))
        at_goal[np.arange(lay.n_experts), list(lay.goal_cells)] = 1.0
        return np.stack([closeness, at_goal], axis=-1)

    # ---- episode ------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._cells is not None

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        self.agents = list(self.possible_agents)
        self.violated = dict.fromkeys(self.possible_agents, False)
        self.timestep = 0
        self._cells = self._draw_start()
        obs = {a: self._cells.copy() for a in self.agents}
        infos = {a: {"violation": False, "cell": int(self._cells[self._index[a]])}
                 for a in self.agents}
        return obs, infos

    def _draw_start(self) -> np.ndarray:
        """``[N]`` int64 start cells drawn from P0 with the env's stream: each expert with
        several start cells (``layout.start_sets``) draws one uniformly, in expert order;
        the others draw nothing, so fixed starts leave the stream as it was."""
        cells = np.array(self.layout.start_cells, dtype=np.int64)
        for i, options in enumerate(self.layout.start_cell_sets):
            if len(options) > 1:
                cells[i] = options[int(self._rng.integers(len(options)))]
        return cells

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of :meth:`CheckedParallelEnv.step`; ``given`` holds an action in
        ``0..8`` (:data:`~dicrl_torch.envs.grid.ACTIONS`) for every live agent."""
        live = list(given)
        acts = {agent: self._check_action(agent, a) for agent, a in given.items()}
        pairs = [(a, self._index[a]) for a in live]

        # One draw per expert, in expert order, also for finished experts: the random
        # stream then depends on the seed only, so the true and nominal games and any
        # set of live experts see the same success draws.
        success = self._rng.random(self.layout.n_experts) < self.p_success
        old = self._cells
        new = old.copy()
        violation = {}
        for agent, i in pairs:
            a = acts[agent]
            forbidden = bool(self._forbidden[a])
            # In the true CMG a forbidden action is refused: the expert does not move.
            blocked = forbidden and self.constrained
            if success[i] and not blocked:
                new[i] = self._next_cell[old[i], a]
            violation[agent] = forbidden or bool(self._obstacle[new[i]])
        if self.layout.collision_constraint:
            # Only live experts are on the board: frozen bodies were removed.
            for agent, i in pairs:
                if any(k != i and new[k] == new[i] for _, k in pairs):
                    violation[agent] = True

        rewards = {a: float(self.reward_table[i, old[i]]) for a, i in pairs}
        self._cells = new
        self.timestep += 1
        terminations = {a: self.constrained and violation[a] for a in live}
        truncations = dict.fromkeys(live, self.timestep >= self.horizon)
        for a in live:
            self.violated[a] = self.violated[a] or violation[a]
        obs = {a: new.copy() for a in live}
        infos = {a: {"violation": violation[a], "cell": int(new[i])} for a, i in pairs}
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The joint cells ``[N]`` int64 (frozen experts at the cell where they stopped)."""
        self._require_started("state")
        return self._cells.copy()

    def _render(self) -> np.ndarray:
        lines = [f"{self.metadata['name']}  t={self.timestep}/{self.horizon}"
                 + ("" if self.constrained else "  (nominal)")]
        if self.layout.forbidden_actions:
            lines.append("forbidden actions: " + ", ".join(self.layout.forbidden_actions))
        stopped = [a for a, v in self.violated.items() if v]
        if stopped:
            lines.append("violated: " + ", ".join(stopped))
        cells = None if self._cells is None else self._cells.tolist()
        return render_grid(self.layout, cells=cells, title="\n".join(lines))

    # ---- helpers ------------------------------------------------------------------
    def _check_action(self, agent: str, a: Any) -> int:
        arr = np.asarray(a)
        if arr.ndim != 0 or not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"Action of {agent} must be an int in [0, {N_ACTIONS}), got {a!r}.")
        if not 0 <= int(a) < N_ACTIONS:
            raise ValueError(
                f"Action {int(a)} of {agent} is out of range; use 0..{N_ACTIONS - 1} "
                f"({', '.join(ACTION_NAMES)})."
            )
        return int(a)


def _check_reward_weights(weights: Any, n: int) -> np.ndarray:
    w = np.asarray(DEFAULT_REWARD_WEIGHTS if weights is None else weights, dtype=np.float64)
    if w.shape == (2,):
        w = np.tile(w, (n, 1))
    if w.shape != (n, 2):
        raise ValueError(
            f"reward_weights must have shape [2] (shared) or [{n}, 2] (one row per expert: "
            f"closeness, at_goal), got shape {list(w.shape)}."
        )
    if not np.all(np.isfinite(w)):
        raise ValueError(f"reward_weights must be finite, got {w.tolist()}.")
    return w


def render_grid(
    layout: GridLayout,
    *,
    cells: Sequence[int | None] | np.ndarray | None = None,
    heat: np.ndarray | None = None,
    constraint_cells: Iterable[int] | None = None,
    cell_colours: Mapping[int, str] | None = None,
    title: str = "",
) -> np.ndarray:
    """Draw the grid world and return it as an ``H x W x 3`` uint8 image.

    Obstacles are dark (hatched over a heat map); each expert's start is a circle and
    its goal a star in the expert's colour (with varied starts, small dots of that colour
    mark the expert's other start cells). Uses a private Agg canvas, never pyplot's
    global state, so it is safe in headless and threaded code.

    The picture is laid out by hand (:func:`_grid_frame`), not by ``tight_layout``; the
    cells' fills and the grid lines are one artist each and the cells' numbers plain
    texts, not ticks: a third of the time of the generic layout of many patches and
    ticks (half with a heat map, whose colour bar is the rest).

    Args:
        layout: the grid to draw.
        cells: current cell of each expert, drawn as filled numbered markers; an entry
            may be None to skip that expert.
        heat: ``[S1]`` values (e.g. a visitation frequency) shown as a colour map.
        constraint_cells: cell indices drawn as red crosses (e.g. learned constraints).
        cell_colours: cell index -> matplotlib colour; those cells are filled in it, under
            the markers, crosses and grid lines (an obstacle given a colour is filled in
            it instead of its dark grey, hatched over a heat map as usual).
        title: figure title, may span several lines.

    Returns:
        The RGB image.
    """
    G, S1 = layout.size, layout.n_cells
    if heat is not None:
        heat = np.asarray(heat, dtype=np.float64)
        if heat.shape != (S1,):
            raise ValueError(
                f"heat must have one value per cell, shape [{S1}], got {list(heat.shape)}."
            )
    colours = {} if cell_colours is None else {int(c): v for c, v in cell_colours.items()}
    bad = [c for c in colours if not 0 <= c < S1]
    if bad:
        raise ValueError(f"cell_colours {bad} lie outside 0..{S1 - 1}.")
    cc = None if constraint_cells is None else [int(c) for c in constraint_cells]
    if cc is not None:
        bad = [c for c in cc if not 0 <= c < S1]
        if bad:
            raise ValueError(f"constraint_cells {bad} lie outside 0..{S1 - 1}.")
    fig = Figure(figsize=(4.2 if heat is not None else 3.6, 4.0), dpi=80)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(-0.5, G - 0.5)
    ax.set_ylim(G - 0.5, -0.5)  # row 0 at the top, as in docs/design.md §3
    # No axis machinery: the cells' numbers are plain texts (_grid_frame), the grid lines
    # one collection.
    ax.xaxis.set_visible(False)
    ax.yaxis.set_visible(False)
    cax = None
    if heat is not None:
        im = ax.imshow(heat.reshape(G, G), cmap="viridis", origin="upper",
                       extent=(-0.5, G - 0.5, G - 0.5, -0.5), interpolation="nearest")
        cax = fig.add_axes((0.0, 0.0, 0.05, 1.0))
        fig.colorbar(im, cax=cax)
    # Cells in a given colour: over a heat map (zorder 0), under the grid lines (1.5) and
    # everything else.
    if colours:
        ax.add_collection(PatchCollection(
            [Rectangle((c % G - 0.5, c // G - 0.5), 1, 1) for c in colours],
            facecolors=list(colours.values()), edgecolors="none", linewidths=0, zorder=1))
    # Over a heat map obstacles are hatched, not filled, so their values stay visible;
    # one given a colour is filled in it above.
    walls = [(x, y) for x, y in layout.obstacles
             if heat is not None or layout.cell((x, y)) not in colours]
    if walls:
        style = ({"facecolors": "none", "edgecolors": "0.15", "hatch": "///", "linewidths": 0}
                 if heat is not None else {"facecolors": "0.2", "edgecolors": "0.2",
                                           "linewidths": rcParams["patch.linewidth"]})
        ax.add_collection(PatchCollection(
            [Rectangle((x - 0.5, y - 0.5), 1, 1) for x, y in walls], zorder=2, **style))
    lines = np.arange(G + 1) - 0.5
    ax.add_collection(LineCollection(
        [[(k, -0.5), (k, G - 0.5)] for k in lines] + [[(-0.5, k), (G - 0.5, k)] for k in lines],
        colors="0.6", linewidths=0.6, zorder=1.5))  # the grid, where minor ticks drew it
    for i, ((sx, sy), (gx, gy)) in enumerate(zip(layout.starts, layout.goals, strict=True)):
        c = EXPERT_COLOURS[i % len(EXPERT_COLOURS)]
        if layout.start_sets is not None and len(layout.start_sets[i]) > 1:
            # varied starts: the cells P0 spreads the expert's start over, as small dots
            xs, ys = zip(*layout.start_sets[i], strict=True)
            ax.plot(xs, ys, ".", ms=5, color=c, alpha=0.6, zorder=3)
        ax.plot(sx, sy, "o", ms=14, mfc="none", mec=c, mew=2, zorder=3)
        ax.plot(gx, gy, "*", ms=15, color=c, zorder=3)
    if cc:
        ax.plot([c % G for c in cc], [c // G for c in cc], "x", ms=11, mew=2.5,
                color="red", zorder=4)
    if cells is not None:
        for i, c in enumerate(cells):
            if c is None:
                continue
            x, y = layout.xy(int(c))
            ax.plot(x, y, "o", ms=10, color=EXPERT_COLOURS[i % len(EXPERT_COLOURS)], mec="k",
                    zorder=5)
            ax.text(x, y, str(i), ha="center", va="center", fontsize=7, color="w", zorder=6)
    _grid_frame(ax, cax, G, title)
    return figure_image(fig)


# Font sizes (points) of render_grid's title and tick labels, and the spacing matplotlib
# gives them: tight_layout's padding (1.08 font sizes of 10 pt) around the picture, the
# title's pad above the axes, the tick labels' pad beside them.
_TITLE_PT, _TICK_PT = 8, 7
_PAD_PT, _TITLE_PAD_PT, _TICK_PAD_PT = 10.8, 6.0, 3.5
# The colour bar as fig.colorbar(ax=...) placed it: 0.04 of the grid's side away, 1/20
# of it wide.
_CBAR_GAP, _CBAR_WIDTH = 0.04, 0.05


def _grid_frame(ax, cax, G: int, title: str) -> None:
    """Place render_grid's square axes, its colour bar ``cax`` (or None) and its title
    as ``tight_layout`` and ``set_title`` would: the grid as large as the figure allows
    after the padding, the tick labels, the colour bar and its labels, and the title
    above it; centred, the colour bar beside the grid. Measures only the title, the
    labels of the colour bar and one tick label per width, where ``tight_layout`` lays
    out every artist of the figure twice."""
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height  # pixels
    pt = fig.dpi / 72.0
    pad, tick_pad = _PAD_PT * pt, _TICK_PAD_PT * pt
    font = FontProperties(size=_TICK_PT)
    widths = {}
    for k in range(G):
        n = len(str(k))
        if n not in widths:  # digits are equally wide: one label per length
            widths[n] = renderer.get_text_width_height_descent(str(k), font, ismath=False)[0]
    label_w = max(widths.values())
    label_h = renderer.get_text_width_height_descent("0123456789", font, ismath=False)[1]
    left, bottom = pad + label_w + tick_pad, pad + label_h + tick_pad
    text = None
    top = pad
    if title:
        text = fig.text(0.5, 0.0, title, ha="center", va="baseline", fontsize=_TITLE_PT)
        top += text.get_window_extent(renderer).y1 + _TITLE_PAD_PT * pt

    def place(right: float) -> tuple[float, float, float]:
        """The grid's square ``(x0, y0, side)`` in pixels, and the colour bar beside it,
        with ``right`` pixels kept right of everything (of the colour bar if any)."""
        share = 1.0 + (_CBAR_GAP + _CBAR_WIDTH if cax is not None else 0.0)
        room_w, room_h = (W - left - right) / share, H - bottom - top
        side = max(1.0, min(room_w, room_h))
        x0 = left + (room_w - side) * (0.5 if cax is None else 1.0)
        y0 = bottom + (room_h - side) / 2
        ax.set_position((x0 / W, y0 / H, side / W, side / H))
        if cax is not None:
            cax.set_position(((x0 + side * (1.0 + _CBAR_GAP)) / W, y0 / H,
                              side * _CBAR_WIDTH / W, side / H))
        return x0, y0, side

    x0, y0, side = place(pad)
    if cax is not None:  # room for its ticks and labels, as many as it has at this height
        labels = [label.get_window_extent(renderer).width
                  for label in cax.yaxis.get_ticklabels(which="major") if label.get_text()]
        x0, y0, side = place(pad + max(labels, default=0.0) + pt * (
            rcParams["ytick.major.size"] + rcParams["ytick.major.pad"]))
    if text is not None:
        text.set_position(((x0 + side / 2) / W, (y0 + side + _TITLE_PAD_PT * pt) / H))
    # The cells' numbers where the axes' tick labels were: below and left of the grid.
    pitch = side / G
    for k in range(G):
        fig.text((x0 + (k + 0.5) * pitch) / W, (y0 - tick_pad) / H, str(k), ha="center",
                 va="top", fontsize=_TICK_PT)
        fig.text((x0 - tick_pad) / W, (y0 + side - (k + 0.5) * pitch) / H, str(k),
                 ha="right", va="center_baseline", fontsize=_TICK_PT)
