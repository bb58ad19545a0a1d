"""The multi-expert grid world as a run's task (docs/design.md §3, paper §6.1, Table 1).

:class:`GridTask` holds what every process of a run rebuilds identically from its seed:
the learners' model, the experts (optimal or soft-optimal in the true CMG), the
demonstrations (sampled, or read from the learners' own files) and their shards; and it
answers what :mod:`dicrl_torch.runs.runner` asks of a task: learner models, per-iteration
metrics, table rows, the greedy baselines, the reference rows and the paper's Fig. 2.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.algos.greedy import GreedyConstraintInference, GreedyResult
from dicrl_torch.algos.identifiability import (
    CERTIFICATE_MIN_PROBABILITY,
    CERTIFICATE_TEMPERATURE,
    Identifiability,
    certify_constraints,
    check_indicator_basis,
    classify_features,
    demonstrated_mask,
    fnr_required,
)
from dicrl_torch.algos.models import TabularLearnerModel
from dicrl_torch.demos import load_demonstrations, partition_demonstrations, save_demonstrations
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.figures import (
    constraint_cells,
    identifiability_figure,
    metric_curves,
    obstacle_cells,
    side_by_side,
    state_visitation,
    visitation_heatmap,
)
from dicrl_torch.metrics import (
    false_negative_rate,
    false_positive_rate,
    learned_constraints,
    reward_function_distance,
    rollout_true_cmg,
    true_constraints_of,
)
from dicrl_torch.runs.grid_regions import GridRegionScoring
from dicrl_torch.runs.results import REGION_COLUMNS, column_header
from dicrl_torch.runs.settings import GRID_BASELINES, GridSettings, with_defaults
from dicrl_torch.runs.task import Rollouts, Task
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories

# What GridTask.annotate adds to every learned row (null where it cannot be computed): the
# identifiability of the basis' true constraints, and the required obstacles' recall.
IDENTIFIABILITY_KEYS = ("FNR_required", "n_demonstrated", "n_required", "n_undetermined",
                        "contradictions")
ANNOTATIONS = (*IDENTIFIABILITY_KEYS, "obstacle_recall_required",
               "obstacle_recall_required_bound")


def constraint_names(names: Sequence[str], learned) -> list[str]:
    """Names of the features in the learned mask ``[d]`` bool (tensor or array): kept in
    the table rows, so that the figures of a distributed run, drawn by one process, know
    every learner's constraints."""
    return [name for name, on in zip(names, np.asarray(learned).tolist(), strict=True) if on]


@dataclass(frozen=True)
class GridEvaluation:
    """What evaluating a grid policy needs: rollouts in the TRUE CMG (violators stop)
    with common random numbers, and the ground truth the metrics compare with.

    Attributes:
        model: the learners' tabular model (dynamics, horizon, start).
        layout: the true constraints.
        reward_table: ``[N, S1]`` each expert's true reward in each cell.
        episodes: evaluation episodes per row.
        seed: the rollouts' seed (every row is rolled out with the same random numbers).
        true_reward_weights: ``[l_r]`` ω_rE (RFD).
        true_constraints: ``[d]`` bool, the true constraint features of the cost basis;
            None for a basis without a ground truth (FPR/FNR are then null).
    """

    model: TabularGridModel
    layout: GridLayout
    reward_table: torch.Tensor
    episodes: int
    seed: int
    true_reward_weights: torch.Tensor
    true_constraints: np.ndarray | None

    def rollout(self, policy) -> dict[str, float]:
        """``CR_mean``, ``CR_std`` and ``CVR`` of ``policy`` (``policy_at``): a row depends
        neither on the process that evaluates it nor on the rows evaluated before it."""
        ev = rollout_true_cmg(policy=policy, model=self.model, layout=self.layout,
                              reward_table=self.reward_table, n_episodes=self.episodes,
                              rng=torch.Generator().manual_seed(self.seed))
        return {"CR_mean": ev.cr_mean, "CR_std": ev.cr_std, "CVR": ev.cvr}

    def rates(self, learned) -> dict[str, float | None]:
        """``FPR`` and ``FNR`` of the learned mask ``[d]``."""
        return {"FPR": false_positive_rate(learned, self.true_constraints),
                "FNR": false_negative_rate(learned, self.true_constraints)}


