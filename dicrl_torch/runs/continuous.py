"""What every continuous game's task shares when its learners are SAC solvers
(docs/design.md §2.3, §7): :class:`SACTask`.

A continuous task (the constrained MPE's :class:`~dicrl_torch.runs.mpe.MPETask`, the
drone arena's :class:`~dicrl_torch.runs.drones.DroneTask`) runs the same steps whatever
the game:

1. one SAC solver is pre-trained on ``η(0), ω_c(0)`` (``warmup_timesteps``), once per
   process; every learner, C-ICRL and the greedy baseline train clones of it, seeded per
   learner and per stream, each holding only its own demonstrations;
2. the learned constraint set of a learner is the paper's rule ``ω_c,j >= threshold``;
   FPR and FNR against the game's true constraint features (None without a ground
   truth);
3. a learner's table row comes from a last solve on its learned ``(η̄, ω_c)``
   (:meth:`~dicrl_torch.solvers.sac.SACConstrainedSolver.solve_keeping_best`), flown in
   the TRUE game with mean and sampled actions on common random numbers;
4. M(C)E-greedy (the paper's §6.2 baseline) given D-ICRL's learned reward, all
   demonstrations pooled.

:class:`SACTask` runs any game of the solver's joint-env protocol as it is (your own
environment: docs/own_environment_draft.md): SR and CVR are the protocol's (per agent,
``info["reached"]`` without ``info["violated"]``, and ``info["violated"]``), the constraint
map a strip of the cost features, no reference row and no figure. A subclass says what
depends on the game (:class:`~dicrl_torch.runs.mpe.MPETask`): :meth:`SACTask.evaluate_policy`,
the reference rows, the figures, the constraint maps, the identifiability record.
Nothing here reads a config.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import shutil
import stat
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.algos.greedy import SACGreedyConstraintInference
from dicrl_torch.algos.models import SACLearnerModel
from dicrl_torch.checks import check_int
from dicrl_torch.demos import partition_demonstrations
from dicrl_torch.demos.continuous import save_continuous_demonstrations
from dicrl_torch.features.continuous import ContinuousFeatureBasis
from dicrl_torch.io import atomic_write
from dicrl_torch.metrics import false_negative_rate, false_positive_rate, learned_constraints
from dicrl_torch.runs.regions import RegionScoring
from dicrl_torch.runs.settings import (
    EVAL_ACTIONS,
    EVAL_POLICIES,
    FINAL_SCORES,
    GREEDY_BASELINE,
    SACSettings,
    with_defaults,
)
from dicrl_torch.runs.task import Rollouts, Task

__all__ = ["EVAL_ACTIONS", "EVAL_POLICIES", "FINAL_SCORES", "GREEDY_BASELINE", "SACTask",
           "derived_seed"]

WARMUP_FILE = "warmup.pt"
"""The run directory's file of the SAC warm-up (:meth:`SACTask.bind_run_dir`)."""
WARMUP_LINEAGES_DIR = "warmup_lineages"
"""Where the processes of one run leave the warm-up lineages they trained, for the one
that trains lineage 0 (:meth:`SACTask.bind_run_dir`); removed once ``warmup.pt`` is
written."""
_SAME_RUN_DIR = ("Every learner process must see the same run directory (multi-node runs: "
                 "hydra.run.dir on a shared file system).")
WARMUP_WAIT_S = 6 * 3600.0
"""How long a process waits for the others' share of the warm-up (a lineage takes
minutes; a process that dies is noticed by the spawning process or torchrun, which stops
the others)."""


def derived_seed(seed: int, *keys: int) -> int:
    """An independent stream per purpose (learner, C-ICRL, evaluation) from one seed: the
    one derivation of every continuous task's streams."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


def _file_stamp(path: Path) -> tuple[int, int, int] | None:
    """``(inode, mtime_ns, size)`` of a regular file (an atomic replacement changes it),
    or None where there is none."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return (st.st_ino, st.st_mtime_ns, st.st_size) if stat.S_ISREG(st.st_mode) else None


