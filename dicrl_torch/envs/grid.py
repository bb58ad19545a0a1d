"""The multi-expert grid world: layout, actions, true constraints and the learner's
tabular model (docs/design.md §3).

Coordinates are ``(x, y)`` with ``x`` the column (left → right) and ``y`` the row
(top → bottom). A cell's index is ``y * size + x``. A joint state of ``N`` experts is
the tuple of their cell indices; flattened, expert 1 is the most significant digit,
so a joint value tensor has shape ``[S1] * N`` (``S1 = size**2``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

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
    """

    size: int
    starts: tuple[tuple[int, int], ...]
    goals: tuple[tuple[int, int], ...]
    obstacles: tuple[tuple[int, int], ...] = ()
    forbidden_actions: tuple[str, ...] = ()
    collision_constraint: bool = True
    regions: tuple[tuple[str, tuple[tuple[int, int], ...]], ...] = ()
    name: str = field(default="custom", compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.size, int) or self.size < 2:
            raise ValueError(f"GridLayout.size must be an int >= 2, got {self.size!r}.")
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
        unknown = set(self.forbidden_actions) - set(ACTION_NAMES)
        if unknown:
            raise ValueError(
                f"Unknown forbidden action(s) {sorted(unknown)}; choose from {ACTION_NAMES}."
            )

    # ---- constructors -------------------------------------------------------------
    @classmethod
    def scobee(cls, n_experts: int = 3) -> GridLayout:
        """The paper's 9x9 layout with the first ``n_experts`` experts of docs/design.md §3."""
        _check_n_experts(n_experts)
        return cls(
            size=9,
            starts=SCOBEE_STARTS[:n_experts],
            goals=SCOBEE_GOALS[:n_experts],
            obstacles=SCOBEE_OBSTACLES,
            forbidden_actions=SCOBEE_FORBIDDEN_ACTIONS,
            regions=SCOBEE_REGIONS,
            name=f"scobee{n_experts}",
        )

    @classmethod
    def open_grid(cls, size: int, n_experts: int) -> GridLayout:
        """A nominal ``size x size`` grid without obstacles, for scaling studies and
        tiny brute-force tests. Experts start in corners and aim for the opposite one."""
        _check_n_experts(n_experts)
        g = size - 1
        starts = ((0, g), (g, 0), (0, 0))[:n_experts]
        goals = ((g, g), (0, 0), (g, g))[:n_experts]
        if n_experts == 3:  # expert 3 goes top-left -> bottom-left so goals stay distinct
            goals = ((g, g), (0, 0), (0, g))
        return cls(size=size, starts=starts, goals=goals, name=f"open{size}")

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
        return tuple(self.cell(c) for c in self.starts)

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
    if n not in (1, 2, 3):
        raise ValueError(f"n_experts must be 1, 2 or 3, got {n!r}.")


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
        layout: the grid; only its size, starts (P0) and experts count are used.
        horizon: number of decisions ``T`` in an episode.
        gamma: discount factor in ``(0, 1]``.
        p_success: probability that an action succeeds (docs/design.md §3: 0.8).
    """

    def __init__(
        self, *, layout: GridLayout, horizon: int = 40, gamma: float = 0.99,
        p_success: float = 0.8,
    ) -> None:
        if not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}.")
        if not (0.0 < gamma <= 1.0):
            raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}.")
        if not (0.0 < p_success <= 1.0):
            raise ValueError(f"p_success must lie in (0, 1], got {p_success!r}.")
        self.layout = layout
        self.horizon = horizon
        self.gamma = float(gamma)
        self.p_success = float(p_success)
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
        return self.layout.start_cells

    def initial_distribution(self) -> torch.Tensor:
        """P0 as a ``state_shape`` float64 tensor (all mass on the start cells)."""
        p0 = torch.zeros(self.state_shape, dtype=torch.float64)
        p0[self.start_state] = 1.0
        return p0

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
