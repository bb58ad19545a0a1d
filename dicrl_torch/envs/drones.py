"""The continuous two-drone arena (docs/design.md §7, paper §6.2) as a PettingZoo ``ParallelEnv``.

Geometry (metres, ``x`` to the right, ``y`` up, origin at the bottom-left corner)::

    y=10 ─┬──door 1──┬───────────────────────────┬──door 0──┬─  (doors in the top wall)
          │ 0.5   2.0                             8.0    9.5 │
          │                                                 │
      6   │                 ┌───────────┐                   │
          │                 │  central  │  <- both straight │
      5   │                 └───────────┘     routes cross  │
          │                                   here          │
      1   │  d0 start (1, 1)                 d1 start (9, 1)│
      0   └─────────────────────────────────────────────────┘
          0   1             4           6                  10

``drone_0`` starts near the bottom-left corner and leaves through the door near the
top-right corner; ``drone_1`` mirrors it, so their straight routes cross in the middle.
The obstacle, a 2 m x 1 m block, sits exactly where both straight routes cross: the
straight route of either drone from its (jittered) start to its door's centre crosses
both of its cells. That is what makes its cells learnable from demonstrations. ICRL
learns a cell as a constraint only when the unconstrained policy would enter it and the
experts do not; an obstacle that no reward-seeking route approaches leaves no trace in
any demonstration. The block is aligned to the 1 m grid, so "cells overlapping an
obstacle" (the true cost constraints of the cell basis) are exactly the cells inside it.

Dynamics of each drone (fixed altitude, planar): the action is a velocity command
``u ∈ [-1, 1]^2``, bounded per axis (``command_set="box"``, the default) or in norm
(``"disc"``: ``u`` scaled back to ``|u| <= 1``), times ``max_speed``, tracked with a
first-order response plus Gaussian noise drawn from the env's seeded generator::

    v' = clip(v + (dt / tau) (max_speed * bound(u) - v) + noise, ±vel_limit)
    p' = clip(p + dt * v', room);  v' = 0 along an axis on which a wall stopped it

The walls are part of the dynamics, known to every learner like the grid world's edge
(a move off the grid stays): a drone pushing into a wall stops against it. The true
constraints (violations) are exactly what the cost features describe (docs/design.md §7):
being inside an obstacle box, and the two active drones closer than
``proximity_radius`` (a collision; both violate). A drone whose position enters the
mouth of its own door (the door's span, the top ``DOOR_DEPTH`` metres of the room) has
reached it: it is done (success) and leaves the arena through the door. In the true game
(``constrained=True``) a violator freezes: it stops, is terminated and removed from the
arena, like the grid world. In the nominal game violations are only reported.

The per-step game transition is the pure function :func:`joint_step`, which works on
numpy arrays and torch tensors with any leading batch shape, so a solver can batch it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from matplotlib.patches import Circle, Rectangle

from dicrl_torch.checks import check_positive
from dicrl_torch.envs.parallel import CheckedParallelEnv, agg_axes, axes_image

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

# Per-drone colours (tab10 blue, orange), as in the grid world's plots.
DRONE_COLOURS: tuple[str, ...] = ("#1f77b4", "#ff7f0e")

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


# ------------------------------------------------------- array-agnostic tiny helpers
# The game transition must run on numpy arrays (the env) and torch tensors (a batched
# solver) alike; these few helpers are all that differs between the two.
def _is_torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


def _const(value: Any, like: Any) -> Any:
    if _is_torch(like):
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)
    return np.asarray(value, dtype=like.dtype)


def _clip(x: Any, lo: float, hi: float) -> Any:
    return x.clamp(lo, hi) if _is_torch(x) else np.clip(x, lo, hi)


def _cat(parts: Sequence[Any]) -> Any:
    return torch.cat(list(parts), -1) if _is_torch(parts[0]) else np.concatenate(parts, -1)


def _rows_where(keep: Any, new: Any, old: Any) -> Any:
    """``[..., N, k]`` ``new`` where ``keep [..., N]``, else ``old``; ``new`` may be
    overwritten. numpy broadcasts a ``[..., N, 1]`` condition slowly: assigning the few
    kept-back rows in place is ~5x faster on a planner's batches, and equal."""
    if _is_torch(new):
        return torch.where(keep[..., None], new, old)
    back = ~np.asarray(keep)
    new[back] = old[back]
    return new


