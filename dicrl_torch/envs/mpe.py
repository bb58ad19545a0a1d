"""A constrained version of Farama's MPE ``simple_spread`` (package ``mpe2``), as a
PettingZoo ``ParallelEnv``: the first third-party game D-ICRL runs on (issue 27).

Geometry (mpe2's units, ``x`` to the right, ``y`` up; defaults for 2 agents)::

      y
     1.5 ┌──────────────────────────────────────────────────────┐  walls at ±1.5
         │                                                      │
     0.5 │  ┌─────┐                                             │
         │  │start│            ╭─────╮    x L0          x L1  │
       0 │  │region            │  d  │                          │  d: centre (0, 0), r 0.3
         │  │     │            ╰─────╯                          │  L0 = (0.5625, 0.1875)
    -0.5 │  └─────┘                                             │  L1 = (1.3125, 0.1875)
    -1.5 └──────────────────────────────────────────────────────┘
          -1.2  -0.8              0         0.5        1.0    1.5

The agents start anywhere in the start region (uniformly, at least
``min_distance + START_MARGIN`` apart) and must cover the landmarks, which lie in a
row behind the forbidden disc (3 agents, staggered: ``(0.5625, 0.1875), (0.9375, -0.1875),
(1.3125, 0.1875)``). Each default landmark is the centre of a cell of the 8 × 8 cost grid
(``features/cost=position_cells``). With landmarks on cell boundaries (the row
``(0.5, 0), (1.0, 0)`` of earlier versions), experts rest on one side of a boundary and
any policy resting a hair across it accrues a cell they never visit, which the learners
then forbid (docs/mpe.md). Every
straight route from a start to a landmark crosses the disc, and the straight routes
converge on the row, so an unconstrained team violates both kinds of true constraints
(:class:`NominalController`: in nearly every episode of the nominal game, see the
tests):

- an agent inside the **forbidden disc** (distance to its centre below its radius);
- two active agents closer than **``min_distance``** (both violate).

In the true game (``constrained=True``) a violator freezes, as in the drone arena
(:mod:`dicrl_torch.envs.drones`): it stops where it is, its actions are ignored, it is
terminated and leaves ``agents``, and it no longer collides or counts for the distance
constraint (it stays in :meth:`ConstrainedSpread.state` and in the other agents'
observations, where it stopped). In the nominal game violations are only reported.

**Task success** (:meth:`ConstrainedSpread.task_success`): at the end of the episode
every landmark lies within :data:`SUCCESS_RADIUS` (0.1, mpe2's own capture radius of
``simple_spread``) of a distinct agent, and no agent violated a constraint during the
episode. The covering test alone is :func:`landmarks_covered`.

**How it is built on mpe2.** mpe2's ``simple_spread`` is an AEC env (a turn-based
wrapper around a physics ``World``) whose ``reset`` draws random agent and landmark
positions; its parallel version is a conversion wrapper. Freezing an agent, fixing the
landmarks and drawing starts from a region do not fit through that public API, so this
env composes mpe2's pieces below it: the ``simple_spread`` :class:`Scenario` builds the
``World`` (agents of size 0.15, silent, landmarks), gives each agent's observation and
each agent's reward, and mpe2's ``World.step`` integrates the physics (force =
``5 * command``, mass 1, damping 0.25, dt 0.1, soft contact forces between agents). This
env adds only what the task needs: fixed landmarks and the start region, the
constraints and freezing, walls (a square arena, so that observations are bounded; an
agent pushing into a wall stops against it, as in the drone arena) and a speed limit
(mpe2's own ``max_speed`` attribute) for the same reason. mpe2's continuous action
``[no_op, left, right, down, up]`` in ``[0, 1]^5`` moves an agent by ``(right - left,
up - down)`` only; this env takes that effective command ``[2]`` in ``[-1, 1]^2``
directly (the symmetric box SAC expects). A frozen agent is marked ``movable = False``
and ``collide = False`` in the world. mpe2's contact force is undefined (NaN) for two
agents at the same point, which the walls make possible (two agents pushed into one
corner); there this env makes it zero.

Observation of agent ``i`` (float32, ``6 N`` values, mpe2's ``simple_spread``
observation): own velocity ``[2]``, own position ``[2]``, the landmarks' positions
relative to it ``[2 N]``, the other agents' relative positions ``[2 (N - 1)]`` and their
communication ``[2 (N - 1)]`` (always 0: the agents are silent). Bounded by the walls
and the speed limit. Reward: mpe2's, ``(1 - local_ratio) * global + local_ratio *
local`` with global = minus the sum over landmarks of the distance to the nearest agent
and local = −1 per agent in contact (the learner brings its own reward anyway).

Controllers for experts and tests: :class:`NominalController` (every agent straight to
its landmark, ignoring the constraints; it violates both kinds) and
:class:`ViaPointController` (around the disc in lanes, with start delays planned so
that the agents keep apart; succeeds without violation), with :func:`run_episode` to fly
one. Both are deterministic given the start state.
"""

