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

The package holds the game in its concerns: :mod:`~dicrl_torch.envs.drones.geometry`
(the room, obstacle, doors, starts and the constraints' tests on positions),
:mod:`~dicrl_torch.envs.drones.dynamics` (:class:`DroneDynamics` and the batched
:func:`joint_step` / :func:`nominal_step`), :mod:`~dicrl_torch.envs.drones.env` (the
PettingZoo :class:`DroneArena` and the single-agent :class:`JointDroneEnv`),
:mod:`~dicrl_torch.envs.drones.vector` (:class:`DroneVectorEnv`, many joint episodes
stepped as one batch) and :mod:`~dicrl_torch.envs.drones.render` (the picture); the
numpy/torch helpers they share are :mod:`~dicrl_torch.envs.drones.arrays`. The
demonstrations' planner is :mod:`dicrl_torch.demos.drone_demos`.
"""

from dicrl_torch.envs.drones import geometry
from dicrl_torch.envs.drones.dynamics import DroneDynamics, JointStep, joint_step, nominal_step
from dicrl_torch.envs.drones.env import (
    DroneArena,
    JointDroneEnv,
    RewardFn,
    joint_obs_from_states,
    joint_obs_to_state,
)

# The room, obstacle, doors, starts and the constraints' tests: geometry's whole public
# API, named once, by its __all__.
from dicrl_torch.envs.drones.geometry import *  # noqa: F403
from dicrl_torch.envs.drones.render import DRONE_COLOURS, constraint_cell_mask, render_arena
from dicrl_torch.envs.drones.vector import DroneVectorEnv

__all__ = [
    "DRONE_COLOURS",
    "DroneArena",
    "DroneDynamics",
    "DroneVectorEnv",
    "JointDroneEnv",
    "JointStep",
    "RewardFn",
    "constraint_cell_mask",
    "joint_obs_from_states",
    "joint_obs_to_state",
    "joint_step",
    "nominal_step",
    "render_arena",
]
__all__ += geometry.__all__