# ----------------------------------------------------------------- constraint checks
def in_obstacle(pos: Any) -> Any:
    """Whether positions lie in an obstacle box (closed boxes).

    Args:
        pos: ``[..., 2]`` positions ``(x, y)``, numpy or torch.

    Returns:
        ``[...]`` bool of the same array type.
    """
    o = _const(_OBSTACLE_ARRAY, pos)
    x, y = pos[..., 0:1], pos[..., 1:2]  # [..., 1] against [K]
    return ((x >= o[:, 0]) & (x <= o[:, 2]) & (y >= o[:, 1]) & (y <= o[:, 3])).any(-1)


def in_own_door(pos: Any) -> Any:
    """Whether each drone is in the mouth of its own door.

    Args:
        pos: ``[..., N, 2]`` positions of the ``N = 2`` drones.

    Returns:
        ``[..., N]`` bool.
    """
    d = _const(_DOOR_ARRAY, pos)
    x, y = pos[..., 0], pos[..., 1]
    return (x >= d[:, 0]) & (x <= d[:, 1]) & (y >= ROOM_SIZE - DOOR_DEPTH)


def outside_room(pos: Any) -> Any:
    """``[...]`` bool: positions ``[..., 2]`` outside the room ``[0, ROOM_SIZE]^2``."""
    return ((pos < 0.0) | (pos > ROOM_SIZE)).any(-1)


def too_close(pos: Any, radius: float = PROXIMITY_RADIUS) -> Any:
    """``[...]`` bool: the two drones of ``pos [..., 2, 2]`` are closer than ``radius``."""
    diff = pos[..., 0, :] - pos[..., 1, :]
    return (diff * diff).sum(-1) < radius * radius