from __future__ import annotations

import itertools
import math
import types
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from gymnasium import spaces
from matplotlib.patches import Circle, Rectangle
from mpe2.simple_spread.simple_spread import Scenario as SpreadScenario

from dicrl_torch.envs.parallel import CheckedParallelEnv, agg_axes, axes_image

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
def _number(name: str, value: Any, *, positive: bool = False) -> float:
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
            set_(self, name, _number(name, getattr(self, name)))
        h = _number("arena_half_width", self.arena_half_width, positive=True)
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


# -------------------------------------------------------------------------- the env
def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Least distance from ``point`` to the segment from ``a`` to ``b`` (all ``[2]``)."""
    ab = b - a
    t = float(np.clip((point - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def _collision_force(world: Any, entity_a: Any, entity_b: Any) -> list[Any]:
    """mpe2's contact force (``World.get_collision_force``), which divides by the
    distance: two agents pushed into the same corner of the walls sit at the same point,
    where it has no direction and mpe2 would give NaN; there it is zero."""
    if entity_a is not entity_b and entity_a.collide and entity_b.collide \
            and np.array_equal(entity_a.state.p_pos, entity_b.state.p_pos):
        return [None, None]
    return type(world).get_collision_force(world, entity_a, entity_b)


def _agent_names(n: int) -> list[str]:
    return [f"agent_{i}" for i in range(n)]


class ConstrainedSpread(CheckedParallelEnv):
    """MPE ``simple_spread`` with fixed landmarks, a start region, a forbidden disc and
    a minimum inter-agent distance; the true game or its nominal game (module docstring).

    Agents ``agent_0 … agent_{N-1}``. Observation of each: ``[6 N]`` float32 (mpe2's).
    Action of each: ``[2]`` float32 force command in ``[-1, 1]^2`` (clipped). Reward:
    mpe2's ``simple_spread`` reward. The state (:meth:`state`) is ``[N, 4]`` float64:
    ``x, y, vx, vy`` per agent. ``infos[agent]`` has ``violated`` (this step),
    ``in_disc``, ``too_close``, ``position`` (``[2]`` float64) and ``reached``: at the
    last step (``max_steps``), whether the agent, still flying, then covers a landmark in
    a maximum matching (:func:`covering_agents`); False before. So every agent of an
    episode reached its goal, with no violation, exactly when :meth:`task_success`. In
    the true game a violator is terminated; every agent still flying is truncated after
    ``max_steps`` (episodes always last ``max_steps`` steps unless every agent froze).
    The random stream (starts, noise) depends only on the seed.

    Args:
        layout: the geometry (default :class:`SpreadLayout()`: 2 agents).
        constrained: True for the true game (violators freeze), False for the nominal.
        max_steps: episode length in steps of 0.1 (default 50). The via-point
            controller covers the landmarks for good within 23 steps with 2 agents and
            26 with 3 (measured on 100 seeded episodes each).
        local_ratio: mpe2's mix of the local and global reward (0.5).
        noise_std: standard deviation of Gaussian noise added to each flying agent's
            velocity per step, from the env's seeded generator (default 0: mpe2's
            deterministic physics).
        order_agents: number the drawn starts so that agent ``k``'s landmark in the
            order-preserving matching (:func:`sorted_assignment`) is landmark ``k``. The
            agents are interchangeable, so this is a labelling, not a change of the
            game; it spares a joint policy learning each assignment once per start
            order (without it SAC policies learned one order and failed the mirror one:
            docs/mpe.md). Starts given in ``options`` keep the caller's order.
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "constrained_spread_v0",
                "is_parallelizable": True, "render_fps": 10}

    def __init__(
        self,
        *,
        layout: SpreadLayout | None = None,
        constrained: bool = True,
        max_steps: int = 50,
        local_ratio: float = 0.5,
        noise_std: float = 0.0,
        order_agents: bool = True,
        render_mode: str | None = None,
    ) -> None:
        if layout is None:
            layout = SpreadLayout()
        if not isinstance(layout, SpreadLayout):
            raise ValueError(f"layout must be a SpreadLayout, got {type(layout).__name__}; "
                             f"build one with SpreadLayout(n_agents=..., ...).")
        if not isinstance(constrained, bool | np.bool_):
            raise ValueError(f"constrained must be a bool (True: true game, False: nominal "
                             f"game), got {constrained!r}.")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) \
                or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
        local_ratio = _number("local_ratio", local_ratio)
        if local_ratio > 1:
            raise ValueError(f"local_ratio must lie in [0, 1], got {local_ratio!r}.")
        self._check_render_mode(render_mode)
        self.layout = layout
        self.constrained = bool(constrained)
        self.max_steps = int(max_steps)
        self.local_ratio = local_ratio
        self.noise_std = _number("noise_std", noise_std)
        if not isinstance(order_agents, bool | np.bool_):
            raise ValueError(f"order_agents must be a bool, got {order_agents!r}.")
        self.order_agents = bool(order_agents)
        self.render_mode = render_mode
        n = self.n_agents = layout.n_agents
        self.possible_agents = _agent_names(n)
        self._index = {a: i for i, a in enumerate(self.possible_agents)}

        self._scenario = SpreadScenario()
        self._world = self._scenario.make_world(n)
        self._world.get_collision_force = types.MethodType(_collision_force, self._world)
        for agent in self._world.agents:
            agent.max_speed = MAX_SPEED
        w = self._world
        # mpe2's continuous action processing: force = sensitivity * command.
        self.sensitivity = float(w.agents[0].accel or 5.0)
        self.dt, self.damping, self.mass = float(w.dt), float(w.damping), \
            float(w.agents[0].mass)

        h = layout.arena_half_width
        obs_bound = np.concatenate([
            np.full(2, MAX_SPEED), np.full(2, h), np.full(2 * n, 2 * h),
            np.full(2 * (n - 1), 2 * h), np.ones(w.dim_c * (n - 1)),
        ]).astype(np.float32)
        self._obs_high, self._obs_low = obs_bound, -obs_bound
        bound = np.tile(np.array([h, h, MAX_SPEED, MAX_SPEED]), (n, 1))
        self.state_space = spaces.Box(low=-bound, high=bound, dtype=np.float64)

        self.agents: list[str] = []
        self.timestep = 0
        self._started = False
        self._active = np.zeros(n, dtype=bool)
        self.violated = np.zeros(n, dtype=bool)  # ever violated, this episode
        self._history: list[np.ndarray] = []
        self._rng: np.random.Generator | None = None

    # ---- spaces (cached per agent by CheckedParallelEnv) ----------------------------
    def _observation_space(self) -> spaces.Box:
        return spaces.Box(low=self._obs_low, high=self._obs_high, dtype=np.float32)

    def _action_space(self) -> spaces.Box:
        return spaces.Box(low=-1.0, high=1.0, shape=(2,), dtype=np.float32)

    # ---- episode ------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._started

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """``reset(options={"positions": [[x, y], ...]})`` sets the starts (anywhere in the
        arena off the constraints) instead of drawing them (other keys are ignored)."""
        pos = sample_starts(self.layout, self._rng)
        assert pos is not None  # the layout checked that the region holds the agents
        if self.order_agents:  # agent k takes the k-th start of the matching's order
            pos = pos[np.argsort(sorted_assignment(self.layout, pos))]
        if options and options.get("positions") is not None:
            pos = self.layout.check_starts(options["positions"])
        w = self._world
        for agent, p in zip(w.agents, pos, strict=True):
            agent.state.p_pos = p.copy()
            agent.state.p_vel = np.zeros(w.dim_p)
            agent.state.c = np.zeros(w.dim_c)
            agent.action.u = np.zeros(w.dim_p)
            agent.action.c = np.zeros(w.dim_c)
            agent.movable = agent.collide = True
        for landmark, p in zip(w.landmarks, self.layout.landmark_array, strict=True):
            landmark.state.p_pos = p.copy()
            landmark.state.p_vel = np.zeros(w.dim_p)
        self._active = np.ones(self.n_agents, dtype=bool)
        self.violated = np.zeros(self.n_agents, dtype=bool)
        self.timestep = 0
        self._started = True
        self._history = [pos.copy()]
        self.agents = list(self.possible_agents)
        obs = {a: self.observe(a) for a in self.agents}
        infos = {a: self._info(i, False, False) for a, i in self._index.items()}
        return obs, infos

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of :meth:`CheckedParallelEnv.step`; ``given`` holds a ``[2]`` command
        for every live agent."""
        w, n = self._world, self.n_agents
        command = np.zeros((n, 2))
        for agent, a in given.items():
            command[self._index[agent]] = self._check_command(agent, a)
        for i, agent in enumerate(w.agents):
            agent.action.u = self.sensitivity * command[i] if self._active[i] \
                else np.zeros(w.dim_p)
            agent.action.c = np.zeros(w.dim_c)
        w.step()  # mpe2's physics; frozen agents are not movable
        noise = self.noise_std * self._rng.standard_normal((n, 2)) if self.noise_std else None
        h = self.layout.arena_half_width
        for i, agent in enumerate(w.agents):
            if not self._active[i]:
                continue
            vel = agent.state.p_vel + (0.0 if noise is None else noise[i])
            speed = np.linalg.norm(vel)
            if speed > MAX_SPEED:
                vel = vel * (MAX_SPEED / speed)
            free = agent.state.p_pos
            pos = np.clip(free, -h, h)
            agent.state.p_pos = pos
            agent.state.p_vel = np.where(pos == free, vel, 0.0)
        positions = self.positions
        layout = self.layout
        disc = in_disc(positions, layout.disc_centre, layout.disc_radius) & self._active
        close = pairwise_too_close(positions, layout.min_distance, self._active)
        violated = disc | close
        self.violated |= violated
        if self.constrained:
            for i in np.flatnonzero(violated):
                agent = w.agents[i]
                agent.state.p_vel = np.zeros(w.dim_p)
                agent.movable = agent.collide = False
            self._active = self._active & ~violated
        self.timestep += 1
        self._history.append(positions.copy())

        global_reward = float(self._scenario.global_reward(w))
        # Success is judged at the end: only the last step reports the agents that then
        # cover a landmark (``reached``), so a solver's "reached in the episode" is
        # "covering at the end".
        last = self.timestep >= self.max_steps
        covering = np.zeros(self.n_agents, dtype=bool)
        if last:  # frozen agents cover nothing (a violation already failed the task)
            covering[self._active] = covering_agents(positions[self._active],
                                                     layout.landmark_array)
        obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in given:
            i = self._index[a]
            obs[a] = self.observe(a)
            local = float(self._scenario.reward(w.agents[i], w))
            rewards[a] = (1 - self.local_ratio) * global_reward + self.local_ratio * local
            terms[a] = not bool(self._active[i])
            truncs[a] = not terms[a] and last
            infos[a] = self._info(i, bool(disc[i]), bool(close[i]),
                                  reached=bool(covering[i]))
        self.agents = [a for a in given if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def observe(self, agent: str) -> np.ndarray:
        """``[6 N]`` float32 observation of ``agent`` (also for agents that are done)."""
        i = self._agent_index(agent)
        self._require_started("observe")
        o = self._scenario.observation(self._world.agents[i], self._world)
        # The walls and the speed limit keep o inside the bounds; the clip only absorbs
        # float32 rounding.
        return np.clip(o.astype(np.float32), self._obs_low, self._obs_high)

    def state(self) -> np.ndarray:
        """``[N, 4]`` float64 ``x, y, vx, vy`` per agent (frozen agents where they stopped)."""
        self._require_started("state")
        return np.array([np.concatenate([a.state.p_pos, a.state.p_vel])
                         for a in self._world.agents])

    @property
    def positions(self) -> np.ndarray:
        """``[N, 2]`` float64 positions."""
        return self.state()[:, :2]

    @property
    def active(self) -> np.ndarray:
        """``[N]`` bool: agents not frozen (in the nominal game: all)."""
        return self._active.copy()

    def trajectory(self) -> np.ndarray:
        """``[t+1, N, 2]`` float64 positions since the last reset."""
        return np.stack(self._history) if self._history \
            else np.zeros((0, self.n_agents, 2))

    def landmarks_covered(self) -> bool:
        """Whether every landmark is now within :data:`SUCCESS_RADIUS` of a distinct agent."""
        return landmarks_covered(self.positions, self.layout.landmark_array)

    def task_success(self) -> bool:
        """The task-success test, meant for the end of an episode: every landmark within
        :data:`SUCCESS_RADIUS` of a distinct agent and no violation in the episode."""
        return self.landmarks_covered() and not self.violated.any()

    # ---- rendering ----------------------------------------------------------------
    def _render(self) -> np.ndarray:
        title = f"{self.metadata['name']}  t={self.timestep}/{self.max_steps}" + (
            "" if self.constrained else "  (nominal)")
        started = self._started
        return render_spread(
            self.layout, trajectories=[self.trajectory()] if started else None,
            positions=self.positions if started else None,
            frozen=~self._active if started and self.constrained else None, title=title)

    # ---- helpers ------------------------------------------------------------------
    def _info(self, i: int, disc: bool, close: bool, reached: bool = False) -> dict[str, Any]:
        return {"violated": disc or close, "in_disc": disc, "too_close": close,
                "reached": reached, "position": self._world.agents[i].state.p_pos.copy()}

    def _check_command(self, agent: str, a: Any) -> np.ndarray:
        """``a`` as a ``[2]`` float64 command, clipped to ``[-1, 1]``."""
        try:
            arr = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"Action of {agent} must be a finite [2] force command in "
                             f"[-1, 1] (right - left, up - down), got {a!r}.")
        return np.clip(arr, -1.0, 1.0)


# ------------------------------------------------------------------------ rendering
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


# ---------------------------------------------------------------------- controllers
class Controller(Protocol):
    """A joint controller: ``reset(state)`` at the episode start, then ``act(state,
    active) -> [N, 2]`` commands in ``[-1, 1]``."""

    def reset(self, state: np.ndarray) -> None: ...

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray: ...


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


def _velocity_command(env: ConstrainedSpread, vel: np.ndarray, v_des: np.ndarray
                      ) -> np.ndarray:
    """``[N, 2]`` commands that bring velocities ``vel`` to ``v_des`` in one step of
    mpe2's physics (``v' = (1 - damping) v + dt * sensitivity * u / mass``), scaled down
    (direction kept) where they exceed ``[-1, 1]``."""
    u = (v_des - (1 - env.damping) * vel) * env.mass / (env.dt * env.sensitivity)
    scale = np.maximum(np.abs(u).max(-1, keepdims=True), 1.0)
    return u / scale


class _WaypointFollower:
    """Each agent flies its own list of via-points at a cruise speed: proportional
    tracking of the current via-point (speed ``min(cruise, gain * distance)``), the
    next via-point once within ``switch`` of it; the last one is held."""

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float, gain: float,
                 switch: float) -> None:
        self.env = env
        self.cruise_speed = _number("cruise_speed", cruise_speed, positive=True)
        self.gain = _number("gain", gain, positive=True)
        self.switch = switch
        self.routes: list[np.ndarray] = []
        self._next: np.ndarray = np.zeros(0, dtype=np.int64)

    def start(self, routes: list[np.ndarray]) -> None:
        self.routes = routes
        self._next = np.zeros(len(routes), dtype=np.int64)

    def targets(self, pos: np.ndarray) -> np.ndarray:
        out = np.empty_like(pos)
        for i, route in enumerate(self.routes):
            while self._next[i] < len(route) - 1 \
                    and np.linalg.norm(route[self._next[i]] - pos[i]) < self.switch:
                self._next[i] += 1
            out[i] = route[self._next[i]]
        return out

    def desired_velocity(self, state: np.ndarray) -> np.ndarray:
        """``[N, 2]`` velocities towards the current via-points."""
        pos, vel = state[:, :2], state[:, 2:]
        ahead = pos + self.env.dt * vel  # mpe2 moves by the current velocity first
        err = self.targets(ahead) - ahead
        dist = np.linalg.norm(err, axis=-1, keepdims=True)
        return err / np.maximum(dist, 1e-9) * np.minimum(self.cruise_speed, self.gain * dist)

    def command(self, state: np.ndarray, active: np.ndarray, v_des: np.ndarray
                ) -> np.ndarray:
        u = _velocity_command(self.env, state[:, 2:], v_des)
        u[~np.asarray(active, dtype=bool)] = 0.0
        return u.astype(np.float32)

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        return self.command(state, active, self.desired_velocity(state))


class NominalController:
    """The unconstrained expert: every agent flies straight to its landmark
    (:func:`sorted_assignment`, fixed at ``reset``) at ``cruise_speed``, ignoring the
    disc and the other agents. Deterministic.

    Args:
        env: the game (for its layout and mpe2's physical constants).
        cruise_speed: speed along the route (default 1.5; mpe2's full speed is 2 per axis).
        gain: proportional gain (1/s) of the approach to the landmark.
    """

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float = 1.5,
                 gain: float = 4.0) -> None:
        self.env = env
        self._follow = _WaypointFollower(env, cruise_speed=cruise_speed, gain=gain,
                                         switch=0.0)

    def reset(self, state: np.ndarray) -> None:
        lm = self.env.layout.landmark_array
        self.assignment = sorted_assignment(self.env.layout, state[:, :2])
        self._follow.start([lm[j][None] for j in self.assignment])

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        return self._follow.act(state, active)


class ViaPointController:
    """The constrained expert: around the disc in lanes, then to the landmark, with
    start times that keep the agents apart.

    Routes: the agents are matched to landmarks in their order across the travel
    direction (:func:`sorted_assignment`); the lower half (``N // 2`` agents) passes the
    disc on the right-hand side of the travel direction, the others on the left. On each
    side the agent nearer the disc's axis takes the inner lane, at ``disc_radius +
    clearance`` from the centre, the next one a lane ``min_distance + lane_margin``
    further out, and so on. Each route runs from the start through two via-points
    abreast the disc (``disc_radius`` before and after its centre along the travel
    direction), then straight to the landmark; if one agent's straight way would pass
    closer than ``clearance`` to the disc or than ``min_distance`` to another landmark,
    every agent follows its lane until abreast of its landmark first.

    Timing: the agents do not interact physically while they keep apart, so the planner
    simulates each agent's flight alone (mpe2's physics, the same tracking law) and
    schedules start delays by prioritized planning: for each order of the agents (every
    permutation up to 4 agents; beyond, front-most first) each agent in turn gets the
    least delay (in steps, waiting at rest at its start) for which it stays at least
    ``min_distance + safety`` from every agent scheduled before it at every step (or
    halfway between ``min_distance`` and the pair's landmark spacing, if that is less:
    settled agents sit on their landmarks) and settles before the episode
    ends; the order finishing first wins. If no order works the one with the widest
    least gap is flown. Deterministic given the start state; without noise the flight
    is exactly the simulated one.

    Args:
        env: the game.
        cruise_speed: speed along the route (default 1.5).
        gain: proportional gain (1/s) of the approach to each via-point.
        clearance: margin of the inner lane from the disc (default 0.2).
        lane_margin: extra spacing of adjacent lanes beyond ``min_distance`` (0.1).
        safety: planned separation beyond ``min_distance`` (0.05).
        lane_spread: each agent's lane lies a further ``U(0, lane_spread)`` out in each
            episode, drawn from a generator seeded by the start state (so still
            deterministic given it); default 0. Experts who vary their way visit the free
            cells beside it: with one way only, the cells that a way passes by without
            entering are never demonstrated, and learners that fly a little wider
            forbid them (docs/mpe.md).
        exit_spread: each agent follows its lane a further ``U(0, exit_spread)`` past
            the disc before turning to its landmark (same generator; default 0): the
            straight legs then sweep the cells between the lane and the landmark.
    """

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float = 1.5,
                 gain: float = 4.0, clearance: float = 0.2, lane_margin: float = 0.1,
                 safety: float = 0.05, lane_spread: float = 0.0,
                 exit_spread: float = 0.0) -> None:
        self.env = env
        self.clearance = _number("clearance", clearance)
        self.lane_spread = _number("lane_spread", lane_spread)
        self.exit_spread = _number("exit_spread", exit_spread)
        self.lane_margin = _number("lane_margin", lane_margin)
        self.safety = _number("safety", safety)
        self._kwargs = {"cruise_speed": cruise_speed, "gain": gain, "switch": 0.15}
        self._follow = _WaypointFollower(env, **self._kwargs)
        self.routes: list[np.ndarray] = []
        self.delays = np.zeros(0, dtype=np.int64)
        self.planned_gap = math.inf
        self._t = 0

    def plan_routes(self, positions: np.ndarray) -> list[np.ndarray]:
        """Each agent's via-points ``[K_i, 2]`` (the last is its landmark) from the
        starts ``[N, 2]``; sets ``assignment``, ``side``, ``lane`` and ``spread`` (each
        lane's extra offset ``[N]``)."""
        layout = self.env.layout
        n, lm = layout.n_agents, layout.landmark_array
        self.assignment = sorted_assignment(layout, positions)
        e = layout.travel_direction
        normal = np.array([-e[1], e[0]])
        centre = np.asarray(layout.disc_centre)
        order = np.argsort(positions @ normal, kind="stable")  # right-most first
        n_right = n // 2
        self.side = np.empty(n, dtype=np.int64)  # -1 right of the travel direction, +1 left
        self.lane = np.empty(n, dtype=np.int64)
        for rank, i in enumerate(order):
            if rank < n_right:
                self.side[i], self.lane[i] = -1, n_right - 1 - rank
            else:
                self.side[i], self.lane[i] = 1, rank - n_right
        r = layout.disc_radius
        self.spread, self.exit_extra = np.zeros(n), np.zeros(n)
        if self.lane_spread > 0 or self.exit_spread > 0:  # seeded by the starts
            starts = np.ascontiguousarray(positions, dtype=np.float64).tobytes()
            rng = np.random.default_rng(zlib.crc32(starts))
            self.spread = rng.uniform(0.0, self.lane_spread, n)
            self.exit_extra = rng.uniform(0.0, self.exit_spread, n)
        legs = []  # (the lane's side point, the two via-points abreast the disc, target)
        for i in range(n):
            offset = r + self.clearance + self.spread[i] + self.lane[i] * (
                layout.min_distance + self.lane_margin + self.lane_spread)
            side = centre + self.side[i] * offset * normal
            legs.append((side, [side - r * e, side + (r + self.exit_extra[i]) * e]
                         if r > 0 else [], lm[self.assignment[i]]))
        # Straight on from the lanes' exits: a constrained-optimal expert takes the
        # shortest way, and a detour (along the lane until abreast of the landmark) leaves
        # free cells unvisited that the learners then read as forbidden (docs/mpe.md).
        # Every agent detours if one straight way would pass closer than the clearance to
        # the disc or than min_distance to another landmark (where a settled agent may
        # sit): a straight descent across a lane that another agent follows is what the
        # start delays could not keep apart (3 agents).
        detour = r > 0 and any(self._needs_detour(via[-1], target, self.assignment[i])
                               for i, (_, via, target) in enumerate(legs))
        routes = []
        for side, via, target in legs:
            if detour:
                via = [*via, side + max((target - centre) @ e, r) * e]
            routes.append(np.array([*via, target]))
        return routes

    def _needs_detour(self, exit_: np.ndarray, target: np.ndarray, k: int) -> bool:
        layout = self.env.layout
        centre = np.asarray(layout.disc_centre)
        if _segment_distance(centre, exit_, target) < layout.disc_radius + self.clearance:
            return True
        others = np.delete(layout.landmark_array, k, axis=0)
        return any(_segment_distance(p, exit_, target) < layout.min_distance for p in others)

    def _fly_alone(self, start: np.ndarray, route: np.ndarray, steps: int) -> np.ndarray:
        """``[steps + 1, 2]`` positions of one agent flying ``route`` from rest at
        ``start`` with no other agent (mpe2's integration: position first, then the
        damped velocity plus the force)."""
        env = self.env
        follow = _WaypointFollower(env, **self._kwargs)
        follow.start([route])
        state = np.concatenate([start, np.zeros(2)])[None]
        out = [start.copy()]
        for _ in range(steps):
            u = follow.act(state, np.ones(1, dtype=bool)).astype(np.float64)[0]
            pos = state[0, :2] + env.dt * state[0, 2:]
            vel = (1 - env.damping) * state[0, 2:] + env.dt * env.sensitivity * u / env.mass
            speed = np.linalg.norm(vel)
            if speed > MAX_SPEED:
                vel = vel * (MAX_SPEED / speed)
            state = np.concatenate([pos, vel])[None]
            out.append(pos)
        return np.stack(out)

    def reset(self, state: np.ndarray) -> None:
        env, layout = self.env, self.env.layout
        pos = np.asarray(state, dtype=np.float64)[:, :2]
        n, horizon = layout.n_agents, env.max_steps
        self.routes = self.plan_routes(pos)
        alone = [self._fly_alone(pos[i], self.routes[i], horizon) for i in range(n)]
        lm = layout.landmark_array[self.assignment]
        spacing = np.linalg.norm(lm[:, None] - lm[None], axis=-1)
        # Settled agents sit on their landmarks, which may be closer than the margin.
        limit = np.minimum(layout.min_distance + self.safety,
                           (layout.min_distance + spacing) / 2)
        near = [np.linalg.norm(a - a[-1], axis=-1) > SUCCESS_RADIUS / 2 for a in alone]
        settle = np.array([int(np.flatnonzero(m)[-1]) + 1 if m.any() else 0 for m in near])

        def shifted(i: int, d: int) -> np.ndarray:  # waits d steps at rest, then flies
            return np.concatenate([np.repeat(pos[i][None], d, 0), alone[i][:horizon + 1 - d]])

        e = layout.travel_direction
        front = tuple(np.argsort(-(pos @ e), kind="stable").tolist())
        orders = list(itertools.permutations(range(n))) if n <= 4 else [front]
        orders.sort(key=lambda o: o != front)  # front-most first wins ties
        best: tuple[tuple[int, float], np.ndarray, float] | None = None
        for order in orders:
            delays = np.zeros(n, dtype=np.int64)
            flown: list[int] = []
            least = math.inf
            feasible = True
            for i in order:
                chosen, chosen_gap = None, -math.inf
                for d in range(horizon + 1 - settle[i]):
                    path = shifted(i, d)
                    gap = min((np.linalg.norm(path - shifted(j, delays[j]), axis=-1)
                               - limit[i, j]).min() for j in flown) if flown else math.inf
                    if gap >= 0:
                        chosen, chosen_gap = d, gap
                        break
                    if gap > chosen_gap:
                        chosen, chosen_gap = d, gap
                if chosen is None:  # cannot settle in time whatever the delay
                    chosen, chosen_gap = 0, -math.inf
                feasible &= chosen_gap >= 0 and settle[i] + chosen <= horizon
                delays[i] = chosen
                least = min(least, chosen_gap)
                flown.append(i)
            key = (0 if feasible else 1, int((settle + delays).max()) if feasible else -least)
            if best is None or key < best[0]:
                best = (key, delays, least)
        assert best is not None
        self.delays, self.planned_gap = best[1], best[2]
        self._follow.start(self.routes)
        self._t = 0

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        v_des = self._follow.desired_velocity(state)
        v_des[self._t < self.delays] = 0.0  # waiting at the start
        self._t += 1
        return self._follow.command(state, active, v_des)


@dataclass
class Episode:
    """One flown episode.

    Attributes:
        states: ``[T+1, N, 4]`` float64 states (``x, y, vx, vy``).
        actions: ``[T, N, 2]`` float32 commands given (a frozen agent's are ignored).
        violated: ``[N]`` bool, agents that violated a constraint.
        in_disc: whether some agent entered the disc.
        too_close: whether two agents came closer than ``min_distance``.
        success: the task-success test at the end (:meth:`ConstrainedSpread.task_success`).
        covered: the landmarks were covered at the end (violations aside).
    """

    states: np.ndarray
    actions: np.ndarray
    violated: np.ndarray
    in_disc: bool
    too_close: bool
    success: bool
    covered: bool
    infos: list[dict[str, dict[str, Any]]] = field(default_factory=list, repr=False)

    @property
    def length(self) -> int:
        return len(self.actions)


def run_episode(env: ConstrainedSpread, controller: Controller, *, seed: int | None = None,
                options: dict[str, Any] | None = None) -> Episode:
    """Fly one episode of ``env`` with ``controller`` (reset with ``seed`` and
    ``options``) until every agent is done."""
    env.reset(seed=seed, options=options)
    state = env.state()
    controller.reset(state)
    states, actions, infos = [state], [], []
    in_disc_any = too_close_any = False
    while env.agents:
        u = controller.act(state, env.active)
        _, _, _, _, info = env.step({a: u[env._index[a]] for a in env.agents})
        in_disc_any |= any(v["in_disc"] for v in info.values())
        too_close_any |= any(v["too_close"] for v in info.values())
        state = env.state()
        states.append(state)
        actions.append(u)
        infos.append(info)
    return Episode(states=np.stack(states), actions=np.stack(actions),
                   violated=env.violated.copy(), in_disc=in_disc_any,
                   too_close=too_close_any, success=env.task_success(),
                   covered=env.landmarks_covered(), infos=infos)
