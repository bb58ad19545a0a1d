"""The multi-expert grid world: layout, actions, true constraints and the learner's
tabular model (docs/design.md §3).

Coordinates are ``(x, y)`` with ``x`` the column (left → right) and ``y`` the row
(top → bottom). A cell's index is ``y * size + x``. A joint state of ``N`` experts is
the tuple of their cell indices; flattened, expert 1 is the most significant digit,
so a joint value tensor has shape ``[S1] * N`` (``S1 = size**2``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from dicrl_torch.checks import InvalidSetting, is_int, setting_int, setting_number

# (name, dx, dy); "N" is up, i.e. towards y = 0.
ACTIONS: tuple[tuple[str, int, int], ...] = (
    ("stay", 0, 0),
    ("N", 0, -1),
    ("S", 0, 1),
    ("E", 1, 0),
    ("W", -1, 0),
    ("NE", 1, -1),
    ("NW", -1, -1),
    ("SE", 1, 1),
    ("SW", -1, 1),
)
ACTION_NAMES: tuple[str, ...] = tuple(a[0] for a in ACTIONS)
N_ACTIONS = len(ACTIONS)

# Scobee & Sastry's 9x9 layout (docs/design.md §3): a chevron plus the column x = 4 with a
# two-cell gap at (4,3),(4,4).
SCOBEE_OBSTACLES: tuple[tuple[int, int], ...] = (
    (2, 3), (3, 4), (4, 5), (5, 4), (6, 3),
    (4, 0), (4, 1), (4, 2), (4, 6), (4, 7), (4, 8),
)
# Scobee & Sastry paint the two halves of that wall (their "blue" and "green" states); a
# cost basis may give each colour one feature (RegionIndicatorCostBasis).
SCOBEE_REGIONS: tuple[tuple[str, tuple[tuple[int, int], ...]], ...] = (
    ("blue", ((4, 0), (4, 1), (4, 2))),
    ("green", ((4, 6), (4, 7), (4, 8))),
)
SCOBEE_STARTS: tuple[tuple[int, int], ...] = ((0, 8), (8, 0), (0, 3))
SCOBEE_GOALS: tuple[tuple[int, int], ...] = ((8, 8), (0, 0), (8, 3))
SCOBEE_FORBIDDEN_ACTIONS: tuple[str, ...] = ("NE", "NW")
# The varied-start protocol's rectangles (x0, y0, x1, y1), corners included, one per expert,
# by number of experts (docs/design.md §3). Each expert starts uniformly in the free cells
# of its rectangle: with 2 experts, expert 1 anywhere left of the wall and expert 2 anywhere
# right of it; with 3, expert 1 keeps the bottom-left block and expert 3 the top-left one
# (the sets must be disjoint). Measured (experiments/studies/identifiability.py --varied: 100
# demonstrations of optimal experts, seed 0, shared basis): all 14 true constraints are
# required, with 2 experts and with 3, where fixed starts leave 8 and 4 undetermined.
SCOBEE_START_REGIONS: dict[int, tuple[tuple[int, int, int, int], ...]] = {
    1: ((0, 0, 3, 8),),
    2: ((0, 0, 3, 8), (5, 0, 8, 8)),
    3: ((0, 5, 3, 8), (5, 0, 8, 8), (0, 0, 3, 4)),
}


@dataclass(frozen=True)
class GridLayout:
    """Geometry and true constraints of a square grid world.

    Args:
        size: side ``G`` of the ``G x G`` grid.
        starts: start cell ``(x, y)`` of each expert.
        goals: goal cell ``(x, y)`` of each expert.
        obstacles: cells that are a state constraint for every expert.
        forbidden_actions: action names forbidden to every expert.
        collision_constraint: whether two experts in one cell is a violation.
        regions: named groups of cells, ``((name, ((x, y), ...)), ...)``, such as
            Scobee's wall colours. Not constraints in themselves: they are what a
            region cost basis may give one feature each.
        start_sets: None (fixed starts: P0 is a point mass on ``starts``), or one tuple
            of ``(x, y)`` cells per expert: the varied-start protocol of docs/design.md
            §3, where P0 is the product of independent uniform distributions, expert
            ``i`` starting uniformly in ``start_sets[i]``. Each expert's ``starts`` entry
            must lie in its set: it stays the *nominal* start (drawn in figures). The
            sets must be disjoint (two experts in one cell is a collision) and avoid
            obstacles. :meth:`with_start_regions` builds them from rectangles.
    """

    size: int
    starts: tuple[tuple[int, int], ...]
    goals: tuple[tuple[int, int], ...]
    obstacles: tuple[tuple[int, int], ...] = ()
    forbidden_actions: tuple[str, ...] = ()
    collision_constraint: bool = True
    regions: tuple[tuple[str, tuple[tuple[int, int], ...]], ...] = ()
    start_sets: tuple[tuple[tuple[int, int], ...], ...] | None = None
    name: str = field(default="custom", compare=False)

    def __post_init__(self) -> None:
        setting_int("size", self.size, least=2, example=9, why="the grid's side")
        if len(self.starts) != len(self.goals) or not 1 <= len(self.starts) <= 3:
            raise ValueError(
                f"GridLayout needs 1 to 3 experts with one start and one goal each; got "
                f"{len(self.starts)} starts and {len(self.goals)} goals."
            )
        for what, cells in (("start", self.starts), ("goal", self.goals),
                            ("obstacle", self.obstacles)):
            for x, y in cells:
                if not (0 <= x < self.size and 0 <= y < self.size):
                    raise ValueError(
                        f"{what} cell {(x, y)} lies outside the {self.size}x{self.size} grid."
                    )
        for cells, what in ((self.starts, "starts"), (self.goals, "goals")):
            if len(set(cells)) != len(cells):
                raise ValueError(f"Two experts share a cell in {what} {cells}; give each its own.")
            bad = set(cells) & set(self.obstacles)
            if bad:
                raise ValueError(f"{what} {sorted(bad)} lie on obstacles; move them.")
        check_regions(self.regions, self.size)
        if self.start_sets is not None:
            # normalised to tuples of (int, int) pairs: a config passes lists
            object.__setattr__(self, "start_sets", self._checked_start_sets(self.start_sets))
        unknown = set(self.forbidden_actions) - set(ACTION_NAMES)
        if unknown:
            raise ValueError(
                f"Unknown forbidden action(s) {sorted(unknown)}; choose from {ACTION_NAMES}."
            )

    def _checked_start_sets(self, sets) -> tuple[tuple[tuple[int, int], ...], ...]:
        """``sets`` (one collection of ``(x, y)`` cells per expert) as tuples, checked.

        Raises:
            ValueError: naming the expert, the cells at fault and the fix.
        """
        try:
            sets = [[(int(x), int(y)) for x, y in cells] for cells in sets]
        except (TypeError, ValueError):
            raise ValueError(f"start_sets must hold one list of (x, y) cells per expert, got "
                             f"{sets!r}; e.g. [[[0, 8], [1, 8]], [[8, 0]]].") from None
        if len(sets) != self.n_experts:
            raise ValueError(f"start_sets gives {len(sets)} start set(s) for "
                             f"{self.n_experts} expert(s); give one per expert.")
        obstacles = set(self.obstacles)
        owner: dict[tuple[int, int], int] = {}
        for i, cells in enumerate(sets):
            who = f"expert {i + 1}'s start set"
            if not cells:
                raise ValueError(f"{who} is empty; give it at least its start "
                                 f"{self.starts[i]}.")
            off = [c for c in cells if not (0 <= c[0] < self.size and 0 <= c[1] < self.size)]
            if off:
                raise ValueError(f"{who}: cells {off} lie outside the {self.size}x{self.size} "
                                 f"grid; remove them.")
            blocked = sorted(set(cells) & obstacles)
            if blocked:
                raise ValueError(f"{who}: cells {blocked} are obstacles (a true constraint: "
                                 f"an expert cannot start there); remove them.")
            for c in cells:
                if owner.get(c, i) != i:
                    raise ValueError(
                        f"cell {c} is in the start sets of experts {owner[c] + 1} and "
                        f"{i + 1}; two experts in one cell is a collision (a true "
                        f"constraint), so the sets must be disjoint: remove it from one.")
                owner[c] = i
            if tuple(self.starts[i]) not in cells:
                raise ValueError(f"expert {i + 1}'s start {tuple(self.starts[i])} is not in its "
                                 f"start set {sorted(set(cells))}; add it (it is the nominal "
                                 f"start, drawn in figures) or move the start into the set.")
        # sorted and without repeats: P0 is uniform over the set, not over a list
        return tuple(tuple(sorted(set(cells), key=self.cell)) for cells in sets)

    # ---- constructors -------------------------------------------------------------
    @classmethod
    def scobee(cls, n_experts: int = 3, start_regions=None) -> GridLayout:
        """The paper's 9x9 layout with the first ``n_experts`` experts of docs/design.md §3.

        Args:
            start_regions: None (fixed starts, the paper's protocol) or rectangles
                ``(x0, y0, x1, y1)``, one per expert in table order (extra ones beyond
                ``n_experts`` are unused): each expert starts uniformly in the free cells
                of its rectangle (see :meth:`with_start_regions`).
        """
        _check_n_experts(n_experts)
        layout = cls(
            size=9,
            starts=SCOBEE_STARTS[:n_experts],
            goals=SCOBEE_GOALS[:n_experts],
            obstacles=SCOBEE_OBSTACLES,
            forbidden_actions=SCOBEE_FORBIDDEN_ACTIONS,
            regions=SCOBEE_REGIONS,
            name=f"scobee{n_experts}",
        )
        return layout if start_regions is None else layout.with_start_regions(start_regions)

    @classmethod
    def scobee_varied(cls, n_experts: int = 3, start_regions=None) -> GridLayout:
        """The paper's layout under the varied-start protocol (docs/design.md §3): expert
        ``i`` starts uniformly in the free cells of ``start_regions[i]`` (rectangles
        ``(x0, y0, x1, y1)``, see :meth:`with_start_regions`); None takes
        :data:`SCOBEE_START_REGIONS` for ``n_experts``. Its ``starts`` stay Scobee's (the
        nominal starts, drawn in figures)."""
        _check_n_experts(n_experts)
        regions = SCOBEE_START_REGIONS[n_experts] if start_regions is None else start_regions
        return replace(cls.scobee(n_experts, start_regions=regions),
                       name=f"scobee{n_experts}_varied")

    @classmethod
    def open_grid(cls, size: int, n_experts: int, start_regions=None) -> GridLayout:
        """A nominal ``size x size`` grid without obstacles, for scaling studies and
        tiny brute-force tests. Experts start in corners and aim for the opposite one;
        ``start_regions`` as in :meth:`scobee`."""
        _check_n_experts(n_experts)
        g = size - 1
        starts = ((0, g), (g, 0), (0, 0))[:n_experts]
        goals = ((g, g), (0, 0), (g, g))[:n_experts]
        if n_experts == 3:  # expert 3 goes top-left -> bottom-left so goals stay distinct
            goals = ((g, g), (0, 0), (0, g))
        layout = cls(size=size, starts=starts, goals=goals, name=f"open{size}")
        return layout if start_regions is None else layout.with_start_regions(start_regions)

    def with_start_regions(self, regions) -> GridLayout:
        """This layout with varied starts: expert ``i`` starts uniformly in the free
        (non-obstacle) cells of the rectangle ``regions[i] = (x0, y0, x1, y1)``, corners
        included (``x0 <= x1``, ``y0 <= y1``). Rectangles beyond the number of experts are
        unused, so that one list serves ``n_experts`` = 1, 2, 3 as the starts' table does.
        Each rectangle must contain its expert's start (the nominal one), and the
        rectangles' free cells must not overlap.

        Raises:
            ValueError: naming the rectangle at fault and the fix.
        """
        try:
            rects = [tuple(int(v) for v in r) for r in regions]
        except (TypeError, ValueError):
            rects = None
        if rects is None or any(len(r) != 4 for r in rects):
            raise ValueError(f"start_regions must be one rectangle [x0, y0, x1, y1] per expert, "
                             f"got {regions!r}; e.g. [[0, 0, 3, 8], [5, 0, 8, 8]].")
        if len(rects) < self.n_experts:
            raise ValueError(f"start_regions gives {len(rects)} rectangle(s) for "
                             f"{self.n_experts} experts; add one [x0, y0, x1, y1] for each "
                             f"expert after the first {len(rects)}.")
        obstacles, G = set(self.obstacles), self.size
        sets = []
        for i, (x0, y0, x1, y1) in enumerate(rects[:self.n_experts]):
            if not (0 <= x0 <= x1 < G and 0 <= y0 <= y1 < G):
                raise ValueError(f"start region {[x0, y0, x1, y1]} of expert {i + 1} is not a "
                                 f"rectangle [x0, y0, x1, y1] inside the {G}x{G} grid (need "
                                 f"0 <= x0 <= x1 <= {G - 1} and 0 <= y0 <= y1 <= {G - 1}).")
            cells = tuple((x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)
                          if (x, y) not in obstacles)
            if not cells:
                raise ValueError(f"start region {[x0, y0, x1, y1]} of expert {i + 1} holds only "
                                 f"obstacles; give it at least one free cell.")
            if tuple(self.starts[i]) not in cells:
                raise ValueError(f"start region {[x0, y0, x1, y1]} of expert {i + 1} does not "
                                 f"contain its start {tuple(self.starts[i])}; widen it.")
            sets.append(cells)
        return replace(self, start_sets=tuple(sets))

    # ---- derived quantities -------------------------------------------------------
    @property
    def n_experts(self) -> int:
        return len(self.starts)

    @property
    def n_cells(self) -> int:
        return self.size * self.size

    def cell(self, xy: tuple[int, int]) -> int:
        return xy[1] * self.size + xy[0]

    def xy(self, cell: int) -> tuple[int, int]:
        return cell % self.size, cell // self.size

    @property
    def start_cells(self) -> tuple[int, ...]:
        """The nominal (fixed) start cell of each expert, as cell indices ``[N]``."""
        return tuple(self.cell(c) for c in self.starts)

    @property
    def start_cell_sets(self) -> tuple[tuple[int, ...], ...]:
        """Each expert's start cells (cell indices, ascending): P0 is uniform over each,
        independently. With fixed starts, the singletons of :attr:`start_cells`."""
        if self.start_sets is None:
            return tuple((c,) for c in self.start_cells)
        return tuple(tuple(self.cell(c) for c in cells) for cells in self.start_sets)

    @property
    def varied_start(self) -> bool:
        """Whether some expert's start is drawn (P0 is not a point mass)."""
        return any(len(s) > 1 for s in self.start_cell_sets)

    @property
    def goal_cells(self) -> tuple[int, ...]:
        return tuple(self.cell(c) for c in self.goals)

    def obstacle_mask(self) -> np.ndarray:
        """``[S1]`` bool, True on obstacle cells."""
        m = np.zeros(self.n_cells, dtype=bool)
        for c in self.obstacles:
            m[self.cell(c)] = True
        return m

    def forbidden_action_mask(self) -> np.ndarray:
        """``[A1]`` bool, True on forbidden actions."""
        return np.array([a in self.forbidden_actions for a in ACTION_NAMES], dtype=bool)

    def next_cell_table(self) -> np.ndarray:
        """``[S1, A1]`` int64: the cell an action leads to when it succeeds; moving off
        the grid means staying. Obstacles do not block motion: they are constraints."""
        G = self.size
        table = np.empty((G * G, N_ACTIONS), dtype=np.int64)
        for c in range(G * G):
            x, y = c % G, c // G
            for a, (_, dx, dy) in enumerate(ACTIONS):
                nx, ny = x + dx, y + dy
                table[c, a] = ny * G + nx if (0 <= nx < G and 0 <= ny < G) else c
        return table

    def chebyshev_to_goal(self) -> np.ndarray:
        """``[N, S1]`` Chebyshev distance of every cell to each expert's goal."""
        xs = np.arange(self.n_cells) % self.size
        ys = np.arange(self.n_cells) // self.size
        return np.stack(
            [np.maximum(abs(xs - gx), abs(ys - gy)) for gx, gy in self.goals]
        ).astype(np.int64)