# ------------------------------------------------------------------------- dynamics
@dataclass(frozen=True)
class DroneDynamics:
    """First-order velocity response of one planar drone, vectorised.

    Args:
        dt: time step in seconds.
        tau: time constant of the velocity response in seconds; ``dt <= tau`` so the
            Euler update does not overshoot.
        max_speed: commanded speed (m/s) of ``|u| = 1``: per axis for ``"box"``, in
            norm for ``"disc"``.
        noise_std: standard deviation (m/s) of the Gaussian velocity noise per step.
        vel_limit: hard bound on each velocity component (m/s); default
            ``1.5 * max_speed`` (noise can push slightly past the commanded speed).
        command_set: ``"box"``: each component of ``u`` clipped to ``[-1, 1]``, so the
            fastest flight is along a diagonal (``sqrt 2 * max_speed``); ``"disc"``:
            ``u`` scaled back to ``|u| <= 1``, the same top speed in every direction.
            Why the disc exists: under the box, the velocity that gains most on a door
            is a corner of the box, so a reward-seeking policy flies 45° lines where
            the experts fly straight to their doors, and ICRL may explain the
            difference with constraints on cells of the 45° routes. Measured on
            ``table2_quick`` seeds 0-2 it gave more exact sets but no wider margins
            (docs/drones.md, "Routes at 45°"); ``table2_quick`` flies it, the class
            default and ``table2`` keep the box until ``table2`` is measured with it.
    """

    COMMAND_SETS = ("box", "disc")

    dt: float = 0.1
    tau: float = 0.3
    max_speed: float = 1.0
    noise_std: float = 0.02
    vel_limit: float | None = None
    command_set: str = "box"

    def __post_init__(self) -> None:
        for name in ("dt", "tau", "max_speed"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        if isinstance(self.noise_std, bool) or not np.isfinite(self.noise_std) \
                or self.noise_std < 0:
            raise ValueError(f"noise_std must be a finite number >= 0, got {self.noise_std!r}.")
        object.__setattr__(self, "noise_std", float(self.noise_std))
        if self.command_set not in self.COMMAND_SETS:
            raise ValueError(f"command_set must be one of {self.COMMAND_SETS}, got "
                             f"{self.command_set!r}.")
        if self.dt > self.tau:
            raise ValueError(
                f"dt={self.dt} exceeds tau={self.tau}: the first-order update would "
                f"overshoot the command; use dt <= tau."
            )
        limit = 1.5 * self.max_speed if self.vel_limit is None else self.vel_limit
        limit = check_positive("vel_limit", limit)
        if limit < self.max_speed:
            raise ValueError(
                f"vel_limit={limit} is below max_speed={self.max_speed}; the commanded "
                f"speed must be reachable: use vel_limit >= max_speed."
            )
        object.__setattr__(self, "vel_limit", limit)

    def step(self, pos: Any, vel: Any, command: Any, noise: Any = None) -> tuple[Any, Any]:
        """One step of the dynamics; pure and batched (numpy or torch).

        Args:
            pos: ``[..., 2]`` positions (m).
            vel: ``[..., 2]`` velocities (m/s).
            command: ``[..., 2]`` velocity commands, bounded by :meth:`bound`.
            noise: ``[..., 2]`` velocity noise (m/s) already scaled, e.g.
                ``noise_std * rng.standard_normal(...)``; None for none.

        Returns:
            ``(pos', vel')``, each ``[..., 2]``; a wall stops a drone: its position is
            clamped to the room and its velocity along that axis set to 0.
        """
        u = self.bound(command) * self.max_speed
        vel = vel + (self.dt / self.tau) * (u - vel)
        if noise is not None:
            vel = vel + noise
        vel = _clip(vel, -self.vel_limit, self.vel_limit)
        free = pos + self.dt * vel
        pos = _clip(free, 0.0, ROOM_SIZE)
        # vel where the wall left the position free, else vel * 0.0 (its signed zero):
        # a product by the 0/1 mask is exact and several times faster than a where.
        vel = vel * (pos == free)
        return pos, vel

    def bound(self, command: Any) -> Any:
        """``[..., 2]`` the commands as flown (numpy or torch): for ``"box"`` clipped to
        ``[-1, 1]`` per component, for ``"disc"`` scaled back to unit norm where longer
        (the direction kept)."""
        if self.command_set == "box":
            return _clip(command, -1.0, 1.0)
        norm = (command * command).sum(-1, keepdims=True) ** 0.5
        return command / _clip(norm, 1.0, math.inf)

    def sample_noise(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """``shape`` float64 velocity noise from ``rng``."""
        return self.noise_std * rng.standard_normal(shape)


@dataclass(frozen=True)
class JointStep:
    """Result of :func:`joint_step`; every field is numpy or torch like the input.

    Attributes:
        state: ``[..., N, 4]`` next positions and velocities.
        active: ``[..., N]`` bool, drones still flying after the step.
        violated: ``[..., N]`` bool, a true constraint was violated in this step.
        reached: ``[..., N]`` bool, the drone arrived at its own door in this step
            (in the true game only without a violation).
        collision: ``[...]`` bool, the two active drones came too close.
        in_obstacle: ``[..., N]`` bool, an active drone is inside an obstacle.
    """

    state: Any
    active: Any
    violated: Any
    reached: Any
    collision: Any
    in_obstacle: Any


def _move(state: Any, command: Any, active: Any, noise: Any, dynamics: DroneDynamics
          ) -> tuple[Any, Any, Any]:
    """The motion shared by :func:`joint_step` and :func:`nominal_step`: the active
    drones' next positions and velocities ``[..., N, 2]`` (inactive ones keep theirs) and
    ``[..., N]`` bool which active drones are then in their own door."""
    pos, vel = state[..., :2], state[..., 2:]
    new_pos, new_vel = dynamics.step(pos, vel, command, noise)
    new_pos = _rows_where(active, new_pos, pos)
    new_vel = _rows_where(active, new_vel, vel)
    return new_pos, new_vel, in_own_door(new_pos) & active


def joint_step(
    state: Any,
    command: Any,
    active: Any,
    noise: Any = None,
    *,
    dynamics: DroneDynamics,
    proximity_radius: float = PROXIMITY_RADIUS,
    constrained: bool = True,
) -> JointStep:
    """One transition of the drone game; pure and batched (numpy or torch).

    Inactive drones (arrived or frozen) neither move nor collide. A drone that stops in
    this step (arrival, or a violation in the true game) comes to rest: velocity 0.

    Args:
        state: ``[..., N, 4]`` positions ``(x, y)`` and velocities ``(vx, vy)``.
        command: ``[..., N, 2]`` velocity commands in ``[-1, 1]`` (clipped).
        active: ``[..., N]`` bool, which drones are still flying.
        noise: ``[..., N, 2]`` velocity noise or None.
        dynamics: the drone dynamics.
        proximity_radius: collision distance (m).
        constrained: True for the true game (violators freeze), False for the nominal.

    Returns:
        The :class:`JointStep`.
    """
    new_pos, new_vel, at_door = _move(state, command, active, noise, dynamics)
    obstacle = in_obstacle(new_pos) & active
    collision = too_close(new_pos, proximity_radius) & active[..., 0] & active[..., 1]
    violated = obstacle | collision[..., None]
    if constrained:
        reached = at_door & ~violated
        stop = violated | at_door
    else:
        reached = at_door
        stop = at_door
    new_vel = new_vel * ~stop[..., None]  # stopped: new_vel * 0.0, exactly
    return JointStep(
        state=_cat([new_pos, new_vel]), active=active & ~stop, violated=violated,
        reached=reached, collision=collision, in_obstacle=obstacle,
    )


def nominal_step(state: Any, command: Any, active: Any, noise: Any = None, *,
                 dynamics: DroneDynamics) -> tuple[Any, Any]:
    """``(state', active')`` of :func:`joint_step` in the nominal game
    (``constrained=False``), equal to it bit for bit, without the violation checks that
    the nominal game only reports (a planner's model: ~1.6x faster on its batches)."""
    new_pos, new_vel, at_door = _move(state, command, active, noise, dynamics)
    new_vel = new_vel * ~at_door[..., None]  # arrived: new_vel * 0.0, exactly
    return _cat([new_pos, new_vel]), active & ~at_door


# -------------------------------------------------------------------------- the env
class DroneArena(CheckedParallelEnv):
    """Two drones crossing a 10 m room; the true game or its nominal game.

    Observation of drone ``i`` (float32, 10 values): own position and velocity, the
    other drone's position and velocity, own door centre. Action: ``[2]`` float32
    velocity command in ``[-1, 1]^2``. Reward: 1 in the step a drone reaches its door
    without a violation, else 0 (the learner brings its own reward; docs/design.md §7).

    ``infos[agent]`` has ``violated``, ``reached``, ``collision`` (this step),
    ``in_obstacle`` and ``position`` (``[2]`` float64). An agent leaves
    ``agents`` (terminated) when it reaches its door or, in the true game, violates; all
    are truncated after ``max_steps``. The random stream (start jitter, noise) depends
    only on the seed: every step draws noise for both drones, flying or not.

    Args:
        constrained: True for the true game (violators freeze), False for the nominal.
        max_steps: episode limit in steps (default 300, i.e. 30 s at dt = 0.1).
        dynamics: the drone dynamics (default :class:`DroneDynamics()`).
        proximity_radius: collision distance in metres.
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "drone_arena_v0",
                "is_parallelizable": True, "render_fps": 10}

    def __init__(
        self,
        *,
        constrained: bool = True,
        max_steps: int = 300,
        dynamics: DroneDynamics | None = None,
        proximity_radius: float = PROXIMITY_RADIUS,
        render_mode: str | None = None,
    ) -> None:
        if not isinstance(constrained, bool | np.bool_):
            raise ValueError(
                f"constrained must be a bool (True: true game, False: nominal game), "
                f"got {constrained!r}."
            )
        if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) \
                or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
        if dynamics is None:
            dynamics = DroneDynamics()
        if not isinstance(dynamics, DroneDynamics):
            raise ValueError(
                f"dynamics must be a DroneDynamics, got {type(dynamics).__name__}; build "
                f"one with DroneDynamics(dt=..., tau=...)."
            )
        self._check_render_mode(render_mode)
        self.constrained = bool(constrained)
        self.max_steps = int(max_steps)
        self.dynamics = dynamics
        self.proximity_radius = check_positive("proximity_radius", proximity_radius)
        self.render_mode = render_mode
        self.possible_agents = list(AGENTS)
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        v = dynamics.vel_limit
        lo, hi = 0.0, ROOM_SIZE
        self._obs_low = np.array([lo, lo, -v, -v] * 2 + [0.0, 0.0], dtype=np.float32)
        self._obs_high = np.array([hi, hi, v, v] * 2 + [ROOM_SIZE] * 2, dtype=np.float32)
        self.state_space = spaces.Box(
            low=np.tile(np.array([lo, lo, -v, -v]), (N_DRONES, 1)),
            high=np.tile(np.array([hi, hi, v, v]), (N_DRONES, 1)), dtype=np.float64,
        )
        self._doors = door_centres()

        self.agents: list[str] = []
        self.timestep = 0
        self._state: np.ndarray | None = None  # [N, 4] float64
        self._active = np.zeros(N_DRONES, dtype=bool)
        self.violated = np.zeros(N_DRONES, dtype=bool)  # ever violated, this episode
        self.reached = np.zeros(N_DRONES, dtype=bool)  # reached the door, this episode
        self._history: list[np.ndarray] = []  # positions [N, 2] per time step
        self._overlay: np.ndarray | None = None
        self._rng: np.random.Generator | None = None

    # ---- spaces (cached per agent by CheckedParallelEnv) ----------------------------
    def _observation_space(self) -> spaces.Box:
        return spaces.Box(low=self._obs_low, high=self._obs_high, dtype=np.float32)

    def _action_space(self) -> spaces.Box:
        return spaces.Box(low=-1.0, high=1.0, shape=(2,), dtype=np.float32)

    # ---- episode ------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._state is not None

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """``reset(options={"positions": [[x0, y0], [x1, y1]]})`` sets the start positions
        instead of the jittered nominal ones (other keys are ignored)."""
        jitter = self._rng.uniform(-START_JITTER, START_JITTER, size=(N_DRONES, 2))
        pos = np.asarray(NOMINAL_STARTS, dtype=np.float64) + jitter
        if options and options.get("positions") is not None:
            pos = _check_start_positions(options["positions"])
        self._state = np.concatenate([pos, np.zeros((N_DRONES, 2))], axis=1)
        self._active = np.ones(N_DRONES, dtype=bool)
        self.violated = np.zeros(N_DRONES, dtype=bool)
        self.reached = np.zeros(N_DRONES, dtype=bool)
        self.timestep = 0
        self._history = [pos.copy()]
        self.agents = list(self.possible_agents)
        obs = {a: self.observe(a) for a in self.agents}
        infos = {a: self._info(i, False, False, False, False)
                 for a, i in self._index.items()}
        return obs, infos

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of :meth:`CheckedParallelEnv.step`; ``given`` holds a ``[2]`` velocity
        command for every live agent."""
        live = list(given)
        command = np.zeros((N_DRONES, 2))
        for agent, a in given.items():
            command[self._index[agent]] = self._check_command(agent, a)
        noise = self.dynamics.sample_noise(self._rng, (N_DRONES, 2))
        res = joint_step(self._state, command, self._active, noise, dynamics=self.dynamics,
                         proximity_radius=self.proximity_radius, constrained=self.constrained)
        self._state, self._active = res.state, res.active
        self.violated |= res.violated
        self.reached |= res.reached
        self.timestep += 1
        self._history.append(self._state[:, :2].copy())

        obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in live:
            i = self._index[a]
            obs[a] = self.observe(a)
            rewards[a] = float(res.reached[i] and not self.violated[i])
            terms[a] = not bool(res.active[i])
            truncs[a] = not terms[a] and self.timestep >= self.max_steps
            infos[a] = self._info(i, bool(res.violated[i]), bool(res.reached[i]),
                                  bool(res.collision), bool(res.in_obstacle[i]))
        self.agents = [a for a in live if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def observe(self, agent: str) -> np.ndarray:
        """``[10]`` float32 observation of ``agent`` (also for agents that are done)."""
        i = self._agent_index(agent)
        self._require_started("observe")
        j = 1 - i
        o = np.concatenate([self._state[i], self._state[j], self._doors[i]])
        # The dynamics keep o inside the bounds; the clip only absorbs float32 rounding.
        return np.clip(o.astype(np.float32), self._obs_low, self._obs_high)

    def state(self) -> np.ndarray:
        """``[N, 4]`` float64 positions and velocities (done drones where they stopped)."""
        self._require_started("state")
        return self._state.copy()

    @property
    def active(self) -> np.ndarray:
        """``[N]`` bool: drones still flying."""
        return self._active.copy()

    def trajectory(self) -> np.ndarray:
        """``[t+1, N, 2]`` float64 positions since the last reset."""
        return np.stack(self._history) if self._history else np.zeros((0, N_DRONES, 2))

    # ---- rendering ----------------------------------------------------------------
    def set_constraint_overlay(self, cells: Any) -> None:
        """Cells to draw as (learned) constraints in :meth:`render`; see
        :func:`render_arena` for the accepted forms. ``None`` clears the overlay."""
        self._overlay = None if cells is None else constraint_cell_mask(cells)

    def _render(self) -> np.ndarray:
        title = f"{self.metadata['name']}  t={self.timestep}/{self.max_steps}" + (
            "" if self.constrained else "  (nominal)")
        traj = self.trajectory() if self._history else None
        return render_arena(
            trajectories=None if traj is None else [traj],
            positions=None if self._state is None else self._state[:, :2],
            frozen=self.violated & ~self._active if self.constrained else None,
            constraint_cells=self._overlay, proximity_radius=self.proximity_radius,
            title=title,
        )

    # ---- helpers ------------------------------------------------------------------
    def _info(self, i: int, violated: bool, reached: bool, collision: bool,
              obstacle: bool) -> dict[str, Any]:
        return {"violated": violated, "reached": reached, "collision": collision,
                "in_obstacle": obstacle, "position": self._state[i, :2].copy()}

    def _check_command(self, agent: str, a: Any) -> np.ndarray:
        """``a`` as a ``[2]`` float64 command, clipped to ``[-1, 1]``."""
        arr = np.asarray(a, dtype=np.float64) if _is_numeric(a) else None
        if arr is None or arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"Action of {agent} must be a finite [2] velocity command in [-1, 1], "
                f"got {a!r}."
            )
        return np.clip(arr, -1.0, 1.0)


def _is_numeric(a: Any) -> bool:
    try:
        arr = np.asarray(a)
    except (TypeError, ValueError):
        return False
    return np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating)


def _check_start_positions(positions: Any) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float64) if _is_numeric(positions) else None
    if pos is None or pos.shape != (N_DRONES, 2) or not np.all(np.isfinite(pos)):
        raise ValueError(
            f"options['positions'] must be finite [{N_DRONES}, 2] start positions (x, y) in "
            f"metres, got {positions!r}."
        )
    bad = outside_room(pos) | in_obstacle(pos) | in_own_door(pos)
    if bad.any() or too_close(pos):
        raise ValueError(
            f"options['positions'] {pos.tolist()} must lie in the room, outside the "
            f"obstacles {list(OBSTACLES)} and the doors, and {PROXIMITY_RADIUS} m apart."
        )
    return pos