def load_shard_files(files: Sequence[str], split: Sequence[int], model: TabularGridModel,
                     read: Sequence[int] | None = None) -> list[Demonstrations | None]:
    """Learner ``v``'s demonstrations from ``files[v]``, checked against the learners' model
    (cells, actions, experts, horizon, starts where P0 has mass) and ``split``, before any
    solve.

    Args:
        read: the learners whose files are read (default: all); the others' entries are None.

    Raises:
        ValueError: naming the file, what does not match and the fix.
    """
    read = list(range(len(files))) if read is None else list(read)
    shards: list[Demonstrations | None] = [None] * len(files)
    for v in read:
        shards[v] = load_demonstrations(files[v], n_cells=model.n_cells,
                                        n_actions=model.n_actions, n_experts=model.n_experts,
                                        horizon=model.horizon)
    if len(read) == len(files):
        counts = [s.n_trajectories for s in shards]
        if counts != list(split):
            raise ValueError(f"shard_files hold {counts} trajectories, but split={list(split)};"
                             f" set split=[{','.join(map(str, counts))}] "
                             f"n_demonstrations={sum(counts)}.")
    for v in read:
        if shards[v].n_trajectories != split[v]:
            raise ValueError(f"demonstrations file '{files[v]}' holds "
                             f"{shards[v].n_trajectories} trajectories, but split[{v}]="
                             f"{split[v]}; set split to the files' trajectory counts.")
    # [N, S1] bool: where P0 lets each expert start (its start set; one cell when fixed)
    sets = model.layout.start_cell_sets
    allowed = np.zeros((model.n_experts, model.n_cells), dtype=bool)
    for i, cells in enumerate(sets):
        allowed[i, list(cells)] = True
    experts = np.arange(model.n_experts)
    for f, shard in ((files[v], shards[v]) for v in read):
        # A trajectory must start where P0 has mass: one starting elsewhere was recorded
        # on another layout (or start sets), and its likelihood would be 0.
        wrong = np.nonzero(~allowed[experts, shard.states[:, 0]].all(1))[0]
        if wrong.size:
            k = int(wrong[0])
            i = int(np.nonzero(~allowed[experts, shard.states[k, 0]])[0][0])
            xy = model.layout.xy
            where = (f"cell {sets[i][0]} {xy(sets[i][0])}" if len(sets[i]) == 1 else
                     f"one of its {len(sets[i])} start cells {[xy(c) for c in sets[i]]}")
            raise ValueError(f"demonstrations file '{f}': trajectory {k} starts in cells "
                             f"{shard.states[k, 0].tolist()}, where P0 has no mass: expert "
                             f"{i + 1} is there in {xy(int(shard.states[k, 0, i]))}, but this "
                             f"layout starts it in {where}; use demonstrations recorded on "
                             f"this layout, or the env.layout (and its start_regions) they "
                             f"were recorded on.")
    return shards


def concatenate(shards: Sequence[Demonstrations]) -> Demonstrations:
    """All learners' trajectories, in learner order (C-ICRL's and the baselines' data)."""
    return Demonstrations(states=np.concatenate([s.states for s in shards]),
                          actions=np.concatenate([s.actions for s in shards]),
                          n_cells=shards[0].n_cells, n_actions=shards[0].n_actions)


