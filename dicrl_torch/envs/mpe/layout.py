"""The geometry of the constrained spread (:mod:`dicrl_torch.envs.mpe`) and its
checks: the layout (landmarks, start region, forbidden disc, minimum distance), the start
sampler, the constraint tests, the landmark-covering test and the matching of agents to
landmarks.

They are pure functions of positions and the layout, shared by the env, the experts
(:mod:`dicrl_torch.demos.mpe_experts`) and the runs' evaluation; none of them touches
mpe2's world, so each can be used without building a game.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from mpe2.simple_spread.simple_spread import Scenario as SpreadScenario

__all__ = [
    "MAX_SPEED", "START_MARGIN", "SUCCESS_RADIUS", "SpreadLayout", "check_number",
    "covering_agents", "in_disc", "landmarks_covered", "pairwise_too_close", "sample_starts",
    "sorted_assignment",
]

SUCCESS_RADIUS: float = float(SpreadScenario.CAPTURE_RADIUS)
"""A landmark is covered by an agent within this distance (0.1; mpe2's capture radius)."""
START_MARGIN: float = 0.05
"""Starts are at least ``min_distance + START_MARGIN`` apart and at least
``START_MARGIN`` outside the disc."""
MAX_SPEED: float = 2.0 * math.sqrt(2.0)
"""Speed limit (norm of the velocity): mpe2's steady speed at a full command ``(±1, ±1)``
(force 5, damping 0.25: 2 per axis). A controlled agent never reaches it; it bounds
pushes by contact forces and noise, so that observations are bounded."""

_DEFAULT_LANDMARKS: dict[int, tuple[tuple[float, float], ...]] = {
    2: ((0.5625, 0.1875), (1.3125, 0.1875)),
    3: ((0.5625, 0.1875), (0.9375, -0.1875), (1.3125, 0.1875)),
}
_DEFAULT_START_REGIONS: dict[int, tuple[float, float, float, float]] = {
    2: (-1.2, -0.5, -0.8, 0.5),
    3: (-1.2, -0.8, -0.8, 0.8),
}


# ------------------------------------------------------------------------ the layout
def check_number(name: str, value: Any, *, positive: bool = False) -> float:
    """``value`` as a float, refused (``ValueError`` naming ``name``) unless it is a
    finite non-negative number (positive with ``positive``); the env's and the experts'
    settings share it, so their refusals read alike."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating) \
            or not np.isfinite(value) or value < 0 or (positive and value == 0):
        kind = "a positive" if positive else "a non-negative"
        raise ValueError(f"{name} must be {kind} finite number, got {value!r}.")
    return float(value)


def _points(name: str, value: Any, n: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n, 2) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be {n} finite points (x, y), shape [{n}, 2], "
                         f"got {value!r}.")
    return arr


@dataclass(frozen=True)
class SpreadLayout:
    """The geometry of a :class:`ConstrainedSpread` game, checked on construction.

    Args:
        n_agents: number of agents, which is also the number of landmarks (2 or more;
            defaults exist for 2 and 3).
        landmarks: ``[N, 2]`` fixed landmark positions; default for 2 agents
            ``(0.5625, 0.1875), (1.3125, 0.1875)``, a row behind the disc, for 3
            ``(0.5625, 0.1875), (0.9375, -0.1875), (1.3125, 0.1875)``, staggered (a row
            of cell centres would be closer than ``min_distance``): each at a cell centre
            of the 8 × 8 cost grid. They must lie
            inside the arena, at least ``disc_radius + SUCCESS_RADIUS`` from the disc's
            centre and ``min_distance`` apart, so that the task can be solved.
        start_region: ``(x_lo, y_lo, x_hi, y_hi)``, the box the starts are drawn from
            (uniformly, at least ``min_distance + START_MARGIN`` apart); default
            ``(-1.2, -0.5, -0.8, 0.5)`` for 2 agents and ``(-1.2, -0.8, -0.8, 0.8)`` for
            3. It must lie in the arena, ``START_MARGIN`` off the disc.
        disc_centre: centre of the forbidden disc; default ``(0, 0)``, between the start
            region and the landmarks, so that every straight route crosses it.
        disc_radius: its radius (default 0.3); 0 removes the disc constraint.
        min_distance: least distance between two active agents (default 0.4; mpe2's
            agents touch at 0.3); 0 removes the distance constraint.
        arena_half_width: the walls are at ``±arena_half_width`` on both axes (1.5).
    """

    n_agents: int = 2
    landmarks: Any = None
    start_region: Any = None
    disc_centre: Any = (0.0, 0.0)
    disc_radius: float = 0.3
    min_distance: float = 0.4
    arena_half_width: float = 1.5

    def __post_init__(self) -> None:
        n = self.n_agents
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 2:
            raise ValueError(f"n_agents must be an int >= 2, got {n!r}.")
        n = int(n)
        set_ = object.__setattr__
        set_(self, "n_agents", n)
        if self.landmarks is None:
            if n not in _DEFAULT_LANDMARKS:
                raise ValueError(f"There is no default layout for {n} agents; give "
                                 f"landmarks=[[x, y], ...] and start_region=(x_lo, y_lo, "
                                 f"x_hi, y_hi).")
            set_(self, "landmarks", _DEFAULT_LANDMARKS[n])
        if self.start_region is None:
            if n not in _DEFAULT_START_REGIONS:
                raise ValueError(f"There is no default start region for {n} agents; give "
                                 f"start_region=(x_lo, y_lo, x_hi, y_hi).")
            set_(self, "start_region", _DEFAULT_START_REGIONS[n])
        landmarks = _points("landmarks", self.landmarks, n)
        set_(self, "landmarks", tuple(map(tuple, landmarks.tolist())))
        centre = _points("disc_centre", [self.disc_centre], 1)[0]
        set_(self, "disc_centre", tuple(centre.tolist()))
        for name in ("disc_radius", "min_distance"):
            set_(self, name, check_number(name, getattr(self, name)))
        h = check_number("arena_half_width", self.arena_half_width, positive=True)
        set_(self, "arena_half_width", h)
        try:
            box = np.asarray(self.start_region, dtype=np.float64)
        except (TypeError, ValueError):
            box = None
        if box is None or box.shape != (4,) or not np.all(np.isfinite(box)) \
                or box[0] >= box[2] or box[1] >= box[3]:
            raise ValueError(f"start_region must be (x_lo, y_lo, x_hi, y_hi) with x_lo < x_hi "
                             f"and y_lo < y_hi, got {self.start_region!r}.")
        set_(self, "start_region", tuple(box.tolist()))
        # ---- solvable and consistent -----------------------------------------------
        if np.any(np.abs(landmarks) > h) or np.any(np.abs(box) > h):
            raise ValueError(f"The landmarks {landmarks.tolist()} and the start region "
                             f"{box.tolist()} must lie inside the arena [-{h}, {h}]^2; move "
                             f"them or raise arena_half_width.")
        if self.disc_radius > 0:
            gap = np.linalg.norm(landmarks - centre, axis=1)
            if np.any(gap < self.disc_radius + SUCCESS_RADIUS):
                raise ValueError(f"Every landmark must be at least disc_radius + "
                                 f"{SUCCESS_RADIUS} from the disc's centre {centre.tolist()} "
                                 f"(else it cannot be covered without entering the disc); "
                                 f"got distances {gap.round(3).tolist()}.")
            nearest = np.clip(centre, box[:2], box[2:])
            if np.linalg.norm(nearest - centre) < self.disc_radius + START_MARGIN:
                raise ValueError(f"The start region {box.tolist()} must stay {START_MARGIN} "
                                 f"outside the forbidden disc (centre {centre.tolist()}, "
                                 f"radius {self.disc_radius}); move one of them.")
        sep = np.linalg.norm(landmarks[:, None] - landmarks[None], axis=-1)
        sep = sep[~np.eye(n, dtype=bool)]
        if np.any(sep < self.min_distance):
            raise ValueError(f"The landmarks must be at least min_distance "
                             f"({self.min_distance}) apart, or no team can cover them "
                             f"without violating it; the closest pair is {sep.min():.3f} "
                             f"apart.")
        if sample_starts(self, np.random.default_rng(0), tries=10_000) is None:
            raise ValueError(f"The start region {box.tolist()} cannot hold {n} agents "
                             f"min_distance + {START_MARGIN} = "
                             f"{self.min_distance + START_MARGIN} apart; enlarge it or lower "
                             f"min_distance.")

    @property
    def landmark_array(self) -> np.ndarray:
        """``[N, 2]`` float64 landmark positions."""
        return np.asarray(self.landmarks, dtype=np.float64)

    @property
    def travel_direction(self) -> np.ndarray:
        """``[2]`` unit vector from the start region's centre to the landmarks' centroid."""
        box = np.asarray(self.start_region)
        d = self.landmark_array.mean(0) - (box[:2] + box[2:]) / 2
        return d / np.linalg.norm(d)

    def check_starts(self, positions: Any) -> np.ndarray:
        """``positions`` as ``[N, 2]`` float64 starts, refused unless they lie in the arena,
        off the disc and ``min_distance`` apart (any start region)."""
        pos = _points("options['positions']", positions, self.n_agents)
        h = self.arena_half_width
        if np.any(np.abs(pos) > h) or in_disc(pos, self.disc_centre, self.disc_radius).any() \
                or pairwise_too_close(pos, self.min_distance).any():
            raise ValueError(f"options['positions'] {pos.tolist()} must lie in the arena "
                             f"[-{h}, {h}]^2, outside the disc (centre {self.disc_centre}, "
                             f"radius {self.disc_radius}) and {self.min_distance} apart.")
        return pos


def sample_starts(layout: SpreadLayout, rng: np.random.Generator,
                  tries: int = 1000) -> np.ndarray | None:
    """``[N, 2]`` starts drawn uniformly from the start region, rejected until they are
    ``min_distance + START_MARGIN`` apart (and ``START_MARGIN`` off the disc, which the
    layout checks for the whole region); None if ``tries`` draws all failed."""
    box = np.asarray(layout.start_region)
    for _ in range(tries):
        pos = rng.uniform(box[:2], box[2:], size=(layout.n_agents, 2))
        if not pairwise_too_close(pos, layout.min_distance + START_MARGIN).any():
            return pos
    return None


# ---------------------------------------------------------------- constraint checks
def in_disc(pos: Any, centre: Sequence[float], radius: float) -> Any:
    """Whether positions lie strictly inside the disc.

    Args:
        pos: ``[..., 2]`` positions, numpy or torch.
        centre: ``(x, y)`` of the disc.
        radius: its radius (0: never).

    Returns:
        ``[...]`` bool of the same array type.
    """
    dx, dy = pos[..., 0] - centre[0], pos[..., 1] - centre[1]
    return dx * dx + dy * dy < radius * radius


def pairwise_too_close(pos: Any, min_distance: float, active: Any = None) -> Any:
    """Which agents are closer than ``min_distance`` to another active agent.

    Args:
        pos: ``[..., N, 2]`` positions, numpy or torch.
        min_distance: the least allowed distance (0: never too close).
        active: ``[..., N]`` bool, the agents that count (None: all).

    Returns:
        ``[..., N]`` bool of the same array type: agent ``i`` is active and some other
        active agent is closer than ``min_distance``.
    """
    diff = pos[..., :, None, :] - pos[..., None, :, :]  # [..., N, N, 2]
    close = (diff * diff).sum(-1) < min_distance * min_distance
    n = pos.shape[-2]
    if isinstance(pos, torch.Tensor):
        close = close & ~torch.eye(n, dtype=torch.bool, device=pos.device)
    else:
        close = close & ~np.eye(n, dtype=bool)
    if active is not None:
        close = close & active[..., :, None] & active[..., None, :]
    return close.any(-1)


def covering_agents(positions: Any, landmarks: Any,
                    radius: float = SUCCESS_RADIUS) -> np.ndarray:
    """``[N]`` bool: the agents that cover a landmark in a maximum matching of landmarks
    to distinct agents within ``radius`` (a bipartite augmenting-path search). Every
    landmark is covered when ``M`` agents are (:func:`landmarks_covered`).

    Args:
        positions: ``[N, 2]`` agents' positions.
        landmarks: ``[M, 2]`` landmark positions.
        radius: the covering distance.
    """
    pos, lm = np.asarray(positions, dtype=np.float64), np.asarray(landmarks, dtype=np.float64)
    near = np.linalg.norm(lm[:, None] - pos[None], axis=-1) <= radius  # [M, N]
    owner = [-1] * len(pos)

    def augment(j: int, seen: list[bool]) -> bool:
        for i in np.flatnonzero(near[j]):
            if not seen[i]:
                seen[i] = True
                if owner[i] < 0 or augment(owner[i], seen):
                    owner[i] = j
                    return True
        return False

    for j in range(len(lm)):
        augment(j, [False] * len(pos))
    return np.array([o >= 0 for o in owner], dtype=bool)


def landmarks_covered(positions: Any, landmarks: Any,
                      radius: float = SUCCESS_RADIUS) -> bool:
    """Whether every landmark lies within ``radius`` of a distinct agent (a perfect
    matching of landmarks to agents: :func:`covering_agents`).

    Args:
        positions: ``[N, 2]`` agents' positions.
        landmarks: ``[M, 2]`` landmark positions.
        radius: the covering distance.
    """
    n_landmarks = len(np.asarray(landmarks).reshape(-1, 2))
    return int(covering_agents(positions, landmarks, radius).sum()) == n_landmarks


# ------------------------------------------------------------ agents to landmarks
def sorted_assignment(layout: SpreadLayout, positions: np.ndarray) -> np.ndarray:
    """``[N]`` int: the landmark of each agent, matching agents and landmarks in their
    order across the travel direction, right to left (ties: the nearer along the travel
    direction first). Landmarks in a row along the travel direction (the 2-agent
    defaults) go from the nearest to the right-most agent to the farthest to the
    left-most."""
    e = layout.travel_direction
    normal = np.array([-e[1], e[0]])
    lm = layout.landmark_array
    agents = np.lexsort((positions @ e, np.round(positions @ normal, 9)))
    marks = np.lexsort((lm @ e, np.round(lm @ normal, 9)))
    out = np.empty(layout.n_agents, dtype=np.int64)
    out[agents] = marks
    return out
