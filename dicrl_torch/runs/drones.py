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
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from dicrl_torch.demos.drone_demos import make_drone_demonstrations, save_drone_demonstrations
from dicrl_torch.envs.drones import (
    ROOM_SIZE,
    in_own_door,
    nominal_step,
    render_arena,
    start_support,
)
from dicrl_torch.runs.continuous import GREEDY_BASELINE, SACTask, derived_seed
from dicrl_torch.solvers.planning import (
    PLAN_SIZES,
    CrossEntropyPlanner,
    check_plan_sizes,
    grid_values,
)

__all__ = ["DRONE_BASELINE", "PLANNER_DEFAULTS", "DroneTask", "derived_seed"]

PLANNER_DEFAULTS = {"horizon": 30, "knot": 5, "replan": 1, "samples": 256, "iterations": 4,
                    "elites": 25, "margin": 0.1, "grid_step": 0.25}
"""``eval_policy="plan"``'s settings (docs/drones.md, "Planning on the learned game"): 3 s
planned in 6 held commands, re-planned every step, 4 rounds of 256 plans; learned cells
grown by 0.1 m; the terminal value on a 0.25 m grid."""


def _features(basis, states: np.ndarray) -> np.ndarray:
    """``[..., l]`` ``basis(states)`` of numpy states: the basis's fast numpy path where
    it has one (``numpy_features``, equal bit for bit)."""
    if callable(getattr(basis, "numpy_features", None)):
        return basis.numpy_features(states)
    return basis.compute(torch.as_tensor(states)).numpy()