def check_regions(regions, size: int) -> dict[str, tuple[tuple[int, int], ...]]:
    """``regions`` (a mapping ``name -> cells`` or ``(name, cells)`` pairs, each cell an
    ``(x, y)`` pair) as a dict, checked: named, non-empty, inside the ``size x size``
    grid.

    Raises:
        ValueError: naming the region and what is wrong with it.
    """
    pairs = regions.items() if isinstance(regions, Mapping) else regions
    try:
        pairs = [(name, cells) for name, cells in pairs]
    except (TypeError, ValueError):
        raise ValueError(f"regions must map names to lists of (x, y) cells, got {regions!r}; "
                         f"e.g. {{'blue': [[4, 0], [4, 1]]}}.") from None
    checked: dict[str, tuple[tuple[int, int], ...]] = {}
    for name, cells in pairs:
        if not isinstance(name, str) or not name or name in checked:
            raise ValueError(f"region names must be distinct non-empty strings, got "
                             f"{name!r}.")
        try:
            xy = tuple((int(x), int(y)) for x, y in cells)
        except (TypeError, ValueError):
            raise ValueError(f"region {name!r}: cells must be (x, y) pairs, got "
                             f"{cells!r}.") from None
        if not xy:
            raise ValueError(f"region {name!r} has no cells; give it at least one.")
        off = [c for c in xy if not (0 <= c[0] < size and 0 <= c[1] < size)]
        if off:
            raise ValueError(f"region {name!r}: cells {off} lie outside the {size}x{size} "
                             f"grid.")
        checked[name] = xy
    return checked


