"""Planning in the drone arena on a learned game (docs/drones.md, "Planning on the learned
game"): the arena's pieces for the game-free planner of :mod:`dicrl_torch.solvers.planning`.

A learner that has learned ``(η̄, ω_c)`` acts by planning in the nominal arena it knows
(:func:`~dicrl_torch.envs.drones.nominal_step`) on the learned reward
``ω_r·φ_r + λ ω_c·φ_c``, never entering a learned cell or the proximity grown by a
margin; the terminal value is each drone's :func:`~dicrl_torch.solvers.planning.grid_values`
(alone in the room, the learned cells forbidden, its door absorbing), summed. It sits
with the solvers, below the runs: the drone task (:class:`dicrl_torch.runs.drones.DroneTask`)
only picks the settings, the nominal dynamics and the cache, and calls
:func:`drone_planner`.

- :class:`DronePlannerSettings`, :data:`PLANNER_DEFAULTS`: the planner's settings (a run's
  ``solver.planner`` overrides them).
- :func:`check_planner_settings`: refuses settings and cost bases the planner cannot use.
- :func:`drone_grid_values`: per drone, the terminal values on a grid of the room.
- :func:`drone_planner`: the :class:`~dicrl_torch.solvers.planning.CrossEntropyPlanner`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dicrl_torch.checks import InvalidSetting, setting_number
from dicrl_torch.envs.drones import ROOM_SIZE, in_own_door, nominal_step
from dicrl_torch.features.continuous import ContinuousFeatureBasis
from dicrl_torch.solvers.planning import (
    PLAN_SIZES,
    CrossEntropyPlanner,
    check_plan_sizes,
    grid_values,
)

__all__ = ["PLANNER_DEFAULTS", "DronePlannerSettings", "check_planner_settings",
           "drone_grid_values", "drone_planner"]


@dataclass(frozen=True)
class DronePlannerSettings:
    """``eval_policy="plan"``'s settings, checked on construction (docs/drones.md,
    "Planning on the learned game"); the defaults: 3 s planned in 6 held commands,
    re-planned every step, 4 rounds of 256 plans; learned cells grown by 0.1 m; the
    terminal value on a 0.25 m grid.

    Attributes:
        horizon, knot, replan, samples, iterations, elites: the cross-entropy planner's
            sizes (:func:`~dicrl_torch.solvers.planning.check_plan_sizes`).
        margin: metres the learned cells (and the proximity) are grown by, in [0, 0.5).
        grid_step: metres between the terminal value's grid centres, in (0, 1], with
            ``margin + grid_step / 2`` below half a cell.

    Raises:
        InvalidSetting: a setting out of range, naming it.
    """

    horizon: int = 30
    knot: int = 5
    replan: int = 1
    samples: int = 256
    iterations: int = 4
    elites: int = 25
    margin: float = 0.1
    grid_step: float = 0.25

    def __post_init__(self) -> None:
        check_plan_sizes(**{k: getattr(self, k) for k in PLAN_SIZES})
        setting_number("margin", self.margin, low=0, high=0.5, high_open=True, example=0.1,
                       why="metres the learned cells are grown by")
        setting_number("grid_step", self.grid_step, low=0, high=1, low_open=True,
                       example=0.25, why="metres between the grid value's centres")
        if not self.margin + self.grid_step / 2 < 0.5:
            # grid_values forbids a centre whose cell grown by both touches a learned one
            raise InvalidSetting(
                "grid_step", self.grid_step, f"a number in (0, 1] with {{margin}}="
                f"{self.margin:g} + half of it below half a cell (0.5 m)", 0.25)


PLANNER_DEFAULTS: dict[str, Any] = dataclasses.asdict(DronePlannerSettings())
""":class:`DronePlannerSettings`' defaults as a dict (a run's ``solver.planner`` overrides
them key by key)."""


def check_planner_settings(cost_basis, settings: dict[str, Any]) -> None:
    """Refuse, before any training, a planner that could not run: ``settings`` (the
    defaults updated by the run's) out of range (:class:`DronePlannerSettings`), or a
    cost basis whose cells cannot be grown by a margin."""
    if not (isinstance(cost_basis, ContinuousFeatureBasis) and cost_basis.dilatable):
        # A plan is refused when it enters a learned constraint: that needs features
        # that are 0 outside their region (cells), which can be grown by the margin.
        raise ValueError(
            f"eval_policy='plan' needs a cost basis of cells that can be grown by a "
            f"margin (dilatable, with dilated(margin), e.g. CellOccupancyCostBasis); "
            f"{type(cost_basis).__name__} has none: set solver.eval_policy=sac.")
    DronePlannerSettings(**settings)


def drone_grid_values(reward_basis: ContinuousFeatureBasis,
                      cost_basis: ContinuousFeatureBasis, eta: np.ndarray,
                      cost_weights: np.ndarray, constraints: np.ndarray, *, n_agents: int,
                      margin: float, grid_step: float, dynamics, gamma: float
                      ) -> list[np.ndarray]:
    """Per drone ``[G, G]`` :func:`~dicrl_torch.solvers.planning.grid_values` of the
    learned game ``(η [l_r + 1], ω_c [l_c])`` on the centres of a ``grid_step`` grid of
    the room: the drone alone, the cells within ``margin + grid_step / 2`` of a learned
    one (``constraints [l_c]`` bool) forbidden, its door absorbing; ``dynamics`` (the
    nominal one) sets the travel time between centres."""
    step = grid_step
    G = int(round(ROOM_SIZE / step))
    centres = (np.arange(G) + 0.5) * step
    gx, gy = np.meshgrid(centres, centres, indexing="xy")  # [G, G], row = y
    n = n_agents
    shares_r = reward_basis.agent_shares().numpy()
    shares_c = cost_basis.agent_shares().numpy()
    # Cells within half a grid step (and the margin) of a learned one are forbidden.
    reach = margin + step / 2
    wide = cost_basis.dilated(reach) if reach else cost_basis
    values = []
    for d in range(n):
        # Drone d at each centre, the others far outside the room, where no position
        # feature and no pair feature (proximity, separation rings) of theirs fires: a
        # cost feature shared by the drones (a unit counting the drones in it) then
        # holds drone d's part alone, and the pair features are left to the planner.
        # The reward keeps drone d's own features only.
        states = np.zeros((G * G, n, 4))
        states[:, :, :2] = -10.0 * ROOM_SIZE
        states[:, d, 0], states[:, d, 1] = gx.ravel(), gy.ravel()
        own_r, own_c = shares_r[:, d] == 1, shares_c[:, d] > 0
        phi_r = reward_basis.compute(torch.as_tensor(states)).numpy()
        phi_c = cost_basis.compute(torch.as_tensor(states)).numpy()
        reward = phi_r @ (eta[:-1] * own_r) + float(eta[-1]) * (
            phi_c @ (cost_weights * own_c))
        near = wide.compute(torch.as_tensor(states)).numpy()
        forbidden = (near @ (constraints & own_c)) > 0
        positions = states[..., :2]
        goal = np.asarray(in_own_door(positions))[:, d]
        values.append(grid_values(
            reward.reshape(G, G), forbidden.reshape(G, G), goal.reshape(G, G),
            steps_per_cell=step / (dynamics.max_speed * dynamics.dt),
            gamma=gamma))
    return values


def drone_planner(reward_basis: ContinuousFeatureBasis, cost_basis: ContinuousFeatureBasis,
                  eta: np.ndarray, cost_weights: np.ndarray, constraints: np.ndarray, *,
                  values: list[np.ndarray], settings: dict[str, Any], dynamics,
                  n_agents: int, gamma: float, seeds: Sequence[int]) -> CrossEntropyPlanner:
    """A cross-entropy planner in the nominal arena (``dynamics``:
    :func:`~dicrl_torch.envs.drones.nominal_step`) on the learned reward
    ``ω_r·φ_r + λ ω_c·φ_c``, never entering a learned cell or the proximity grown by
    ``settings["margin"]``; its terminal value is each drone's ``values`` (of
    :func:`drone_grid_values` with the same settings), summed. One planning problem
    (episode) per seed.

    Args:
        reward_basis, cost_basis: the learner's feature bases.
        eta: ``[l_r + 1]`` the learned ``(ω_r, λ)``.
        cost_weights: ``[l_c]`` the learned ``ω_c``.
        constraints: ``[l_c]`` bool, the learned constraints.
        values: per drone ``[G, G]`` terminal values.
        settings: :data:`PLANNER_DEFAULTS` updated by the run's.
        dynamics: the nominal :class:`~dicrl_torch.envs.drones.DroneDynamics`.
        n_agents: drones per problem.
        gamma: discount.
        seeds: one per planning problem.
    """
    wr, lam = eta[:-1], float(eta[-1])
    forbidden = constraints.astype(np.float64)
    grown = (cost_basis.dilated(settings["margin"]) if settings["margin"]
             else cost_basis)
    step = settings["grid_step"]

    def model(states, active, actions):
        return nominal_step(states, actions, active, dynamics=dynamics)

    def reward(states):
        # The bases' numpy paths (ContinuousFeatureBasis: generic, or a basis's faster
        # one, equal bit for bit): thousands of plans' states per step.
        return (reward_basis.numpy_features(states) @ wr
                + lam * cost_basis.dot(states, cost_weights))

    def entered(states):
        return grown.dot(states, forbidden) > 0

    def terminal(states):
        cells = np.clip((states[..., :2] / step).astype(np.int64), 0, len(values[0]) - 1)
        return sum(values[d][cells[:, d, 1], cells[:, d, 0]] for d in range(len(values)))

    return CrossEntropyPlanner(
        step_fn=model, reward_fn=reward, forbidden_fn=entered, terminal_fn=terminal,
        action_shape=(n_agents, 2), gamma=gamma, seed=seeds,
        **{k: settings[k] for k in PLAN_SIZES})
