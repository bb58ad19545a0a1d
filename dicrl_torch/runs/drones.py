"""The drone arena as a run's task (docs/design.md §7, paper §6.2, Table 2).

The same runner and D-ICRL trainer as the grid world drive it; the learner model is
:class:`dicrl_torch.algos.models.SACLearnerModel` (one warm-started SAC solver per
learner). The steps:

1. The demonstrated pairs of the via-point planner, split over the learners.
2. One SAC solver is pre-trained on ``η(0), ω_c(0)`` (``warmup_timesteps``); every
   learner, C-ICRL and the greedy baseline start from a clone of it (all start from the
   same ``η(0)``), so the warm-up is paid once per process (and again on resume: it is
   deterministic, so the resumed run continues the same numbers).
3. D-ICRL (and C-ICRL). A last solve of ``final_timesteps`` on each learner's learned
   ``(η̄, ω_c)`` gives its policy, rolled out ``eval_episodes`` times in the TRUE game
   (violators freeze) with the policy's mean and with sampled actions: SR and CVR.
4. M(C)E-greedy given the reward learned by D-ICRL (learner 1's ``ω_r``), as in the
   paper (the arena's noise is small, so ME and MCE coincide: one row).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.algos.greedy import SACGreedyConstraintInference
from dicrl_torch.algos.models import SACLearnerModel
from dicrl_torch.demos import partition_demonstrations
from dicrl_torch.demos.drone_demos import make_drone_demonstrations, save_drone_demonstrations
from dicrl_torch.envs.drones import render_arena, start_support
from dicrl_torch.metrics import false_negative_rate, false_positive_rate, learned_constraints

DRONE_BASELINE = "M(C)E-greedy"


def derived_seed(seed: int, *keys: int) -> int:
    """An independent stream per purpose (learner, C-ICRL, evaluation) from one seed."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