def _check_n_experts(n: int) -> None:
    if not is_int(n) or n not in (1, 2, 3):
        raise InvalidSetting("n_experts", n, "1, 2 or 3 (the experts of the layout's table, "
                             "taken in order)", 2)


# A dense transition tensor has S * A * S entries; beyond this it is refused.
DENSE_ENTRY_LIMIT = 50_000_000


class TabularGridModel:
    """What a learner knows of the grid world: states, actions, the nominal factored
    dynamics, P0, horizon and discount — never the obstacles nor the reward.

    Each expert's dynamics is a "move or stay" operator: action ``a`` at cell ``s``
    leads to ``next_cell[s, a]`` with probability ``p_success`` and leaves the expert
    at ``s`` otherwise. The joint transition is the product over experts, so it is
    never materialised by the solver (see :mod:`dicrl_torch.solvers.factored`).

    Args:
        layout: the grid; only its size, start sets (P0) and experts count are used.
        horizon: number of decisions ``T`` in an episode.
        gamma: discount factor in ``(0, 1]``.
        p_success: probability that an action succeeds (docs/design.md §3: 0.8).
    """

    def __init__(
        self, *, layout: GridLayout, horizon: int = 40, gamma: float = 0.99,
        p_success: float = 0.8,
    ) -> None:
        self.horizon = setting_int("horizon", horizon, example=40,
                                   why="the horizon T, decisions per episode")
        # γ = 1 is well defined over a finite horizon.
        self.gamma = setting_number("gamma", gamma, low=0, high=1, low_open=True,
                                    example=0.99, why="the discount γ")
        self.p_success = setting_number("p_success", p_success, low=0, high=1,
                                        low_open=True, example=0.8,
                                        why="the probability that a move succeeds")
        self.layout = layout
        self.n_experts = layout.n_experts
        self.n_cells = layout.n_cells
        self.n_actions = N_ACTIONS
        self.next_cell = torch.from_numpy(layout.next_cell_table())  # [S1, A1]

    # ---- sizes --------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        return self.n_cells**self.n_experts

    @property
    def n_joint_actions(self) -> int:
        return self.n_actions**self.n_experts

    @property
    def n_pairs(self) -> int:
        return self.n_states * self.n_joint_actions

    @property
    def state_shape(self) -> tuple[int, ...]:
        return (self.n_cells,) * self.n_experts

    @property
    def start_state(self) -> tuple[int, ...]:
        """The nominal joint start ``[N]`` (the layout's ``starts``): P0's only state with
        fixed starts, one of its states with varied ones (:meth:`start_support`)."""
        return self.layout.start_cells

    def initial_distribution(self) -> torch.Tensor:
        """P0 as a ``state_shape`` (``[S1] * N``) float64 tensor summing to 1: the product
        of each expert's uniform distribution over its start cells (a point mass on
        :attr:`start_state` with fixed starts)."""
        p0 = None
        for cells in self.layout.start_cell_sets:
            p = torch.zeros(self.n_cells, dtype=torch.float64)
            p[list(cells)] = 1.0 / len(cells)
            p0 = p if p0 is None else p0.unsqueeze(-1) * p  # expert 1 the leading axis
        return p0

    def start_support(self) -> torch.Tensor:
        """``[K, N]`` int64: the joint start states P0 gives mass to, ``K = Π_i |set_i|``,
        in ascending joint index (expert 1 most significant). P0 is uniform over them
        (``1 / K`` each); ``[[*start_state]]`` with fixed starts."""
        sets = [torch.tensor(cells, dtype=torch.int64) for cells in self.layout.start_cell_sets]
        return torch.cartesian_prod(*sets).reshape(-1, self.n_experts)

    def sample_starts(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``[n, N]`` int64 joint start cells drawn from P0 with ``generator``: each
        expert with more than one start cell draws ``torch.randint`` over its set, in
        expert order. Experts with one start cell draw nothing, so with fixed starts the
        generator's stream is untouched (rollouts and samples stay as they were)."""
        cells = torch.tensor(self.start_state, dtype=torch.int64).expand(n, self.n_experts)
        cells = cells.clone()
        for i, options in enumerate(self.layout.start_cell_sets):
            if len(options) > 1:
                pick = torch.randint(len(options), (n,), generator=generator)
                cells[:, i] = torch.tensor(options, dtype=torch.int64)[pick]
        return cells

    def expert_transition(self) -> torch.Tensor:
        """``[S1, A1, S1]`` float64: one expert's transition kernel P_i(s'|s, a)."""
        S1, A1 = self.n_cells, self.n_actions
        P = torch.zeros(S1, A1, S1, dtype=torch.float64)
        s = torch.arange(S1).unsqueeze(1).expand(S1, A1)
        a = torch.arange(A1).unsqueeze(0).expand(S1, A1)
        P[s, a, self.next_cell] += self.p_success
        P[s, a, s] += 1.0 - self.p_success
        return P

    def dense_transition(self) -> torch.Tensor:
        """``[S, A, S]`` float64 joint transition, for brute-force checks on tiny
        instances only. Raises ``ValueError`` beyond :data:`DENSE_ENTRY_LIMIT`."""
        S, A = self.n_states, self.n_joint_actions
        if S * A * S > DENSE_ENTRY_LIMIT:
            raise ValueError(
                f"A dense transition for this model has {S * A * S:,} entries "
                f"(limit {DENSE_ENTRY_LIMIT:,}); use the factored solver instead, or a "
                f"smaller grid / fewer experts for brute-force checks."
            )
        P1 = self.expert_transition()
        P = P1
        for _ in range(self.n_experts - 1):
            # joint (s, s_i), (a, a_i) -> (s', s_i'): Kronecker product in expert order.
            P = torch.einsum("uav,sbt->usabvt", P, P1).reshape(
                P.shape[0] * self.n_cells, P.shape[1] * self.n_actions, P.shape[2] * self.n_cells
            )
        return P


def encode_joint(per_expert: Sequence[int] | np.ndarray | torch.Tensor,
                 base: int) -> int | np.ndarray | torch.Tensor:
    """Flattened joint index of per-expert indices ``[..., N]`` -> ``[...]`` int64.

    Expert 1 is the most significant digit: ``Σ_i x_i · base^(N-1-i)``, the order of a
    C-contiguous ``[base] * N`` tensor. Cells give the joint state (``base = S1``),
    actions the joint action (``base = A1``). A torch tensor gives a tensor on its device;
    anything else a numpy array, or a Python int for a single ``[N]`` tuple. The inverse
    is :func:`decode_joint`."""
    if isinstance(per_expert, torch.Tensor):
        flat = torch.zeros(per_expert.shape[:-1], dtype=torch.int64, device=per_expert.device)
    else:
        per_expert = np.asarray(per_expert)
        flat = np.zeros(per_expert.shape[:-1], dtype=np.int64)
    for i in range(per_expert.shape[-1]):
        flat = flat * base + per_expert[..., i]
    return flat if isinstance(flat, torch.Tensor) or flat.ndim else int(flat)


def decode_joint(joint: int | np.ndarray | torch.Tensor, base: int,
                 n: int) -> np.ndarray | torch.Tensor:
    """Per-expert indices ``[..., n]`` of flattened joint indices ``[...]``: the inverse
    of :func:`encode_joint` (expert 1 the most significant digit). A torch tensor gives
    a tensor on its device, anything else a numpy int64 array."""
    if isinstance(joint, torch.Tensor):
        digits = base ** torch.arange(n - 1, -1, -1, device=joint.device)
        return (joint.unsqueeze(-1) // digits) % base
    digits = base ** np.arange(n - 1, -1, -1, dtype=np.int64)
    return (np.asarray(joint, dtype=np.int64)[..., None] // digits) % base