# ------------------------------------------------------------------ joint gym adapter
RewardFn = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


def joint_obs_to_state(obs: Any) -> Any:
    """Joint observations ``[..., 20]`` of :class:`JointDroneEnv` to states ``[..., 2, 4]``
    (drone ``i``'s own position and velocity are its observation's first 4 values)."""
    obs_dim = obs.shape[-1] // N_DRONES
    parts = [obs[..., i * obs_dim:i * obs_dim + 4] for i in range(N_DRONES)]
    return torch.stack(parts, -2) if _is_torch(obs) else np.stack(parts, -2)


def joint_obs_from_states(states: Any) -> np.ndarray:
    """Joint observations of :class:`JointDroneEnv` from joint states.

    Drone ``i``'s observation is its own position and velocity, the other drone's, and
    its own door centre; the joint observation is drone 0's then drone 1's.

    Args:
        states: ``[..., 2, 4]`` positions and velocities (numpy or torch).

    Returns:
        ``[..., 20]`` float32, the inverse of :func:`joint_obs_to_state`.
    """
    s = states.detach().cpu().numpy() if isinstance(states, torch.Tensor) else np.asarray(states)
    if s.ndim < 2 or s.shape[-2:] != (N_DRONES, 4):
        raise ValueError(f"states must have shape [..., {N_DRONES}, 4], got {list(s.shape)}.")
    doors = door_centres()
    parts = []
    for i in range(N_DRONES):
        door = np.broadcast_to(doors[i], (*s.shape[:-2], 2))
        parts.append(np.concatenate([s[..., i, :], s[..., 1 - i, :], door], -1))
    return np.concatenate(parts, -1).astype(np.float32)