class GridTask(GridRegionScoring, Task):
    """The grid world's run: problem, evaluation, baselines and figures.

    Args:
        layout, model, solver: the true layout, the learners' (nominal) model and its
            factored solver.
        reward_basis, cost_basis: the learners' feature bases.
        true_reward_weights: ``[N · l_r]`` ω_rE in the reward basis' layout.
        expert_solver: the solver of the experts' policies (default ``solver``; a float64
            one on small problems makes the demonstrations exact).
        expert_temperature: 0: optimal experts (ties uniform); > 0 soft-optimal.
        split: trajectories per learner (their sum is the number of demonstrations).
        seed: seeds the demonstrations and the evaluation rollouts.
        eval_episodes: evaluation episodes per table row.
        shard_files: one ``.npz`` per learner instead of sampled demonstrations.
        read_shards: the learners whose files this process reads (default all); a
            learner process of a distributed run reads only its own.
        with_experts: solve the experts' policies (the reference rows and sampling need
            them; a learner process on its own file does not).
        constraint_rule: how a trained learner's row gets its constraint set:
            ``"certificate"`` (:func:`~dicrl_torch.algos.identifiability.certify_constraints`
            on the learner's η̄ and own shard) or ``"threshold"`` (the paper's rule).
            The per-iteration curves always threshold ω_c (a certificate costs a solve
            per unseen feature).
        certificate_temperature, certificate_min_probability: the certificate's.
        certificate_network: the certificate asks what the network knows: its candidates
            are the features no learner's shard accrues, and each must be required under
            every learner's η̄ (:meth:`before_evaluation` exchanges the bitmasks and η̄);
            False: the learner's own shard and η̄ alone.
        certificate_shard_fits: with the network's certificate, each feature must also be
            required under every learner's own-shard fit (``DICRL.shard_fits``: its inner
            process alone from its η̄), exchanged with the η̄: learners whose η̄ agree
            still ask what each shard's own data say. C-ICRL, which pools the shards,
            asks the fit each shard's learner would make from its own η̄.
        threshold: ``ω_c,j >= threshold`` marks a learned constraint (threshold rule).
        prune_min_gain: prune learned constraints the data does not need (nats per
            trajectory), or None to keep them all (threshold rule).
        baselines: greedy rows to run (``"ME-greedy"``, ``"MCE-greedy"``).
        baseline_epsilon, baseline_max_constraints: the greedy's stopping rule.

    Raises:
        InvalidSetting: a setting out of range (checked before anything is solved:
            :class:`~dicrl_torch.runs.settings.GridSettings`), naming it.
        ValueError: a cost basis the certificate cannot use, shard files that do not fit.
    """

    columns = ("CR", "FPR", "FNR", "FNR_required", *REGION_COLUMNS, "obstacle_recall_required",
               "obstacle_FPR", "obstacle_FPR_determined", "CVR", "RFD")

    def __init__(self, *, layout: GridLayout, model: TabularGridModel, solver, reward_basis,
                 cost_basis, true_reward_weights: torch.Tensor, expert_solver=None,
                 expert_temperature: float = 0.0, split: Sequence[int], seed: int,
                 eval_episodes: int, shard_files: Sequence[str] | None = None,
                 read_shards: Sequence[int] | None = None, with_experts: bool = True,
                 constraint_rule: str = "certificate",
                 certificate_temperature: float = CERTIFICATE_TEMPERATURE,
                 certificate_min_probability: float = CERTIFICATE_MIN_PROBABILITY,
                 certificate_network: bool = True, certificate_shard_fits: bool = False,
                 threshold: float = 0.5,
                 prune_min_gain: float | None = None,
                 baselines: Sequence[str] = (), baseline_epsilon: float | None = None,
                 baseline_max_constraints: int | None = None) -> None:
        s = GridSettings(
            split=split, seed=seed, eval_episodes=eval_episodes,
            expert_temperature=expert_temperature, constraint_rule=constraint_rule,
            certificate_temperature=certificate_temperature,
            certificate_min_probability=certificate_min_probability,
            certificate_network=certificate_network,
            certificate_shard_fits=certificate_shard_fits, threshold=threshold,
            prune_min_gain=prune_min_gain, baselines=baselines,
            baseline_epsilon=baseline_epsilon, baseline_max_constraints=baseline_max_constraints)
        self.layout, self.model, self.solver = layout, model, solver
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        self.split = list(s.split)
        if s.constraint_rule == "certificate":
            try:
                check_indicator_basis(cost_basis, model)
            except ValueError as e:
                raise ValueError(f"{e} The certificate needs such a basis; with this one keep "
                                 f"the paper's rule: constraint_rule='threshold' "
                                 f"(algo.constraint_rule=threshold).") from None
        self.constraint_rule = s.constraint_rule
        self.certificate = {"temperature": s.certificate_temperature,
                            "min_probability": s.certificate_min_probability,
                            "network": s.certificate_network,
                            "shard_fits": s.certificate_shard_fits and s.certificate_network,
                            # overlapping features asked about their own support (rows
                            # from before it are evaluated again on resume)
                            "open_overlaps": True}
        self._also_demonstrated: torch.Tensor | None = None
        self._network_rewards: torch.Tensor | None = None
        self.threshold, self.prune_min_gain = s.threshold, s.prune_min_gain
        self.expert_temperature = s.expert_temperature
        self._identifiability: Identifiability | None = None
        self.baseline_names = list(s.baselines)
        self.baseline_epsilon = s.baseline_epsilon
        self.baseline_max_constraints = s.baseline_max_constraints
        self.shard_files = None if shard_files is None else list(shard_files)
        reward_table = reward_basis().weighted(true_reward_weights).local[:, :, 0]
        self.evaluation = GridEvaluation(
            model=model, layout=layout, reward_table=reward_table, episodes=s.eval_episodes,
            seed=s.seed, true_reward_weights=true_reward_weights,
            true_constraints=true_constraints_of(cost_basis))
        self.experts = self.nominal = None
        if with_experts:
            exp_solver = solver if expert_solver is None else expert_solver
            kw = dict(solver=exp_solver, reward_features=reward_basis(),
                      reward_weights=true_reward_weights, temperature=expert_temperature)
            self.experts = expert_solution(**kw)
            self.nominal = expert_solution(**kw, constrained=False)
        if self.shard_files is None:
            if self.experts is None:
                raise ValueError("Sampled demonstrations need the experts: with_experts=True.")
            self.demos: Demonstrations | None = sample_trajectories(
                self.experts, sum(self.split), np.random.default_rng(s.seed))
            self.shards: list[Demonstrations | None] = list(
                partition_demonstrations(self.demos, self.split))
        else:
            self.shards = load_shard_files(self.shard_files, self.split, model, read_shards)
            self.demos = None if None in self.shards else concatenate(self.shards)

    @classmethod
    def check_settings(cls, **settings: Any) -> GridSettings:
        """The checked settings of ``GridTask(**settings, ...)`` (keyword arguments named
        as :class:`~dicrl_torch.runs.settings.GridSettings`' fields; the others at their
        defaults), building nothing: a config's values are checked with it before
        anything is computed.

        Raises:
            InvalidSetting: the first setting out of range, naming it.
        """
        names = [f.name for f in dataclasses.fields(GridSettings)]
        return GridSettings(**with_defaults(cls.__init__, names, settings))

    # ------------------------------------------------------------------ set-up
    def describe(self) -> str:
        sets = self.layout.start_sets
        starts = ("" if sets is None else
                  "; varied starts over " + "×".join(str(len(c)) for c in sets) + " cells")
        return (f"{self.layout.n_experts} experts, {len(self.split)} learners holding "
                f"{self.split} demonstrations; {self.model.n_pairs:,} state-action pairs"
                f"{starts}")

    def announce(self, out: Path) -> None:
        """Save the demonstrations (sampled ones) and check the baselines build."""
        if self.demos is not None and self.shard_files is None:
            save_demonstrations(out / "demos.npz", self.demos)
        self.make_baselines({}, progress=False)  # a baseline that cannot run fails now
        print(self.describe())
        self.check_expressive()
        self.print_expressivity()

    def learner_model(self, local_ids: Sequence[int], shards: Sequence, stream: int
                      ) -> TabularLearnerModel:
        """One stateless exact model serves every learner."""
        return TabularLearnerModel(solver=self.solver, reward_basis=self.reward_basis,
                                   cost_basis=self.cost_basis)

    # ------------------------------------------------------------------ per iteration
    def outer_metrics(self, trainer: DICRL, rollouts: bool) -> dict[str, list]:
        """This outer iteration's metrics of the local learners, lists in local order:
        FPR and FNR (of ``ω_c >= threshold``, before the final pruning) and RFD always;
        CR and CVR when ``rollouts``."""
        ev = self.evaluation
        rates = [ev.rates(learned_constraints(w, self.threshold))
                 for w in trainer.state.cost_weights]
        metrics = {"FPR": [r["FPR"] for r in rates], "FNR": [r["FNR"] for r in rates],
                   "RFD": [reward_function_distance(eta[:-1], ev.true_reward_weights)
                           for eta in trainer.state.eta_bar]}
        if rollouts:
            rows = [ev.rollout(trainer.policy(i).policy_at) for i in range(len(trainer.local))]
            metrics.update(CR=[r["CR_mean"] for r in rows], CVR=[r["CVR"] for r in rows])
        return metrics

    # ------------------------------------------------------------------ table rows
    def before_evaluation(self, trainer: DICRL) -> None:
        """With the certificate of the network (``certificate_network``): the features
        any learner's shard accrues and every learner's reward weights, from one exchange
        of bitmasks and one of η̄ (collectives: the runner calls this on every process)."""
        self._also_demonstrated = self._network_rewards = None
        if self.constraint_rule != "certificate" or not self.certificate["network"]:
            return
        p0 = self.model.initial_distribution()
        masks = torch.stack([demonstrated_mask(cost_basis=self.cost_basis, model=self.model,
                                               demonstrations=shard,
                                               initial_distribution=p0)
                             for shard in trainer.shards])
        self._also_demonstrated = trainer.network_or(masks)
        self._network_rewards = trainer.comm.all_gather(  # ω_r of η̄, without λ: [N_L, l_r]
            trainer.state.eta_bar[:, :-1].contiguous(), "eta", phase="outer")
        if not self.certificate["shard_fits"]:
            return
        if trainer.n_learners == 1 and len(self.shards) > 1 and None not in self.shards:
            # C-ICRL pools the shards: the fit each shard's learner would make from its
            # reward, so that both rows ask the rewards each part of the data supports.
            fits = trainer.shard_fits(folds=self.shards)[:, :-1]
        else:  # each learner's own-shard fit: [N_L, l_r]
            fits = trainer.comm.all_gather(trainer.shard_fits()[:, :-1].contiguous(), "eta",
                                           phase="outer")
        self._network_rewards = torch.cat([self._network_rewards, fits])

    def _other_rewards(self, trainer: DICRL, i: int) -> list:
        """The other learners' learned rewards (:meth:`before_evaluation`), for local
        learner ``i``'s certificate; none without the network's certificate."""
        if self._network_rewards is None:
            return []
        own = trainer.local[i]  # its η̄ is the certificate's own reward; its fit is not
        basis = self.reward_basis()
        return [basis.weighted(w) for v, w in enumerate(self._network_rewards) if v != own]

    def evaluate_learner(self, trainer: DICRL, i: int, progress: bool = True
                         ) -> tuple[dict, Rollouts]:
        """The table row of local learner ``i``: its policy π_{η̄, ω_c} rolled out, and its
        constraint set by ``constraint_rule`` (the threshold rule prunes ω_c first, if
        asked, and the pruned ω_c is the policy's); no rollouts kept (the map shows
        cells, not paths)."""
        ev = self.evaluation
        names = list(self.cost_basis.names)
        raw = learned_constraints(trainer.state.cost_weights[i], self.threshold)
        before = ev.rates(raw)
        extra: dict[str, Any] = {"FPR_before_pruning": before["FPR"],
                                 "FNR_before_pruning": before["FNR"],
                                 "constraint_rule": self.constraint_rule}
        if self.constraint_rule == "certificate":
            cert = certify_constraints(
                solver=self.solver, cost_basis=self.cost_basis,
                reward=self.reward_basis().weighted(trainer.state.eta_bar[i, :-1]),
                demonstrations=trainer.shards[i],
                initial_distribution=self.model.initial_distribution(),
                also_demonstrated=self._also_demonstrated, progress=progress,
                other_rewards=self._other_rewards(trainer, i),
                temperature=self.certificate["temperature"],
                min_probability=self.certificate["min_probability"])
            learned = cert.required.numpy()
            # No wall time in the row: rows must not depend on the machine or its load.
            certified = torch.nonzero(cert.required).flatten().tolist()
            extra.update(certificate_candidates=cert.n_solves,
                         certificate_probability={names[j]: float(cert.probability[j])
                                                  for j in certified})
        else:
            if self.prune_min_gain is not None:
                # The pruned set explains the learner's data to within min_gain nats per
                # trajectory.
                cw, pruned = trainer.prune_constraints(i, self.threshold, self.prune_min_gain,
                                                       progress=progress)
                trainer.state.cost_weights[i] = cw
                extra["pruned"] = len(pruned)
            learned = learned_constraints(trainer.state.cost_weights[i], self.threshold)
        row = ev.rollout(trainer.policy(i).policy_at)
        row.update(extra)
        row.update(ev.rates(learned), **self.region_rates(learned),
                   region_recall_bound=self.recall_bound(trainer.shards[i]),
                   RFD=reward_function_distance(trainer.state.eta_bar[i, :-1],
                                                ev.true_reward_weights),
                   SR=None, multiplier=float(trainer.state.eta_bar[i, -1]),
                   n_learned=int(learned.sum()))
        row["constraints"] = constraint_names(names, learned)
        return row, ()

    def constraint_map(self, label: str, row: dict, rollouts: Rollouts = ()) -> np.ndarray:
        """PNG-ready map of the cells a row's learned set forbids (red crosses: an expert
        there accrues learned cost whatever it does, :meth:`predicted_cells`, whatever
        the basis) over the true obstacles (bright); ``rollouts`` (none are kept) are not
        drawn."""
        heat = np.zeros(self.layout.n_cells)
        heat[obstacle_cells(self.layout)] = 1.0
        return render_grid(self.layout, heat=heat,
                           constraint_cells=self.predicted_cells(self.learned_mask(row)),
                           title=f"{label}: cells the learned set forbids (x)")

    def reference_rows(self) -> dict[str, dict]:
        """The experts' rows: in the true CMG and in the nominal game."""
        rows = {}
        for name, sol in (("Experts (ground truth)", self.experts),
                          ("Experts (nominal)", self.nominal)):
            row = self.evaluation.rollout(sol.policy_at)
            row.update(FPR=None, FNR=None, RFD=0.0, SR=None)
            rows[name] = row
        return rows

    # ------------------------------------------------------------------ baselines
    def make_baselines(self, methods: dict[str, dict], progress: bool = True
                       ) -> dict[str, GreedyConstraintInference]:
        """The requested greedy baselines by row name, built (and so checked: e.g. a cost
        basis that is not non-negative) but not run.

        As in the paper, they are given the TRUE reward and all demonstrations pooled; the
        candidate constraints are the cost basis, the model the learners' solver.
        """
        reward = self.reward_basis().weighted(self.evaluation.true_reward_weights)
        return {name: GreedyConstraintInference(
                    solver=self.solver, reward=reward, cost_basis=self.cost_basis,
                    demonstrations=self.demos, model=GRID_BASELINES[name],
                    epsilon=self.baseline_epsilon, max_constraints=self.baseline_max_constraints,
                    progress=progress)
                for name in self.baseline_names}

    def baseline_row(self, name: str, greedy: GreedyConstraintInference,
                     result: GreedyResult) -> tuple[dict, list[dict], Rollouts]:
        """A finished greedy baseline's table row, its per-step history (FPR, FNR and
        log-likelihood after each constraint added) and no rollouts; ``result`` holds
        all it needs (its policy), ``greedy`` is not read."""
        ev = self.evaluation
        mask = torch.zeros_like(result.constraint_mask)
        history = []
        for k, ll in enumerate(result.log_likelihood):
            if k:
                mask[result.added[k - 1]] = True
            history.append({"step": k, "added": result.added_names[k - 1] if k else None,
                            "log_likelihood": ll,
                            "improvement": result.improvement[k - 1] if k else None,
                            **ev.rates(mask)})
        row = ev.rollout(result.solution.policy_at)
        row.update(ev.rates(result.constraint_mask),
                   **self.region_rates(result.constraint_mask.numpy()), RFD=None, SR=None,
                   n_learned=len(result.added), stop_reason=result.stop_reason)
        row["constraints"] = constraint_names(self.cost_basis.names, result.constraint_mask)
        return row, history, ()

    # ------------------------------------------------------------------ identifiability
    def identifiability(self) -> Identifiability | None:
        """The true constraints classified as demonstrated / required / undetermined from
        every learner's demonstrations (docs/design.md §6; evaluation only: it uses the
        true reward and the experts' model). None without a ground truth or without the
        pooled demonstrations (a learner process on its own file). Computed once: one
        solve per undemonstrated true constraint."""
        true = self.evaluation.true_constraints
        if self._identifiability is None and true is not None and self.demos is not None:
            reward = self.reward_basis().weighted(self.evaluation.true_reward_weights)
            self._identifiability = classify_features(
                solver=self.solver, reward=reward, cost_basis=self.cost_basis,
                demonstrations=self.demos, temperature=self.expert_temperature,
                only=torch.as_tensor(true))
        return self._identifiability

    def annotate(self, methods: dict) -> dict | None:
        """Adds to every learned row ``FNR_required``, the true set's class counts,
        ``contradictions`` (learned constraints a demonstration or P0 accrues) and the
        required obstacles' recall and its bound (:meth:`required_rates`); returns
        ``results.json``'s ``identifiability`` record (None where it does not apply)."""
        ident = self.identifiability()
        for m in methods.values():
            for v, row in enumerate(m["learners"]):
                if "constraints" not in row:  # reference rows learn nothing
                    continue
                # D-ICRL's rows hold one shard each; C-ICRL and the baselines all of them
                shard = self.shards[v] if len(m["learners"]) > 1 else self.demos
                row.update({"obstacle_recall_required_bound": None,
                            **self.required_rates(self.learned_mask(row), shard)})
                if ident is None:  # no truth, or no process holds every demonstration
                    row.update(dict.fromkeys(IDENTIFIABILITY_KEYS))
                    continue
                learned = torch.from_numpy(self.learned_mask(row))
                row.update(FNR_required=fnr_required(
                               learned, torch.as_tensor(self.evaluation.true_constraints),
                               ident),
                           n_demonstrated=ident.n_demonstrated, n_required=ident.n_required,
                           n_undetermined=ident.n_undetermined,
                           contradictions=ident.names_of(learned & ident.accrued))
        return None if ident is None else ident.as_dict()

    # ------------------------------------------------------------------ figures
    def evaluation_settings(self) -> dict[str, Any]:
        """What a trained method's rows depend on besides its state and the training
        config (which holds the rollouts' seed): a checkpointed row is reused only
        under the same settings."""
        settings = {"threshold": self.threshold, "eval_episodes": self.evaluation.episodes,
                    "prune_min_gain": None if self.prune_min_gain is None
                    else float(self.prune_min_gain)}
        if self.constraint_rule != "threshold":  # the threshold rule's rows predate the key
            settings.update(constraint_rule=self.constraint_rule, certificate=self.certificate)
        return settings

    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """The paper's Fig. 2 for this run: 2a, the experts' visitation with the true
        constraints; 2b, the same with each bi-level learner's learned constraints (after
        pruning); 2c-2g, the metric curves over outer iterations, greedy baselines and
        experts as reference lines. Where :meth:`identifiability` applies, also
        ``identifiability_classes``: the true constraints by class beside each bi-level
        learner's learned set (:func:`~dicrl_torch.figures.identifiability_figure`).

        ``methods``: the table (rows by method), ``histories``: ``results.json``'s history.
        Bi-level methods are those with an outer-iteration history.
        """
        bilevel = [k for k in methods if k in histories and k not in GRID_BASELINES]
        colour = "colour: share of expert trajectories entering the cell"
        held = self.demos
        if held is None:  # torchrun's rank 0 with private shard files reads only its own
            held = next(s for s in self.shards if s is not None)
            colour += " (learner 1's file)"
        visits = state_visitation(held.states, self.layout.n_cells)
        regions = self.cost_basis.region_cells
        images = {"fig2a_true_visitation": visitation_heatmap(
            self.layout, visits, constraint_cells=obstacle_cells(self.layout),
            title=f"Fig. 2a: the true CMG, its constraints (x)\n{colour}")}
        panels = []
        for name in bilevel:
            rows = methods[name]["learners"]
            for v, row in enumerate(rows):
                who = f"{name} learner {v + 1}" if len(rows) > 1 else name
                # Action and collision constraints have no cell to cross: named in the title.
                off_grid = [n for n in row["constraints"]
                            if not constraint_cells(self.layout, [n], regions)]
                listed = ", ".join(off_grid[:4]) + (f" and {len(off_grid) - 4} more"
                                                    if len(off_grid) > 4 else "")
                # a basis without per-feature truth is scored as regions (§6.1)
                keys = ("FPR", "FNR") if row.get("FPR") is not None or "obstacle_FPR" not in row \
                    else ("region_recall", "obstacle_FPR")
                rates = ", ".join(f"{column_header(k)} "
                                  f"{'N/A' if row.get(k) is None else format(row[k], '.2f')}"
                                  for k in keys)
                panels.append(visitation_heatmap(
                    self.layout, visits,
                    constraint_cells=constraint_cells(self.layout, row["constraints"], regions),
                    title=f"Fig. 2b: {who}, learned constraints (x)\n"
                          f"not on a cell: {listed or 'none'}\n"
                          f"{rates} (after pruning)\n{colour}"))
        if panels:
            images["fig2b_learned_constraints"] = side_by_side(panels)
        if bilevel:
            images["fig2c-g_metric_curves"] = metric_curves(
                {k: histories[k] for k in bilevel},
                final_rows={k: methods[k]["learners"] for k in bilevel},
                baselines={k: methods[k]["learners"][0] for k in GRID_BASELINES
                           if k in methods},
                experts={k: m["learners"][0] for k, m in methods.items()
                         if k not in histories},
                title=f"{experiment}: {self.layout.n_experts} expert(s), {len(self.split)} "
                      f"learner(s) holding {self.split} of {sum(self.split)} demonstrations "
                      f"(CR, CVR: {self.evaluation.episodes} episodes every {eval_every} "
                      f"outer iterations)")
        ident = self.identifiability()
        if ident is not None:
            labelled = {}
            for name in bilevel:
                rows = methods[name]["learners"]
                labelled.update({f"{name} learner {v + 1}" if len(rows) > 1 else name: row
                                 for v, row in enumerate(rows)})
            images["identifiability_classes"] = identifiability_figure(
                self.layout, ident.as_dict(), labelled, region_cells=regions)
        return images
