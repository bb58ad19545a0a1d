"""The drone arena as a run's task (docs/design.md §7, paper §6.2, Table 2).

The same runner and D-ICRL trainer as the grid world drive it. :class:`DroneTask` is a
:class:`~dicrl_torch.runs.continuous.SACTask` (the learner model, the warm-up, the
evaluation and the baseline are every continuous game's); what it adds is the arena's:
the via-point planner's demonstrations, the arena's constraint map, the experts' row and
Fig. 3b. The steps:

1. The demonstrated pairs of the via-point planner, split over the learners.
2. One SAC solver is pre-trained on ``η(0), ω_c(0)`` (``warmup_timesteps``); every
   learner, C-ICRL and the greedy baseline start from a clone of it (all start from the
   same ``η(0)``), so the warm-up is paid once per process (and again on resume: it is
   deterministic, so the resumed run continues the same numbers).
3. D-ICRL (and C-ICRL). A last solve of ``final_timesteps`` on each learner's learned
   ``(η̄, ω_c)`` gives its policy, rolled out ``eval_episodes`` times in the TRUE game
   (violators freeze) with the policy's mean and with sampled actions: SR and CVR. With
   ``eval_policy="plan"`` there is no last solve: each learner acts by planning on its
   learned game in the nominal arena (:meth:`DroneTask.make_planner`).
4. M(C)E-greedy given the reward learned by D-ICRL (learner 1's ``ω_r``), as in the
   paper (the arena's noise is small, so ME and MCE coincide: one row).

The planner itself (its settings, their checks, the grid values and the cross-entropy
planner on the learned game) is the arena's solver, :mod:`dicrl_torch.solvers.drone_planning`;
this task only picks the settings and the nominal dynamics and caches the grid values.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dicrl_torch.demos.drone_demos import make_drone_demonstrations, save_drone_demonstrations
from dicrl_torch.envs.drones import DroneDynamics, render_arena, start_support
from dicrl_torch.envs.drones.geometry import PROXIMITY_RADIUS, ROOM_SIZE, in_obstacle, too_close
from dicrl_torch.metrics import true_constraints_of
from dicrl_torch.region import RegionTruth
from dicrl_torch.runs.continuous import GREEDY_BASELINE, SACTask, derived_seed
from dicrl_torch.runs.results import REGION_COLUMNS
from dicrl_torch.runs.task import Rollouts
from dicrl_torch.solvers.drone_planning import (
    PLANNER_DEFAULTS,
    check_planner_settings,
    drone_grid_values,
    drone_planner,
)
from dicrl_torch.solvers.planning import CrossEntropyPlanner

__all__ = ["DRONE_BASELINE", "PLANNER_DEFAULTS", "DroneTask", "derived_seed"]

# The arena is (nearly) deterministic, so ME and MCE coincide: the one greedy row.
DRONE_BASELINE = GREEDY_BASELINE


class DroneTask(SACTask):
    """The drone arena's run: problem, evaluation, baseline and figures (the evaluation
    and the baseline are :class:`~dicrl_torch.runs.continuous.SACTask`'s).

    Args:
        solver: an untrained :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` over
            the learners' bases (the warm-up trains it; learners train clones).
        reward_basis, cost_basis: the learners' feature bases (the solver's); the cost
            basis gives the true constraints.
        split: demonstrated pairs per learner.
        seed: seeds the demonstrations, the clones and the evaluation.
        final_score: the last solve's score (``"learned_success"`` here).
        dynamics: the arena's :class:`~dicrl_torch.envs.drones.DroneDynamics`, the
            solver's env's; the planner flies the demonstrations in it (default: the
            default dynamics).
        **settings: the rest of :class:`~dicrl_torch.runs.continuous.SACTask`'s
            (``eval_episodes``, ``eval_action``, ``timesteps``, ``n_eval_episodes``,
            ``warmup_timesteps``, ``η(0)``, ``ω_c(0)``, the last solve, ``threshold``,
            ``baseline*``).
    """

    columns = ("FPR", "FNR", *REGION_COLUMNS, "CVR", "SR")
    can_plan = True  # make_planner: the nominal arena's dynamics
    game = "drones"
    # make_planner's caches: the nominal dynamics (one env read, not one per episode)
    # and the grid values of the last learned game planned on (every episode shares them).
    _nominal_model = None
    _grid_cache: tuple = (None, None)

    def __init__(self, *, solver, reward_basis, cost_basis, split: Sequence[int], seed: int,
                 final_score: str = "learned_success", dynamics=None, **settings) -> None:
        # The settings before the planner's pairs, which take seconds.
        self.check_settings(split=split, seed=seed, final_score=final_score, **settings)
        # The planner flies its pairs with the learners' dynamics, for the arena's
        # default 30 s: a shorter learner episode limit must not make it fail.
        self.drone_demos = make_drone_demonstrations(
            sum(int(m) for m in split), rng=np.random.default_rng(int(seed)),
            dynamics=dynamics)
        super().__init__(solver=solver, demos=self.drone_demos, split=split, seed=seed,
                         true_constraints=true_constraints_of(cost_basis),
                         final_score=final_score, start_states=start_support(), **settings)
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        self.dynamics = DroneDynamics() if dynamics is None else dynamics
        if self.eval_policy == "plan":
            # now rather than after training, where the evaluation builds the planner
            check_planner_settings(cost_basis, {**PLANNER_DEFAULTS, **self.planner_settings})

    def region_truth(self) -> RegionTruth:
        """The true game's violations as a function of a joint state (both drones
        flying): a drone inside an obstacle, or the two closer than the proximity radius
        (as :func:`~dicrl_torch.envs.drones.joint_step` checks them); states over the
        room, velocities up to the dynamics' velocity bound."""

        def forbidden(states: np.ndarray) -> np.ndarray:
            pos = states[..., :2]
            return in_obstacle(pos).any(-1) | too_close(pos, PROXIMITY_RADIUS)

        return RegionTruth(forbidden=forbidden, low=(0.0, 0.0), high=(ROOM_SIZE, ROOM_SIZE),
                           max_speed=float(self.dynamics.vel_limit), n_agents=2,
                           kinds=("obstacle", "proximity"))

    # ------------------------------------------------------------------ planning
    def make_planner(self, eta: np.ndarray, cost_weights: np.ndarray, constraints: np.ndarray,
                     seeds: Sequence[int]) -> CrossEntropyPlanner:
        """A cross-entropy planner in the nominal arena on the learned game
        (:func:`~dicrl_torch.solvers.drone_planning.drone_planner`, with the learner's env's
        dynamics and this run's settings). One planning problem (episode) per seed."""
        settings = {**PLANNER_DEFAULTS, **self.planner_settings}
        if self._nominal_model is None:
            arena = self.base.env_factory(constrained=False).arena
            self._nominal_model = arena.dynamics
        dynamics = self._nominal_model
        values = self._grid_values(eta, cost_weights, constraints, settings, dynamics)
        return drone_planner(
            self.reward_basis, self.cost_basis, eta, cost_weights, constraints,
            values=values, settings=settings, dynamics=dynamics,
            n_agents=self.base.spec.n_agents, gamma=self.base.gamma, seeds=seeds)

    def _grid_values(self, eta, cost_weights, constraints, settings, dynamics) -> list:
        """Per drone ``[G, G]``
        :func:`~dicrl_torch.solvers.drone_planning.drone_grid_values` of the learned game
        (cached for the last weights: every episode's planner shares them)."""
        key = (eta.tobytes(), cost_weights.tobytes(), constraints.tobytes(),
               tuple(sorted(settings.items())))
        if self._grid_cache[0] == key:
            return self._grid_cache[1]
        values = drone_grid_values(
            self.reward_basis, self.cost_basis, eta, cost_weights, constraints,
            n_agents=self.base.spec.n_agents, margin=settings["margin"],
            grid_step=settings["grid_step"], dynamics=dynamics, gamma=self.base.gamma)
        self._grid_cache = (key, values)
        return values

    # ------------------------------------------------------------------ set-up
    def describe(self) -> str:
        truth = ("no per-feature ground truth (the region scores say what is recovered)"
                 if self.true is None else f"{int(self.true.sum())} of them true constraints")
        return (f"2 drones, {len(self.split)} learners holding {self.split} demonstrated "
                f"pairs; {self.cost_basis.dim} cost features, {truth}")

    def announce(self, out: Path) -> None:
        """As :meth:`SACTask.announce`, saving the planner's pairs
        (``DroneDemonstrations``) as ``demos.npz``."""
        self.check_expressive()
        save_drone_demonstrations(Path(out) / "demos.npz", self.drone_demos)
        print(self.describe(), flush=True)
        self.print_expressivity()

    def warmup_summary(self, solution) -> str:
        return (f"{float(solution.reached.double().mean()):.2f} of the drones reach their "
                f"door and {solution.violation_rate:.2f} cross a true constraint")

    # ------------------------------------------------------------------ pictures
    def constraint_map(self, label: str, row: dict, rollouts: Rollouts = ()) -> np.ndarray:
        """Fig. 3c: the learned constraint cells (hatched) and up to 9 of the row's
        ``rollouts`` (joint states ``[L+1, 2, 4]``; none for a row taken from a
        checkpoint)."""
        mask = self.learned_mask(row)
        paths = [p[:, :, :2] for p in list(rollouts)[:9]]  # the drones' positions
        if self.true is None:  # not cells: the region maps (figures) show the learned set
            return render_arena(trajectories=paths, title=f"{label}: {len(paths)} rollouts")
        return render_arena(trajectories=paths, constraint_cells=mask,
                            title=f"{label}: learned constraints (hatched) and "
                                  f"{len(paths)} rollouts")

    def reference_rows(self) -> dict[str, dict]:
        """The demonstrations themselves (flown in the true game): SR 1, CVR 0 by design."""
        return {"Experts (ground truth)": {"CR_mean": None, "CR_std": None, "RFD": None,
                                           "FPR": None, "FNR": None, "SR": 1.0, "CVR": 0.0}}

    def annotate(self, methods: dict) -> dict | None:
        """No identifiability classes for the arena: they need a SAC solve per feature."""
        return None

    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """Fig. 3b: the demonstrations and the true constraint cells; the cost weights'
        curves."""
        images = super().figures(methods=methods, histories=histories,
                                 experiment=experiment, eval_every=eval_every)
        images["fig3b_demonstrations"] = render_arena(
            trajectories=[s[:, :, :2] for s in self.drone_demos.states],
            constraint_cells=self.true,
            title="Demonstrations" + ("" if self.true is None
                                      else " and the true constraint cells"))
        return images