class JointDroneEnv(gym.Env):
    """Both drones as one gymnasium agent, for single-policy solvers (e.g. SB3 SAC).

    Observation: ``[20]`` float32, drone 0's observation then drone 1's. Action:
    ``[4]`` float32 in ``[-1, 1]``, drone 0's command then drone 1's (a done drone's
    part is ignored). Reward: ``reward_fn(obs, action, next_obs)`` or 0. Terminated
    when no drone flies any more (all arrived or frozen); truncated at ``max_steps``.
    ``info`` holds per-drone ``[2]`` bool arrays ``violated``, ``reached``, ``active``,
    ``in_obstacle``, the bool ``collision`` and the ``[2, 4]`` float64
    ``state``.

    It is a joint env as the constrained SAC solver drives one (the protocol of
    :mod:`dicrl_torch.solvers.sac`): :attr:`n_agents`, :attr:`state_shape`, the infos
    above, :meth:`obs_from_states` and :meth:`set_rng`; build it for the solver with
    ``functools.partial(JointDroneEnv, max_steps=...)`` (the solver adds
    ``constrained``).

    Args:
        reward_fn: ``(obs [20], action [4], next_obs [20]) -> float``, e.g. a learner's
            linear reward on :func:`joint_obs_to_state` features; None gives 0.
        **arena_kwargs: forwarded to :class:`DroneArena` (``constrained``,
            ``max_steps``, ``dynamics``, ``proximity_radius``, ``render_mode``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    n_agents: int = N_DRONES
    state_shape: tuple[int, int] = (N_DRONES, 4)
    """``(N, d_s)`` of ``info["state"]``: per drone ``x, y, vx, vy``."""

    def __init__(self, *, reward_fn: RewardFn | None = None, **arena_kwargs: Any) -> None:
        if reward_fn is not None and not callable(reward_fn):
            raise ValueError(
                f"reward_fn must be callable (obs, action, next_obs) -> float or None, got "
                f"{type(reward_fn).__name__}."
            )
        self.arena = DroneArena(**arena_kwargs)
        self.reward_fn = reward_fn
        self.render_mode = self.arena.render_mode
        single = self.arena.observation_space(AGENTS[0])
        self.observation_space = spaces.Box(
            low=np.tile(single.low, N_DRONES), high=np.tile(single.high, N_DRONES),
            dtype=np.float32,
        )
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(2 * N_DRONES,),
                                       dtype=np.float32)
        self._obs: np.ndarray | None = None

    def _joint_obs(self) -> np.ndarray:
        return np.concatenate([self.arena.observe(a) for a in AGENTS])

    def _joint_info(self, infos: dict[str, dict[str, Any]]) -> dict[str, Any]:
        def per(key: str) -> np.ndarray:
            return np.array([bool(infos.get(a, {}).get(key, False)) for a in AGENTS])

        return {"violated": per("violated"), "reached": per("reached"),
                "in_obstacle": per("in_obstacle"),
                "collision": bool(per("collision").any()), "active": self.arena.active,
                "state": self.arena.state()}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        _, infos = self.arena.reset(seed=seed, options=options)
        self._obs = self._joint_obs()
        return self._obs.copy(), self._joint_info(infos)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("step() called before reset(); call env.reset(seed=...) first.")
        if not self.arena.agents:
            raise RuntimeError("The episode is over; call env.reset() before step().")
        arr = np.asarray(action, dtype=np.float64) if _is_numeric(action) else None
        if arr is None or arr.shape != (2 * N_DRONES,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"action must be a finite [{2 * N_DRONES}] array in [-1, 1] (drone 0's "
                f"command, then drone 1's), got {action!r}."
            )
        cmd = arr.reshape(N_DRONES, 2)
        _, _, _, _, infos = self.arena.step(
            {a: cmd[self.arena._index[a]] for a in self.arena.agents})
        obs = self._joint_obs()
        reward = 0.0 if self.reward_fn is None else float(self.reward_fn(self._obs, arr, obs))
        terminated = not self.arena.active.any()
        truncated = not terminated and self.arena.timestep >= self.arena.max_steps
        self._obs = obs
        return obs.copy(), reward, terminated, truncated, self._joint_info(infos)

    def state(self) -> np.ndarray:
        """``[2, 4]`` float64 positions and velocities."""
        return self.arena.state()

    # ---- the solver's joint-env protocol (dicrl_torch.solvers.sac) ----------------
    def obs_from_states(self, states: Any) -> np.ndarray:
        """The joint observations ``[..., 20]`` of joint states ``[..., 2, 4]``
        (:func:`joint_obs_from_states`)."""
        return joint_obs_from_states(states)

    def set_rng(self, rng: np.random.Generator) -> None:
        """Draw the rest of this episode (its noise) and the unseeded resets after it
        from ``rng``: the arena's stream."""
        self.arena._rng = rng

    def set_constraint_overlay(self, cells: Any) -> None:
        """See :meth:`DroneArena.set_constraint_overlay`."""
        self.arena.set_constraint_overlay(cells)

    def render(self) -> np.ndarray | None:
        return self.arena.render()

    def close(self) -> None:
        self.arena.close()


# ------------------------------------------------------------------------- rendering
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