class DroneTask:
    """The drone arena's run: problem, evaluation, baseline and figures.

    Args:
        solver: an untrained :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` over
            the learners' bases (the warm-up trains it; learners train clones).
        reward_basis, cost_basis: the learners' feature bases (the solver's).
        split: demonstrated pairs per learner.
        seed: seeds the demonstrations, the clones and the evaluation.
        eval_episodes: true-game rollouts per table row.
        eval_action: ``"mean"`` or ``"sampled"``: the actions of the table's SR and CVR.
        timesteps, n_eval_episodes: SAC steps and rollouts per inner solve.
        warmup_timesteps: pre-training steps on ``η(0), ω_c(0)``.
        init_reward_weights, init_multiplier, init_cost_weights: ``η(0)``, ``ω_c(0)``.
        final_timesteps, final_checks, final_restarts, final_score: the last solve on
            each learned ``(η̄, ω_c)`` (see ``SACConstrainedSolver.solve_keeping_best``).
        threshold: ``ω_c,j >= threshold`` marks a learned constraint.
        baseline: run M(C)E-greedy; ``baseline_*``: its settings.
    """

    columns = ("FPR", "FNR", "CVR", "SR")

    def __init__(self, *, solver, reward_basis, cost_basis, split: Sequence[int], seed: int,
                 eval_episodes: int, eval_action: str = "mean", timesteps: int,
                 n_eval_episodes: int, warmup_timesteps: int,
                 init_reward_weights: float, init_multiplier: float,
                 init_cost_weights: float, final_timesteps: int, final_checks: int = 1,
                 final_restarts: int = 1, final_score: str = "learned_success",
                 threshold: float = 0.5, baseline: bool = False,
                 baseline_penalty: float = 10.0, baseline_timesteps: int = 3000,
                 baseline_epsilon: float | None = None,
                 baseline_max_constraints: int | None = None) -> None:
        self.base, self.reward_basis, self.cost_basis = solver, reward_basis, cost_basis
        self.split, self.seed = [int(m) for m in split], int(seed)
        self.eval_episodes, self.eval_action = int(eval_episodes), str(eval_action)
        self.timesteps, self.n_eval_episodes = int(timesteps), int(n_eval_episodes)
        self.warmup_timesteps = int(warmup_timesteps)
        self.eta0 = torch.full((solver.l_r + 1,), float(init_reward_weights),
                               dtype=torch.float64)
        self.eta0[-1] = float(init_multiplier)
        self.cw0 = torch.full((solver.l_c,), float(init_cost_weights), dtype=torch.float64)
        self.final = dict(timesteps=int(final_timesteps), checks=int(final_checks),
                          restarts=int(final_restarts), score=str(final_score))
        self.threshold = float(threshold)
        self.baseline = dict(run=bool(baseline), penalty=float(baseline_penalty),
                             timesteps=int(baseline_timesteps), epsilon=baseline_epsilon,
                             max_constraints=baseline_max_constraints)
        self.true = cost_basis.true_constraints().numpy()
        # The planner flies its pairs in the default arena (30 s): a shorter learner
        # episode limit must not make it fail.
        self.demos = make_drone_demonstrations(sum(self.split),
                                               rng=np.random.default_rng(self.seed))
        self.shards = list(partition_demonstrations(self.demos, self.split))
        self._warm = False
        self._paths: list = []  # rollouts of the row evaluated last (its figure)
        self._greedy: dict[str, SACGreedyConstraintInference] = {}

    # ------------------------------------------------------------------ set-up
    def describe(self) -> str:
        return (f"2 drones, {len(self.split)} learners holding {self.split} demonstrated "
                f"pairs; {self.cost_basis.dim} cost features, {int(self.true.sum())} of them "
                f"true constraints")

    def announce(self, out: Path) -> None:
        save_drone_demonstrations(out / "demos.npz", self.demos)
        print(self.describe(), flush=True)

    def _warmed_base(self):
        """The base solver after its warm-up on ``η(0), ω_c(0)`` (once per process)."""
        if not self._warm and self.warmup_timesteps:
            t0 = time.perf_counter()
            sol = self.base.solve(self.eta0, self.cw0, self.warmup_timesteps)
            print(f"SAC warm-up: {self.warmup_timesteps} steps on η(0) in "
                  f"{time.perf_counter() - t0:.0f} s; in the nominal game "
                  f"{float(sol.reached.double().mean()):.2f} of the drones reach their door "
                  f"and {sol.violation_rate:.2f} cross a true constraint", flush=True)
        self._warm = True
        return self.base

    def learner_model(self, local_ids: Sequence[int], shards: Sequence, stream: int
                      ) -> SACLearnerModel:
        """Each local learner owns a clone of the warmed-up solver, seeded per learner and
        per ``stream`` (0: D-ICRL, 1: C-ICRL), holding its own pairs."""
        base = self._warmed_base()
        solvers = [base.clone(derived_seed(self.seed, 2, stream, v)) for v in local_ids]
        for solver, shard in zip(solvers, shards, strict=True):
            solver.set_demonstrations(shard)  # its own pairs only (solver.demo_fraction)
        return SACLearnerModel(solvers=solvers, timesteps=self.timesteps,
                               n_eval_episodes=self.n_eval_episodes,
                               start_states=start_support())

    # ------------------------------------------------------------------ metrics
    def _rates(self, mask: np.ndarray) -> dict[str, Any]:
        names = [self.cost_basis.names[j] for j in np.flatnonzero(mask)]
        return {"FPR": false_positive_rate(mask, self.true),
                "FNR": false_negative_rate(mask, self.true),
                "n_learned": int(mask.sum()), "constraints": names}

    def outer_metrics(self, trainer: DICRL, rollouts: bool) -> dict[str, list]:
        """FPR and FNR of each local learner's ``ω_c >= threshold`` (no rollouts: a
        true-game evaluation of SAC is a table-row affair)."""
        rates = [self._rates(learned_constraints(w, self.threshold))
                 for w in trainer.state.cost_weights]
        return {"FPR": [r["FPR"] for r in rates], "FNR": [r["FNR"] for r in rates]}

    def _evaluate_true_game(self, solver) -> dict:
        """SR and CVR of the solver's current policy in the TRUE game, on common random
        numbers (the same episode seeds for every row and both action modes). ``mean``
        flies the policy's mean action (how an SAC policy is deployed), ``sampled`` the
        stochastic MCE policy itself; the row holds both, SR and CVR are
        ``eval_action``'s."""
        evs = {mode: solver.evaluate(self.eval_episodes, deterministic=mode == "mean",
                                     true_game=True, trajectories=True,
                                     rng=np.random.default_rng(derived_seed(self.seed, 3)))
               for mode in ("mean", "sampled")}
        row: dict[str, Any] = {"CR_mean": None, "CR_std": None, "RFD": None}
        for mode, ev in evs.items():
            row[f"SR_{mode}"], row[f"CVR_{mode}"] = ev.success_rate, ev.violation_rate
        shown = evs[self.eval_action]
        row.update(SR=shown.success_rate, CVR=shown.violation_rate)
        self._paths = shown.paths
        return row

    def evaluate_learner(self, trainer: DICRL, i: int, progress: bool = True) -> dict:
        """A last solve on the learned ``(η̄, ω_c)``, then the true-game row."""
        eta, cw = trainer.state.eta_bar[i], trainer.state.cost_weights[i]
        mask = learned_constraints(cw, self.threshold)
        solver = trainer.learner_model.inner_solver(i)
        f = self.final
        kept = solver.solve_keeping_best(
            eta, cw, f["timesteps"], checks=f["checks"], restarts=f["restarts"],
            deterministic=self.eval_action == "mean",
            constraints=mask if f["score"] == "learned_success" else None)
        row = self._evaluate_true_game(solver)
        row.update(self._rates(mask), multiplier=float(eta[-1]),
                   reward_weights=eta[:-1].tolist(), policy_timesteps=kept.timesteps,
                   final_checks=solver.last_checks)
        return row

    def evaluation_settings(self) -> dict[str, Any]:
        return {"threshold": self.threshold, "eval_episodes": self.eval_episodes,
                "eval_action": self.eval_action, **{f"final_{k}": v
                                                    for k, v in self.final.items()}}

    def row_scalars(self, row: dict) -> list[tuple[str, float, int]]:
        """The last solve's chunk scores, per restart (``final/...``)."""
        out = []
        for check in row.get("final_checks") or ():
            suffix = f"/restart{check['restart']}" if check["restart"] else ""
            for key in ("penalised_return", "success_under_constraints"):
                if check[key] is not None:
                    out.append((f"final/{key}{suffix}", check[key], check["timesteps"]))
        return out

    def constraint_map(self, label: str, row: dict) -> np.ndarray:
        """Fig. 3c: the learned constraint cells (hatched) and up to 9 rollouts of the row
        evaluated last (none for a row taken from a checkpoint)."""
        mask = np.zeros(len(self.true), dtype=bool)
        mask[[self.cost_basis.names.index(n) for n in row["constraints"]]] = True
        # The rollouts' joint states [L+1, 2, 4]: the drones' positions are columns 0-1.
        paths, self._paths = [p[:, :, :2] for p in self._paths[:9]], []
        return render_arena(trajectories=paths, constraint_cells=mask,
                            title=f"{label}: learned constraints (hatched) and "
                                  f"{len(paths)} rollouts")

    def reference_rows(self) -> dict[str, dict]:
        """The demonstrations themselves (flown in the true game): SR 1, CVR 0 by design."""
        return {"Experts (ground truth)": {"CR_mean": None, "CR_std": None, "RFD": None,
                                           "FPR": None, "FNR": None, "SR": 1.0, "CVR": 0.0}}

    # ------------------------------------------------------------------ baseline
    def make_baselines(self, methods: dict[str, dict], progress: bool = True) -> dict:
        """M(C)E-greedy given D-ICRL's learned reward (learner 1's ω_r), on all pairs (the
        paper's protocol); nothing before D-ICRL has a row."""
        b = self.baseline
        if not b["run"] or "D-ICRL" not in methods:
            return {}
        greedy = SACGreedyConstraintInference(
            solver=self._warmed_base().clone(derived_seed(self.seed, 4)),
            reward_weights=torch.tensor(methods["D-ICRL"]["learners"][0]["reward_weights"],
                                        dtype=torch.float64),
            demonstrations=self.demos, penalty=b["penalty"], timesteps=b["timesteps"],
            epsilon=b["epsilon"], max_constraints=b["max_constraints"], progress=progress)
        self._greedy = {DRONE_BASELINE: greedy}
        return dict(self._greedy)

    def baseline_row(self, name: str, result) -> tuple[dict, list[dict]]:
        mask = result.constraint_mask.numpy()
        row = self._evaluate_true_game(self._greedy[name].solver)
        row.update(self._rates(mask), stop_reason=result.stop_reason)
        history, sel = [], np.zeros_like(mask)
        for k, ll in enumerate(result.log_likelihood):
            if k:
                sel[result.added[k - 1]] = True
            rates = self._rates(sel)
            history.append({"step": k, "added": result.added_names[k - 1] if k else None,
                            "log_likelihood": ll, "FPR": rates["FPR"], "FNR": rates["FNR"]})
        return row, history

    def annotate(self, methods: dict) -> dict | None:
        """No identifiability classes for the arena: they need a SAC solve per feature."""
        return None

    # ------------------------------------------------------------------ figures
    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """Fig. 3b: the demonstrations and the true constraint cells."""
        return {"fig3b_demonstrations": render_arena(
            trajectories=[s[:, :, :2] for s in self.demos.states], constraint_cells=self.true,
            title="Demonstrations and the true constraint cells")}