class SACTask(RegionScoring, Task):
    """A continuous game's task, for the runner (:class:`~dicrl_torch.runs.task.Task`;
    module docstring): usable as it is for any game of the joint-env protocol, or
    subclassed for a game's own metrics and pictures.

    Args:
        solver: an untrained :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` over
            the learners' bases (the warm-up trains it; learners train clones).
        demos: every demonstration (``ContinuousDemonstrations`` of the solver's game, or
            convertible with ``to_continuous()``), split over the learners by ``split``
            in order; checked against the solver's env (states ``[N, d_s]``, actions).
        split: demonstrations per learner (positive, summing to ``demos``' count).
        seed: seeds the clones and the evaluation.
        true_constraints: ``[l_c]`` bool, the cost features that are true constraints of
            the game; None when the cost basis has no ground truth (FPR and FNR are then
            None: ``null`` in ``results.json``, N/A in the table).
        eval_episodes, eval_action, eval_policy, planner: the table's rollouts
            (:class:`~dicrl_torch.runs.settings.TableRollouts`); ``eval_policy="plan"``
            plans with :meth:`make_planner` (the task's; the drone arena has one).
        timesteps, n_eval_episodes: SAC steps and rollouts per inner solve.
        warmup_timesteps, warmup_restarts, warmup_checks, warmup_until_success: the warm-up
            on ``η(0), ω_c(0)`` (:class:`~dicrl_torch.runs.settings.WarmUp`).
        init_reward_weights, init_multiplier, init_cost_weights: ``η(0)``, ``ω_c(0)``
            (the trainer's, the same numbers).
        final_timesteps, final_checks, final_restarts, final_score, final_margin: the last
            solve on each learned ``(η̄, ω_c)``, whose policy a row evaluates
            (:class:`~dicrl_torch.runs.settings.LastSolve`; ``final_timesteps`` None:
            ``timesteps``). The learned constraints and the scores are the cost basis's
            whatever the margin.
        threshold: ``ω_c,j >= threshold`` marks a learned constraint.
        start_states: ``[P, N, d_s]`` joint states spanning the start distribution's
            support (:meth:`SACLearnerModel.start_features`); None: unknown.
        baseline: build M(C)E-greedy; ``baseline_*``: its settings
            (:class:`~dicrl_torch.runs.settings.GreedyBaseline`).

    Raises:
        InvalidSetting: a setting out of range (checked first:
            :class:`~dicrl_torch.runs.settings.SACSettings`), naming it.
        ValueError: demonstrations that do not fit the solver's env, a split that does not
            fit them, a basis the settings cannot use, or a true-constraint mask of the
            wrong width.
    """

    columns: tuple[str, ...] = ("FPR", "FNR", "CVR", "SR")
    can_plan: bool = False
    """Whether :meth:`make_planner` gives a planner (a game with a model of its nominal
    dynamics, the drone arena's), which ``eval_policy="plan"`` needs."""
    game: str | None = None
    """The game a subclass is for (a basis built for another game's geometry, its
    ``game``, is refused); None: a user's own game, which takes only game-free bases."""

    def __init__(self, *, solver, demos, split: Sequence[int], seed: int,
                 true_constraints: Any = None, eval_episodes: int = 100,
                 eval_action: str = "mean", timesteps: int, n_eval_episodes: int = 10,
                 warmup_timesteps: int = 0, warmup_restarts: int = 1, warmup_checks: int = 1,
                 warmup_until_success: float | None = None,
                 init_reward_weights: float = 1.0,
                 init_multiplier: float = -1.0, init_cost_weights: float = 0.0,
                 final_timesteps: int | None = None, final_checks: int = 1,
                 final_restarts: int = 1, final_score: str = "penalised_return",
                 final_margin: float = 0.0, eval_policy: str = "sac",
                 planner: dict | None = None, threshold: float = 0.5, start_states: Any = None,
                 baseline: bool = False,
                 baseline_penalty: float = 10.0, baseline_timesteps: int = 3000,
                 baseline_epsilon: float | None = None,
                 baseline_max_constraints: int | None = None) -> None:
        from dicrl_torch.solvers.sac.protocol import as_continuous

        # Every setting is checked before anything else is looked at.
        s = self.settings = SACSettings.from_keywords(
            split=split, seed=seed, eval_episodes=eval_episodes, eval_action=eval_action,
            timesteps=timesteps, n_eval_episodes=n_eval_episodes,
            warmup_timesteps=warmup_timesteps, warmup_restarts=warmup_restarts,
            warmup_checks=warmup_checks, warmup_until_success=warmup_until_success,
            init_reward_weights=init_reward_weights,
            init_multiplier=init_multiplier, init_cost_weights=init_cost_weights,
            final_timesteps=final_timesteps, final_checks=final_checks,
            final_restarts=final_restarts, final_score=final_score, final_margin=final_margin,
            eval_policy=eval_policy, planner=planner, threshold=threshold, baseline=baseline,
            baseline_penalty=baseline_penalty, baseline_timesteps=baseline_timesteps,
            baseline_epsilon=baseline_epsilon, baseline_max_constraints=baseline_max_constraints)
        self.base = solver
        self.reward_basis, self.cost_basis = solver.reward_basis, solver.cost_basis
        for role, basis in (("reward", self.reward_basis), ("cost", self.cost_basis)):
            built_for = getattr(basis, "game", None)
            if built_for is not None and built_for != self.game:
                raise ValueError(
                    f"The {role} basis {type(basis).__name__} is built on the geometry of "
                    f"the game {built_for!r}, not of {self.game or 'this game'!r}; give a "
                    f"basis of this game (e.g. PositionCellBasis over its bounds, or your "
                    f"own ContinuousFeatureBasis).")
        demos = as_continuous(demos, solver.spec)  # refused, naming the fix, if unfit
        self.split = list(s.split)
        if sum(self.split) != demos.n_trajectories:
            raise ValueError(f"split {self.split} sums to {sum(self.split)}, but there are "
                             f"{demos.n_trajectories} demonstrations; make them agree.")
        self.seed, self.timesteps, self.n_eval_episodes = s.seed, s.timesteps, s.n_eval_episodes
        self.eval_episodes, self.eval_action = s.rollouts.episodes, s.rollouts.action
        self.warmup_timesteps, self.warmup_restarts, self.warmup_checks = (
            s.warmup.timesteps, s.warmup.restarts, s.warmup.checks)
        self.warmup_until_success = s.warmup.until_success
        self.eta0 = torch.full((solver.l_r + 1,), s.init_reward_weights, dtype=torch.float64)
        self.eta0[-1] = s.init_multiplier
        self.cw0 = torch.full((solver.l_c,), s.init_cost_weights, dtype=torch.float64)
        self.final = dataclasses.asdict(s.last_solve)
        self.penalty_basis = None
        if self.final["margin"] != 0.0:
            if not (isinstance(self.cost_basis, ContinuousFeatureBasis)
                    and self.cost_basis.dilatable):
                raise ValueError(
                    f"final_margin={final_margin!r} needs a cost basis that can be grown by a "
                    f"margin (dilatable, with dilated(margin), e.g. CellOccupancyCostBasis); "
                    f"{type(self.cost_basis).__name__} has none: set final_margin=0.")
            self.penalty_basis = self.cost_basis.dilated(self.final["margin"])
        if s.rollouts.policy == "plan" and not self.can_plan:
            raise ValueError(f"eval_policy='plan' needs a model of the nominal game to plan "
                             f"in, which {type(self).__name__} does not give (the drone "
                             f"arena does); use eval_policy='sac'.")
        self.eval_policy, self.planner_settings = s.rollouts.policy, s.rollouts.planner
        self.threshold = s.threshold
        if true_constraints is None:
            self.true = None
        else:
            true = np.asarray(true_constraints)
            if true.dtype != bool or true.shape != (solver.l_c,):
                raise ValueError(f"true_constraints must be [{solver.l_c}] bool (one per cost "
                                 f"feature), got dtype {true.dtype} shape {true.shape}.")
            self.true = true.copy()
        self.start_states = start_states
        self.baseline = dataclasses.asdict(s.baseline)
        self.demos = demos
        self.shards = list(partition_demonstrations(demos, self.split))
        self._warm = False
        self._warmup_file: Path | None = None  # bind_run_dir
        self._stale: dict[Path, tuple[int, int, int]] = {}  # files of another config
        self._warmup_key: str | None = None
        self._process, self._processes = 0, 1

    @classmethod
    def check_settings(cls, **settings: Any) -> SACSettings:
        """The checked settings of ``SACTask(**settings, ...)`` (its keyword arguments of
        :meth:`SACSettings.from_keywords`' names; the others at their defaults), building
        nothing: a config's values are checked with it before anything is computed.

        Raises:
            InvalidSetting: the first setting out of range, naming it.
        """
        names = inspect.signature(SACSettings.from_keywords).parameters
        return SACSettings.from_keywords(**with_defaults(SACTask.__init__, list(names),
                                                         settings))

    # ------------------------------------------------------------------ set-up
    def describe(self) -> str:
        n, d_s = self.base.spec.state_shape
        truth = "no ground truth" if self.true is None \
            else f"{int(self.true.sum())} of them true constraints"
        return (f"{self.base.spec.name}: {n} agents (joint state [{n}, {d_s}]); "
                f"{len(self.split)} learners holding {self.split} episodes; "
                f"{self.cost_basis.dim} cost features, {truth}")

    def announce(self, out: Path) -> None:
        """Prints :meth:`describe` and what the cost basis can express
        (:meth:`expressivity`), refusing one that can express nothing
        (:meth:`check_expressive`), and saves the demonstrations as ``demos.npz``."""
        self.check_expressive()
        save_continuous_demonstrations(Path(out) / "demos.npz", self.demos)
        print(self.describe(), flush=True)
        self.print_expressivity()


    def initial_weights(self) -> dict[str, float]:
        """``η(0)`` and ``ω_c(0)`` as the trainer takes them (``DICRL``'s
        ``init_reward_weights``, ``init_multiplier``, ``init_cost_weights``): the warm-up
        trains on them, and the runner's trainers start from them."""
        return {"init_reward_weights": float(self.eta0[0]),
                "init_multiplier": float(self.eta0[-1]),
                "init_cost_weights": float(self.cw0[0]) if len(self.cw0) else 0.0}

    # ------------------------------------------------------------------ learners
    def warmup_summary(self, solution) -> str:
        """What the warm-up's policy does in the nominal game (one line); a subclass
        says it in its game's words."""
        return (f"{float(solution.reached.double().mean()):.2f} of the agents reach their "
                f"goal and {solution.violation_rate:.2f} cross a true constraint")

    def bind_run_dir(self, out: Path, training_config: dict, *, process: int = 0,
                     processes: int = 1) -> None:
        """Keep the warm-up's solver in ``out/warmup.pt``, keyed by the run's
        ``training_config``: the processes of one run (the learners of ``comm=distributed``,
        then the process that runs C-ICRL) and a resumed run load it instead of training
        it again. A file of another config is ignored and replaced.

        With ``processes`` > 1 this is process ``process`` of that many that reach the
        warm-up together (the learner processes): a warm-up of several lineages
        (``warmup_restarts``) is then shared, process ``p`` training lineages
        ``p, p + processes, ...``; process 0 adopts the best of all (read from
        ``out/warmup_lineages/``) and writes ``warmup.pt``, which the others load. A
        warm-up of one lineage and one chunk is process 0's alone. The result is the
        one-process warm-up's (the lineages are independent and seeded).
        """
        key = json.dumps(training_config, sort_keys=True, default=str)
        self._warmup_file = Path(out) / WARMUP_FILE
        self._warmup_key = hashlib.sha256(key.encode()).hexdigest()
        if not all(isinstance(x, int | np.integer) and not isinstance(x, bool)
                   for x in (process, processes)) or not 0 <= process < processes:
            raise ValueError(f"process must lie in [0, processes), got process={process!r}, "
                             f"processes={processes!r}.")
        self._process, self._processes = int(process), int(processes)
        self._stale.clear()

    def _load_warmup(self, report: bool = True) -> str | None:
        """Load the bound run directory's warm-up into the base solver; its summary
        line, or None where there is none of this run's config (``report``: say so when
        the file is unreadable)."""
        path = self._warmup_file
        stamp = None if path is None else _file_stamp(path)
        if stamp is None or self._stale.get(path) == stamp:
            return None
        try:
            saved = torch.load(path, weights_only=True)  # tensors and plain values only
            if not isinstance(saved, dict) or saved.get("key") != self._warmup_key:
                # Another config's (a reused run directory; 33 MB for the drones): read
                # again only once it has been replaced, not at every poll of a wait.
                self._stale[path] = stamp
                return None
            summary = str(saved["summary"])
            self.base.load_state_dict(saved["solver"])  # checked before anything changes
            return summary
        except Exception as e:  # noqa: BLE001 - any unreadable file: train it again
            if report:
                print(f"SAC warm-up: {path} is unreadable ({type(e).__name__}: {e}); "
                      f"training it again.", flush=True)
            return None

    def _warmed_base(self, progress: bool = False):
        """The base solver after its warm-up on ``η(0), ω_c(0)`` (once per process, or
        loaded from the run directory, :meth:`bind_run_dir`; it is deterministic, so
        either way every process starts from the same state); ``progress``: a bar over
        the warm-up's steps."""
        if not self._warm and self.warmup_timesteps:
            t0 = time.perf_counter()
            summary = self._load_warmup()
            if summary is not None:
                print(f"SAC warm-up loaded from {self._warmup_file} ({summary})", flush=True)
            else:
                label = "SAC warm-up" if progress else None
                if self._processes > 1 and self._warmup_file is not None:
                    done = self._shared_warmup(label)
                elif self._plain_warmup():
                    done = self._train_plain_warmup(label)
                else:  # no constraint known yet: "success" is reaching the goals
                    sol = self.base.solve_keeping_best(
                        self.eta0, self.cw0, self.warmup_timesteps,
                        **self._warmup_lineage_settings(), progress=label)
                    done = self.warmup_summary(sol)
                if done is None:  # another process adopted the best lineage
                    summary = self._wait_for_warmup()
                    print(f"SAC warm-up loaded from {self._warmup_file} ({summary})",
                          flush=True)
                else:
                    summary = (f"{self._warmup_steps()} steps on η(0) in "
                               f"{time.perf_counter() - t0:.0f} s; in the nominal game {done}")
                    print(f"SAC warm-up: {summary}", flush=True)
                    if self._warmup_file is not None:
                        state = {"key": self._warmup_key, "summary": summary,
                                 "solver": self.base.state_dict()}
                        atomic_write(self._warmup_file, lambda f: torch.save(state, f))
                        if self._processes > 1:
                            shutil.rmtree(self._warmup_file.parent / WARMUP_LINEAGES_DIR,
                                          ignore_errors=True)
        self._warm = True
        return self.base

    def _warmup_steps(self) -> str:
        """The steps the warm-up trained, per lineage (fewer than ``warmup_timesteps``
        where ``warmup_until_success`` stopped one)."""
        if self._plain_warmup():
            return str(self.warmup_timesteps)
        trained = {}
        for check in self.base.last_checks:  # every chunk of every lineage, in order
            trained[check["restart"]] = check["timesteps"]
        steps = [trained[r] for r in sorted(trained)]
        return str(steps[0]) if len(set(steps)) == 1 else "+".join(map(str, steps))

    def _warmup_lineage_settings(self) -> dict[str, Any]:
        """The warm-up's lineages: chunks, restarts, how they are scored (no constraint
        known yet: "success" is reaching the goals)."""
        return {"checks": self.warmup_checks, "restarts": self.warmup_restarts,
                "stop_at": self.warmup_until_success,
                "deterministic": self.eval_action == "mean",
                "constraints": torch.zeros(self.base.l_c, dtype=torch.bool)}

    def _plain_warmup(self) -> bool:
        """One lineage, one chunk: a plain solve, nothing scored."""
        return self.warmup_restarts == 1 and self.warmup_checks == 1

    def _train_plain_warmup(self, label: str | None) -> str:
        """Train the plain warm-up; its summary line."""
        return self.warmup_summary(self.base.solve(self.eta0, self.cw0,
                                                   self.warmup_timesteps, progress=label))

    def _shared_warmup(self, label: str | None) -> str | None:
        """This process's share of the warm-up's lineages (:meth:`bind_run_dir`; a plain
        warm-up is process 0's alone). Process 0 waits for the others', adopts the best
        and returns its summary line; the others leave theirs in the run directory and
        return None."""
        from dicrl_torch.solvers.sac import Lineage  # SB3: only where SAC runs

        if self._plain_warmup():
            return self._train_plain_warmup(label) if self._process == 0 else None
        p, n, restarts = self._process, self._processes, self.warmup_restarts
        folder = self._warmup_file.parent / WARMUP_LINEAGES_DIR
        mine = list(range(p, restarts, n))
        lineages = self.base.train_lineages(
            self.eta0, self.cw0, self.warmup_timesteps, lineages=mine,
            **self._warmup_lineage_settings(), progress=label) if mine else []
        summaries = {}
        for lineage in lineages:
            summaries[lineage.restart] = self.warmup_summary(lineage.solution)
            record = {"key": self._warmup_key, "summary": summaries[lineage.restart],
                      "lineage": lineage.state()}
            folder.mkdir(parents=True, exist_ok=True)
            atomic_write(folder / f"lineage{lineage.restart}.pt",
                         lambda f, record=record: torch.save(record, f))
        if p != 0:
            return None
        others = [r for r in range(restarts) if r not in mine]
        if others:
            print(f"SAC warm-up: waiting for lineages {others} from the other learner "
                  f"processes ({folder})", flush=True)
        deadline = time.monotonic() + WARMUP_WAIT_S
        while others:
            for r in list(others):
                record = self._read_lineage(folder / f"lineage{r}.pt")
                if record is not None:
                    lineages.append(Lineage.from_state(record["lineage"]))
                    summaries[r] = str(record["summary"])
                    others.remove(r)
            if others:
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"SAC warm-up: lineages {others} did not appear in {folder} within "
                        f"{WARMUP_WAIT_S:.0f} s. {_SAME_RUN_DIR}")
                time.sleep(1.0)
        best = self.base.adopt_best(lineages)
        return summaries[best.restart]

    def _read_lineage(self, path: Path) -> dict | None:
        """A lineage file of this run's config, or None (absent, of another config, or
        not readable yet; a file found of another config is read again only once it has
        been replaced)."""
        stamp = _file_stamp(path)
        if stamp is None or self._stale.get(path) == stamp:
            return None
        try:
            record = torch.load(path, weights_only=True)  # tensors and plain values only
        except Exception:  # noqa: BLE001 - written atomically: another run's leftovers
            return None
        if not isinstance(record, dict) or record.get("key") != self._warmup_key:
            self._stale[path] = stamp
            return None
        return record

    def _wait_for_warmup(self) -> str:
        """Wait for process 0 to write this run's ``warmup.pt`` and load it; its summary."""
        deadline = time.monotonic() + WARMUP_WAIT_S
        while (summary := self._load_warmup(report=False)) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"SAC warm-up: {self._warmup_file} was not written within "
                    f"{WARMUP_WAIT_S:.0f} s by learner process 0. {_SAME_RUN_DIR}")
            time.sleep(1.0)
        return summary

    def learner_model(self, local_ids: Sequence[int], shards: Sequence, stream: int
                      ) -> SACLearnerModel:
        """Each local learner owns a clone of the warmed-up solver, seeded per learner and
        per ``stream`` (0: D-ICRL, 1: C-ICRL), holding its own demonstrations."""
        # One bar per run: the process holding D-ICRL's learner 1 shows it.
        base = self._warmed_base(progress=stream == 0 and 0 in local_ids)
        solvers = [base.clone(derived_seed(self.seed, 2, stream, v)) for v in local_ids]
        for solver, shard in zip(solvers, shards, strict=True):
            solver.set_demonstrations(shard)  # its own episodes only (solver.demo_fraction)
        return SACLearnerModel(solvers=solvers, timesteps=self.timesteps,
                               n_eval_episodes=self.n_eval_episodes,
                               start_states=self.start_states)

    # ------------------------------------------------------------------ metrics
    def rates(self, mask: np.ndarray) -> dict[str, Any]:
        """FPR, FNR (None without a ground truth), the size and the names of a learned
        set ``mask`` ``[l_c]`` bool, and its region scores (:meth:`region_rates`)."""
        names = [self.cost_basis.names[j] for j in np.flatnonzero(mask)]
        return {"FPR": false_positive_rate(mask, self.true),
                "FNR": false_negative_rate(mask, self.true),
                "n_learned": int(mask.sum()), "constraints": names,
                **self.region_rates(mask)}

    def outer_metrics(self, trainer: DICRL, rollouts: bool) -> dict[str, list]:
        """FPR and FNR of each local learner's ``ω_c >= threshold`` (no rollouts: a
        true-game evaluation of SAC is a table-row affair)."""
        rates = [self.rates(learned_constraints(w, self.threshold))
                 for w in trainer.state.cost_weights]
        return {"FPR": [r["FPR"] for r in rates], "FNR": [r["FNR"] for r in rates]}

    def evaluate_policy(self, solver, deterministic: bool) -> tuple[float, float, list]:
        """SR, CVR and the rollouts' joint states ``[L+1, N, d_s]`` of ``solver``'s
        current policy, ``eval_episodes`` episodes in the TRUE game on the evaluation's
        common random numbers (the same starts for every row). Here the protocol's:
        SR the share of agents that reached their goal (``info["reached"]``) without a
        violation, CVR the share that violated (``info["violated"]``); a game with a task
        success of its own overrides it."""
        ev = solver.evaluate(self.eval_episodes, deterministic=deterministic,
                             true_game=True, trajectories=True, rng=self.evaluation_rng())
        return ev.success_rate, ev.violation_rate, list(ev.paths)

    def planning_seed(self) -> int:
        """The planner's seed for every planned row (:meth:`planning_actor`): one stream
        for every row, as every row flies the same starts, so rows differ by their learned
        games only, and a learner's row is the same in whichever process holds it."""
        return derived_seed(self.seed, 4, 0)

    def evaluation_rng(self) -> np.random.Generator:
        """A fresh generator of the evaluation's episode seeds: every row, and both
        action modes, fly from the same starts."""
        return np.random.default_rng(derived_seed(self.seed, 3))

    def _evaluate_true_game(self, solver) -> tuple[dict, list]:
        """The row's SR and CVR with mean actions (how an SAC policy is deployed) and
        sampled ones (the MCE policy itself), ``SR`` and ``CVR`` being ``eval_action``'s;
        and the rollouts of ``eval_action``."""
        row: dict[str, Any] = {"CR_mean": None, "CR_std": None, "RFD": None}
        paths: dict[str, list] = {}
        for mode in EVAL_ACTIONS:
            sr, cvr, paths[mode] = self.evaluate_policy(solver, deterministic=mode == "mean")
            row[f"SR_{mode}"], row[f"CVR_{mode}"] = sr, cvr
        row.update(SR=row[f"SR_{self.eval_action}"], CVR=row[f"CVR_{self.eval_action}"])
        return row, paths[self.eval_action]

    def make_planner(self, eta: np.ndarray, cost_weights: np.ndarray, constraints: np.ndarray,
                     seeds: Sequence[int]):
        """A planner (:class:`~dicrl_torch.solvers.planning.CrossEntropyPlanner`) acting on
        the learned game ``(η [l_r + 1], ω_c [l_c])`` with ``constraints [l_c]`` bool
        forbidden, in the nominal model, for one problem (episode) per seed; a game with a
        model overrides this."""
        raise NotImplementedError(f"{type(self).__name__} has no model to plan in.")

    def planning_actor(self, eta: np.ndarray, cost_weights: np.ndarray,
                       constraints: np.ndarray, seed: int, n_episodes: int | None = None
                       ) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
        """An ``actor`` for the solver's ``evaluate`` that plans on the learned game
        ``(η [l_r + 1], ω_c [l_c])`` with ``constraints [l_c]`` bool forbidden
        (:meth:`make_planner`): episode ``k`` of ``n_episodes`` (default
        ``eval_episodes``) is its own planning problem with its own random stream from
        ``seed``. Fly it in either game, e.g. the nominal one to see where the learned game
        leads: ``solver.evaluate(n, true_game=False, actor=task.planning_actor(...),
        rng=task.evaluation_rng(), trajectories=True)``."""
        n = self.eval_episodes if n_episodes is None else check_int("n_episodes", n_episodes)
        planner = self.make_planner(eta, cost_weights, constraints,
                                    [derived_seed(seed, 5, k) for k in range(n)])

        def actor(states: np.ndarray, active: np.ndarray, episodes: np.ndarray) -> np.ndarray:
            return planner.act(states, active, episodes).reshape(len(episodes), -1)

        return actor

    def evaluate_planned(self, solver, eta: np.ndarray, cost_weights: np.ndarray,
                         constraints: np.ndarray, seed: int, progress: str | None = None
                         ) -> tuple[dict, list[np.ndarray]]:
        """The true-game row of planning on the learned game (:meth:`planning_actor`):
        ``eval_episodes`` episodes on the evaluation's common starts, planned together
        (``SR_plan``, ``CVR_plan``; SAC's columns None), and the rollouts' joint states
        ``[L+1, N, d_s]``; ``progress`` labels a bar over the finished episodes."""
        ev = solver.evaluate(self.eval_episodes, true_game=True, trajectories=True,
                             rng=self.evaluation_rng(),
                             actor=self.planning_actor(eta, cost_weights, constraints, seed),
                             progress=progress)
        row = {"CR_mean": None, "CR_std": None, "RFD": None, "SR_mean": None,
               "CVR_mean": None, "SR_sampled": None, "CVR_sampled": None,
               "SR_plan": ev.success_rate, "CVR_plan": ev.violation_rate,
               "SR": ev.success_rate, "CVR": ev.violation_rate}
        return row, list(ev.paths)

    def evaluate_learner(self, trainer: DICRL, i: int, progress: bool = True
                         ) -> tuple[dict, Rollouts]:
        """A last solve on the learned ``(η̄, ω_c)``, then the true-game row (with
        ``eval_policy="plan"``: planning on it instead of a last solve) and its rollouts
        (of :meth:`evaluate_policy`, ``eval_action``'s)."""
        eta, cw = trainer.state.eta_bar[i], trainer.state.cost_weights[i]
        mask = learned_constraints(cw, self.threshold)
        solver = trainer.learner_model.inner_solver(i)
        if self.eval_policy == "plan":
            row, paths = self.evaluate_planned(
                solver, np.asarray(eta, dtype=np.float64), np.asarray(cw, dtype=np.float64),
                mask, self.planning_seed(),
                progress=self._planning_label(trainer, i) if progress else None)
            row.update(self.rates(mask), multiplier=float(eta[-1]),
                       reward_weights=eta[:-1].tolist(), policy_timesteps=None,
                       final_checks=None, region_recall_bound=self._bound(trainer, i))
            return row, paths
        f = self.final
        kept = solver.solve_keeping_best(
            eta, cw, f["timesteps"], checks=f["checks"], restarts=f["restarts"],
            deterministic=self.eval_action == "mean",
            constraints=mask if f["score"] == "learned_success" else None,
            penalty_basis=self.penalty_basis)
        row, paths = self._evaluate_true_game(solver)
        row.update(self.rates(mask), multiplier=float(eta[-1]),
                   reward_weights=eta[:-1].tolist(), policy_timesteps=kept.timesteps,
                   final_checks=solver.last_checks, region_recall_bound=self._bound(trainer, i))
        return row, paths

    @staticmethod
    def _planning_label(trainer: DICRL, i: int) -> str:
        """The planned evaluation's bar: which learner of how many (C-ICRL: the one)."""
        if trainer.n_learners == 1:
            return "planning the centralized learner"
        return f"planning learner {trainer.local[i] + 1} of {trainer.n_learners}"

    def evaluation_settings(self) -> dict[str, Any]:
        return {"threshold": self.threshold, "eval_episodes": self.eval_episodes,
                "eval_action": self.eval_action, "eval_policy": self.eval_policy,
                "planner": self.planner_settings,
                **{f"final_{k}": v for k, v in self.final.items()}}

    def row_scalars(self, row: dict) -> list[tuple[str, float, int]]:
        """The last solve's chunk scores, per restart (``final/...``)."""
        out = []
        for check in row.get("final_checks") or ():
            suffix = f"/restart{check['restart']}" if check["restart"] else ""
            for key in ("penalised_return", "success_under_constraints"):
                if check[key] is not None:
                    out.append((f"final/{key}{suffix}", check[key], check["timesteps"]))
        return out

    # ------------------------------------------------------------------ baseline
    def make_baselines(self, methods: dict[str, dict], progress: bool = True
                       ) -> dict[str, SACGreedyConstraintInference]:
        """M(C)E-greedy given D-ICRL's learned reward (learner 1's ω_r), on every
        demonstration (the paper's protocol); nothing before D-ICRL has a row."""
        b = self.baseline
        if not b["run"] or "D-ICRL" not in methods:
            return {}
        greedy = SACGreedyConstraintInference(
            solver=self._warmed_base().clone(derived_seed(self.seed, 4)),
            reward_weights=torch.tensor(methods["D-ICRL"]["learners"][0]["reward_weights"],
                                        dtype=torch.float64),
            demonstrations=self.demos, penalty=b["penalty"], timesteps=b["timesteps"],
            epsilon=b["epsilon"], max_constraints=b["max_constraints"], progress=progress)
        return {GREEDY_BASELINE: greedy}

    def baseline_row(self, name: str, greedy: SACGreedyConstraintInference, result
                     ) -> tuple[dict, list[dict], Rollouts]:
        """The true-game row of ``greedy``'s final policy (its solver's) with its
        constraint set ``result.constraint_mask``, the per-step history (FPR, FNR and
        log-likelihood after each constraint added) and the row's rollouts."""
        mask = result.constraint_mask.numpy()
        row, paths = self._evaluate_true_game(greedy.solver)
        row.update(self.rates(mask), stop_reason=result.stop_reason)
        history, sel = [], np.zeros_like(mask)
        for k, ll in enumerate(result.log_likelihood):
            if k:
                sel[result.added[k - 1]] = True
            rates = self.rates(sel)
            history.append({"step": k, "added": result.added_names[k - 1] if k else None,
                            "log_likelihood": ll, "FPR": rates["FPR"], "FNR": rates["FNR"]})
        return row, history, paths

    # ------------------------------------------------------------------ pictures
    def constraint_map(self, label: str, row: dict, rollouts: Rollouts = ()) -> np.ndarray:
        """The cost features as a strip: learned ones filled (red), true ones outlined
        (black), without the ``rollouts`` (a strip has no space to draw them in); a game
        with a map of its own overrides it."""
        from dicrl_torch.figures import feature_strip

        return feature_strip(self.learned_mask(row), self.true,
                             title=f"{label}: {int(self.learned_mask(row).sum())} learned "
                                   f"constraints of {self.cost_basis.dim} features")

    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """``cost_weights``: every ω_c,j of the bi-level methods' learners against the
        outer iteration, beside the threshold (:func:`~dicrl_torch.figures.cost_weight_curves`);
        a game adds its own figures to these."""
        from dicrl_torch.figures import cost_weight_curves

        images = self.region_maps(methods, experiment)
        if not any(h.get("cost_weights") is not None for hs in histories.values() for h in hs):
            return images  # e.g. a history checkpointed before the weights were recorded
        return {**images, "cost_weights": cost_weight_curves(
            histories, true=self.true, threshold=self.threshold,
            title=f"{experiment}: the cost weights by outer iteration")}


