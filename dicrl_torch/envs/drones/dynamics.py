"""The drone game's motion and transition (:mod:`dicrl_torch.envs.drones`):
:class:`DroneDynamics` (one drone's first-order velocity response, with the walls) and
the pure, batched joint step of both drones, :func:`joint_step` (with the violation
checks) and :func:`nominal_step` (without them, for a planner's model).

They work on numpy arrays and torch tensors with any leading batch shape, so the env, a
solver and a planner all step the same game.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dicrl_torch.checks import check_positive
from dicrl_torch.envs.drones.arrays import clip, concat, rows_where
from dicrl_torch.envs.drones.geometry import (
    PROXIMITY_RADIUS,
    ROOM_SIZE,
    in_obstacle,
    in_own_door,
    too_close,
)


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
        vel = clip(vel, -self.vel_limit, self.vel_limit)
        free = pos + self.dt * vel
        pos = clip(free, 0.0, ROOM_SIZE)
        # vel where the wall left the position free, else vel * 0.0 (its signed zero):
        # a product by the 0/1 mask is exact and several times faster than a where.
        vel = vel * (pos == free)
        return pos, vel

    def bound(self, command: Any) -> Any:
        """``[..., 2]`` the commands as flown (numpy or torch): for ``"box"`` clipped to
        ``[-1, 1]`` per component, for ``"disc"`` scaled back to unit norm where longer
        (the direction kept)."""
        if self.command_set == "box":
            return clip(command, -1.0, 1.0)
        norm = (command * command).sum(-1, keepdims=True) ** 0.5
        return command / clip(norm, 1.0, math.inf)

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
    new_pos = rows_where(active, new_pos, pos)
    new_vel = rows_where(active, new_vel, vel)
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
        state=concat([new_pos, new_vel]), active=active & ~stop, violated=violated,
        reached=reached, collision=collision, in_obstacle=obstacle,
    )


def nominal_step(state: Any, command: Any, active: Any, noise: Any = None, *,
                 dynamics: DroneDynamics) -> tuple[Any, Any]:
    """``(state', active')`` of :func:`joint_step` in the nominal game
    (``constrained=False``), equal to it bit for bit, without the violation checks that
    the nominal game only reports (a planner's model: ~1.6x faster on its batches)."""
    new_pos, new_vel, at_door = _move(state, command, active, noise, dynamics)
    new_vel = new_vel * ~at_door[..., None]  # arrived: new_vel * 0.0, exactly
    return concat([new_pos, new_vel]), active & ~at_door