def _weighted(basis, states: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``[...]`` ``basis(states) @ weights``: the basis's fast ``dot`` where it has one."""
    if callable(getattr(basis, "dot", None)):
        return basis.dot(states, weights)
    return _features(basis, states) @ weights

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

    game = "drones"

    def __init__(self, *, solver, reward_basis, cost_basis, split: Sequence[int], seed: int,
                 final_score: str = "learned_success", dynamics=None, **settings) -> None:
        # The planner flies its pairs with the learners' dynamics, for the arena's
        # default 30 s: a shorter learner episode limit must not make it fail.
        self.drone_demos = make_drone_demonstrations(
            sum(int(m) for m in split), rng=np.random.default_rng(int(seed)),
            dynamics=dynamics)
        super().__init__(solver=solver, demos=self.drone_demos, split=split, seed=seed,
                         true_constraints=cost_basis.true_constraints().numpy(),
                         final_score=final_score, start_states=start_support(), **settings)
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        if self.eval_policy == "plan":
            if not callable(getattr(cost_basis, "dilated", None)):
                # A plan is refused when it enters a learned constraint: that needs features
                # that are 0 outside their region (cells), which can be grown by the margin.
                raise ValueError(
                    f"eval_policy='plan' needs a cost basis of cells that can be grown by a "
                    f"margin (dilated(margin), e.g. CellOccupancyCostBasis); "
                    f"{type(cost_basis).__name__} has none: set solver.eval_policy=sac.")
            plan = {**PLANNER_DEFAULTS, **self.planner_settings}
            # now rather than after training, where the evaluation builds the planner
            check_plan_sizes(**{k: plan[k] for k in PLAN_SIZES})
            if not plan["margin"] + plan["grid_step"] / 2 < 0.5:
                # grid_values forbids a centre whose cell grown by both touches a learned one
                raise ValueError(
                    f"planner margin {plan['margin']} + grid_step {plan['grid_step']} / 2 must "
                    f"stay below half a cell (0.5 m); lower solver.planner.grid_step.")

    # ------------------------------------------------------------------ planning
    def make_planner(self, eta: np.ndarray, cost_weights: np.ndarray, constraints: np.ndarray,
                     seeds: Sequence[int]) -> CrossEntropyPlanner:
        """A cross-entropy planner in the nominal arena (the learner's env's dynamics:
        :func:`~dicrl_torch.envs.drones.nominal_step`) on the learned reward
        ``ω_r·φ_r + λ ω_c·φ_c``, never entering a learned cell or the proximity grown by
        ``margin``; its terminal value is each drone's
        :func:`~dicrl_torch.solvers.planning.grid_values` (alone in the room, the learned
        cells forbidden, its door absorbing), summed. One planning problem (episode) per
        seed."""
        settings = {**PLANNER_DEFAULTS, **self.planner_settings}
        if getattr(self, "_nominal_model", None) is None:  # one env read, not one per episode
            arena = self.base.env_factory(constrained=False).arena
            self._nominal_model = arena.dynamics
        dynamics = self._nominal_model
        wr, lam = eta[:-1], float(eta[-1])
        forbidden = constraints.astype(np.float64)
        grown = (self.cost_basis.dilated(settings["margin"]) if settings["margin"]
                 else self.cost_basis)
        values = self._grid_values(eta, cost_weights, constraints, settings, dynamics)
        step = settings["grid_step"]

        def model(states, active, actions):
            return nominal_step(states, actions, active, dynamics=dynamics)

        def reward(states):
            return (_features(self.reward_basis, states) @ wr
                    + lam * _weighted(self.cost_basis, states, cost_weights))

        def entered(states):
            return _weighted(grown, states, forbidden) > 0

        def terminal(states):
            cells = np.clip((states[..., :2] / step).astype(np.int64), 0, len(values[0]) - 1)
            return sum(values[d][cells[:, d, 1], cells[:, d, 0]] for d in range(len(values)))

        return CrossEntropyPlanner(
            step_fn=model, reward_fn=reward, forbidden_fn=entered, terminal_fn=terminal,
            action_shape=(self.base.spec.n_agents, 2), gamma=self.base.gamma, seed=seeds,
            **{k: settings[k] for k in PLAN_SIZES})

    def _grid_values(self, eta, cost_weights, constraints, settings, dynamics) -> list:
        """Per drone ``[G, G]`` :func:`grid_values` of the learned game (cached for the
        last weights: every episode's planner shares them)."""
        key = (eta.tobytes(), cost_weights.tobytes(), constraints.tobytes(),
               tuple(sorted(settings.items())))
        if getattr(self, "_grid_cache", (None,))[0] == key:
            return self._grid_cache[1]
        step = settings["grid_step"]
        G = int(round(ROOM_SIZE / step))
        centres = (np.arange(G) + 0.5) * step
        gx, gy = np.meshgrid(centres, centres, indexing="xy")  # [G, G], row = y
        n = self.base.spec.n_agents
        shares_r = self.reward_basis.agent_shares().numpy()
        shares_c = self.cost_basis.agent_shares().numpy()
        # Cells within half a grid step (and the margin) of a learned one are forbidden.
        reach = settings["margin"] + step / 2
        wide = self.cost_basis.dilated(reach) if reach else self.cost_basis
        values = []
        for d in range(n):
            # Drone d at each centre, the others at the origin; only drone d's own
            # features count (a shared one, the proximity, is left to the planner).
            states = np.zeros((G * G, n, 4))
            states[:, d, 0], states[:, d, 1] = gx.ravel(), gy.ravel()
            own_r, own_c = shares_r[:, d] == 1, shares_c[:, d] == 1
            phi_r = self.reward_basis.compute(torch.as_tensor(states)).numpy()
            phi_c = self.cost_basis.compute(torch.as_tensor(states)).numpy()
            reward = phi_r @ (eta[:-1] * own_r) + float(eta[-1]) * (
                phi_c @ (cost_weights * own_c))
            near = wide.compute(torch.as_tensor(states)).numpy()
            forbidden = (near @ (constraints & own_c)) > 0
            positions = states[..., :2]
            goal = np.asarray(in_own_door(positions))[:, d]
            values.append(grid_values(
                reward.reshape(G, G), forbidden.reshape(G, G), goal.reshape(G, G),
                steps_per_cell=step / (dynamics.max_speed * dynamics.dt),
                gamma=self.base.gamma))
        self._grid_cache = (key, values)
        return values

    # ------------------------------------------------------------------ set-up
    def describe(self) -> str:
        return (f"2 drones, {len(self.split)} learners holding {self.split} demonstrated "
                f"pairs; {self.cost_basis.dim} cost features, {int(self.true.sum())} of them "
                f"true constraints")

    def announce(self, out: Path) -> None:
        """Prints :meth:`describe` and saves the planner's pairs (``DroneDemonstrations``)
        as ``demos.npz``."""
        save_drone_demonstrations(Path(out) / "demos.npz", self.drone_demos)
        print(self.describe(), flush=True)

    def warmup_summary(self, solution) -> str:
        return (f"{float(solution.reached.double().mean()):.2f} of the drones reach their "
                f"door and {solution.violation_rate:.2f} cross a true constraint")

    # ------------------------------------------------------------------ pictures
    def constraint_map(self, label: str, row: dict) -> np.ndarray:
        """Fig. 3c: the learned constraint cells (hatched) and up to 9 rollouts of the row
        evaluated last (none for a row taken from a checkpoint)."""
        mask = self.learned_mask(row)
        # The rollouts' joint states [L+1, 2, 4]: the drones' positions are columns 0-1.
        paths, self._paths = [p[:, :, :2] for p in self._paths[:9]], []
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
            constraint_cells=self.true, title="Demonstrations and the true constraint cells")
        return images
