"""The tasks' settings, checked on construction: :class:`GridSettings`
(:class:`~dicrl_torch.runs.grid.GridTask`'s) and :class:`SACSettings`
(:class:`~dicrl_torch.runs.continuous.SACTask`'s, grouped: the warm-up, the last solve, the
table's rollouts and the greedy baseline).

A task builds its settings before anything else, and ``experiments/common.py`` builds
them from a config before anything is computed (``GridTask.check_settings``,
``SACTask.check_settings``), so each rule lives here once. A value out of range raises
:class:`~dicrl_torch.checks.InvalidSetting` naming the task's keyword argument
(``warmup_checks``), which a config reports under its own key.

Rules of the learned-constraint threshold and of the trainer's options live with them
(:func:`~dicrl_torch.metrics.check_threshold`,
:func:`~dicrl_torch.algos.dicrl.check_trainer_options`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dicrl_torch.algos.dicrl import check_trainer_options
from dicrl_torch.checks import (
    InvalidSetting,
    is_int,
    setting_bool,
    setting_choice,
    setting_int,
    setting_number,
)
from dicrl_torch.metrics import check_threshold

__all__ = ["CONSTRAINT_RULES", "EVAL_ACTIONS", "EVAL_POLICIES", "FINAL_SCORES", "GREEDY_BASELINE",
           "GRID_BASELINES", "GreedyBaseline", "GridSettings", "LastSolve", "SACSettings",
           "TableRollouts", "WarmUp", "check_greedy_stop", "check_split", "with_defaults"]

# How a trained learner's η̄ and ω_c become its constraint set (docs/design.md §6):
# "certificate" (ours, certify_constraints) or "threshold" (the paper's ω_c,j >= threshold).
CONSTRAINT_RULES: tuple[str, ...] = ("certificate", "threshold")
# The grid's baseline rows (names as in the paper) and the greedy's demonstrator model.
GRID_BASELINES = {"ME-greedy": "me", "MCE-greedy": "mce"}
# The continuous games' one greedy row: ME and MCE coincide on a (nearly) deterministic game.
GREEDY_BASELINE = "M(C)E-greedy"
EVAL_ACTIONS: tuple[str, ...] = ("mean", "sampled")
EVAL_POLICIES: tuple[str, ...] = ("sac", "plan")
"""How a learner acts in the table's rollouts: the SAC policy of a last solve, or planning
on its learned game with the nominal model (a task with ``make_planner``)."""
FINAL_SCORES: tuple[str, ...] = ("penalised_return", "learned_success")


def check_split(split: Any) -> tuple[int, ...]:
    """``split`` (demonstrations per learner, in learner order) as a tuple of ints.

    Raises:
        InvalidSetting: not a non-empty sequence of ints >= 1.
    """
    if not _is_list(split) or not split or not all(is_int(m) and m >= 1 for m in split):
        raise InvalidSetting("split", list(split) if _is_list(split) else split,
                             "a non-empty list of ints >= 1, one per learner (a learner "
                             "without trajectories has nothing to learn from)", "[10,20,30,40]")
    return tuple(int(m) for m in split)


def _is_list(value: Any) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, str | bytes)


def check_greedy_stop(epsilon: Any, max_constraints: Any) -> tuple[float | None, int | None]:
    """M(C)E-greedy's stopping rule (both worlds): ``baseline_epsilon`` (gain per
    trajectory below which it stops; None: BIC, ``ln(m)/(2m)``) and
    ``baseline_max_constraints`` (None: no limit).

    Raises:
        InvalidSetting: either out of range.
    """
    return (setting_number("baseline_epsilon", epsilon, low=0, example=0.023,
                           none="BIC: ln(m)/(2m)", why="nats per trajectory"),
            setting_int("baseline_max_constraints", max_constraints, least=0, example=20,
                        none="no limit"))


def with_defaults(function: Callable, names: Sequence[str], given: Mapping[str, Any]
                  ) -> dict[str, Any]:
    """``given`` completed to every one of ``names`` by ``function``'s defaults (a task's
    signature is the one place of its settings' defaults). A name without either is left
    out, for the settings' constructor to name."""
    params = inspect.signature(function).parameters
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise TypeError(f"unknown settings {unknown}; the settings are {sorted(names)}.")
    out = {n: params[n].default for n in names
           if n in params and params[n].default is not inspect.Parameter.empty}
    return {**out, **given}


def _split_and_seed(split: Any, seed: Any, seeds: str) -> dict[str, Any]:
    """Every task's ``split`` (:func:`check_split`) and ``seed`` (``seeds``: what it
    seeds), checked."""
    return {"split": check_split(split),
            "seed": setting_int("seed", seed, least=0, example=0, why=f"it seeds {seeds}")}


def _sac_timesteps(timesteps: Any) -> int:
    """``SACTask``'s ``timesteps``, checked."""
    return setting_int("timesteps", timesteps, example=2000, why="SAC env steps per solve")


def _frozen_set(obj: Any, **values: Any) -> None:
    """Store checked (normalised) values on a frozen dataclass."""
    for name, value in values.items():
        object.__setattr__(obj, name, value)


@dataclass(frozen=True)
class GridSettings:
    """:class:`~dicrl_torch.runs.grid.GridTask`'s settings (its keyword arguments of the
    same names; their meaning: its docstring), checked and normalised on construction.

    Raises:
        InvalidSetting: the first setting out of range, naming it.
    """

    split: Sequence[int]
    seed: int
    eval_episodes: int
    expert_temperature: float
    constraint_rule: str
    certificate_temperature: float
    certificate_min_probability: float
    certificate_network: bool
    certificate_shard_fits: bool
    threshold: float
    prune_min_gain: float | None
    baselines: Sequence[str]
    baseline_epsilon: float | None
    baseline_max_constraints: int | None

    def __post_init__(self) -> None:
        epsilon, most = check_greedy_stop(self.baseline_epsilon, self.baseline_max_constraints)
        _frozen_set(
            self, **_split_and_seed(self.split, self.seed, "the demonstrations and evaluation"),
            eval_episodes=setting_int("eval_episodes", self.eval_episodes, example=200,
                                      why="evaluation episodes per table row"),
            expert_temperature=setting_number("expert_temperature", self.expert_temperature,
                                              low=0, example=0.0, why="0: optimal experts"),
            constraint_rule=setting_choice(
                "constraint_rule", self.constraint_rule, CONSTRAINT_RULES,
                why="the certified set of the learner's demonstrations, or the paper's "
                    "ω_c >= threshold"),
            certificate_temperature=setting_number(
                "certificate_temperature", self.certificate_temperature, low=0, example=0.0,
                why="the certificate's experts; 0: optimal"),
            certificate_min_probability=setting_number(
                "certificate_min_probability", self.certificate_min_probability, low=0,
                high=1, low_open=True, example=0.001,
                why="per-trajectory probability that certifies a feature"),
            certificate_network=setting_bool("certificate_network",
                                             self.certificate_network),
            certificate_shard_fits=setting_bool("certificate_shard_fits",
                                                self.certificate_shard_fits),
            threshold=check_threshold(self.threshold),
            prune_min_gain=setting_number("prune_min_gain", self.prune_min_gain, low=0,
                                          example=0.001, none="keep every constraint",
                                          why="nats per trajectory"),
            baselines=self._baselines(), baseline_epsilon=epsilon,
            baseline_max_constraints=most)

    def _baselines(self) -> tuple[str, ...]:
        names = self.baselines
        if not _is_list(names) or any(n not in GRID_BASELINES for n in names) \
                or len(set(names)) != len(names):
            raise InvalidSetting("baselines", list(names) if _is_list(names) else names,
                                 f"a list of distinct names among "
                                 f"{list(GRID_BASELINES)} (the rows to add; [] for none)",
                                 "[ME-greedy,MCE-greedy]")
        return tuple(names)


@dataclass(frozen=True)
class WarmUp:
    """The SAC warm-up on ``η(0), ω_c(0)``, paid once per run (``SACTask``'s
    ``warmup_*``).

    Attributes:
        timesteps: pre-training steps (0: none).
        restarts, checks: with either above 1, ``restarts`` lineages of ``timesteps``
            steps each, scored after each of ``checks`` chunks by the share of agents at
            their goals in the nominal game (no constraint is known yet); the best chunk
            is kept (a lineage can strand an agent on a wall for good, and its visits
            become false constraints; docs/drones.md).
        until_success: a lineage stops at its first chunk at which this share of the
            agents reach their goals (the steps left would buy nothing the score can
            see), or None: every step is trained. Needs ``checks`` > 1.
    """

    timesteps: int
    restarts: int
    checks: int
    until_success: float | None = None

    def __post_init__(self) -> None:
        t = setting_int("warmup_timesteps", self.timesteps, least=0, example=30000,
                        why="SAC pre-training steps")
        restarts = setting_int("warmup_restarts", self.restarts, example=3,
                               why="warm-up lineages; the best-scored chunk is kept")
        checks = setting_int("warmup_checks", self.checks, example=3,
                             why="scored chunks per warm-up lineage")
        if t and checks > t:
            raise InvalidSetting("warmup_checks", checks, f"an int in [1, {{warmup_timesteps}}"
                                 f"={t}] (each scored chunk needs a step)", min(3, t))
        until = setting_number("warmup_until_success", self.until_success, low=0,
                               high=1, low_open=True, example=1.0, none="train every step",
                               why="the share of agents at their goals that ends a lineage")
        if until is not None and checks == 1:
            raise InvalidSetting("warmup_until_success", until,
                                 "null with {warmup_checks}=1 (a lineage stops only after "
                                 "a scored chunk; set warmup_checks to e.g. 3)", "null")
        _frozen_set(self, timesteps=t, restarts=restarts, checks=checks,
                    until_success=until)


@dataclass(frozen=True)
class LastSolve:
    """The last solve on each learned ``(η̄, ω_c)``, whose policy the table evaluates
    (``SACTask``'s ``final_*``;
    :meth:`~dicrl_torch.solvers.sac.SACConstrainedSolver.solve_keeping_best`).

    Attributes:
        timesteps: SAC steps.
        checks: scored chunks, the best-scored networks kept (1: no selection).
        restarts: continuations from the same state, the best chunk of any kept (1: the
            solver's own).
        score: how the chunks are ranked, one of :data:`FINAL_SCORES`.
        margin: metres the penalty's cells are grown by (a cost basis's
            ``dilated(margin)``), so that the deployed policy keeps clear of its learned
            constraints instead of grazing them; 0: none.
    """

    timesteps: int
    checks: int
    restarts: int
    score: str
    margin: float

    def __post_init__(self) -> None:
        t = setting_int("final_timesteps", self.timesteps, example=2000,
                        why="SAC steps of the last solve, on the learned (η̄, ω_c)")
        checks = setting_int("final_checks", self.checks, example=1,
                             why="scored chunks of the last solve; 1: no selection")
        if checks > t:
            raise InvalidSetting("final_checks", checks, f"an int in [1, {{final_timesteps}}"
                                 f"={t}] (each scored chunk needs a step)", min(8, t))
        _frozen_set(
            self, timesteps=t, checks=checks,
            restarts=setting_int("final_restarts", self.restarts, example=1,
                                 why="independent continuations of the last solve; 1: the "
                                     "solver's own"),
            score=setting_choice("final_score", self.score, FINAL_SCORES,
                                 why="how the last solve's chunks are ranked"),
            margin=setting_number("final_margin", self.margin, low=0, high=0.5,
                                  high_open=True, example=0.2,
                                  why="metres the last solve's penalty cells are grown by; "
                                      "0: none"))


@dataclass(frozen=True)
class TableRollouts:
    """How the table's rows are measured (``SACTask``'s ``eval_*`` and ``planner``).

    Attributes:
        episodes: true-game rollouts per row.
        action: ``"mean"`` or ``"sampled"``, the actions of the row's SR and CVR (the row
            holds both).
        policy: ``"sac"`` (the policy of a last solve) or ``"plan"`` (planning on the
            learned game in the nominal model, with ``planner`` the task's planner
            settings, which the task checks).
    """

    episodes: int
    action: str
    policy: str
    planner: dict | None

    def __post_init__(self) -> None:
        planner = {} if self.planner is None else self.planner
        if not isinstance(planner, dict):
            raise InvalidSetting("planner", planner, "None or a dict of the task's planner "
                                 "settings", "{'replan': 5}")
        _frozen_set(
            self, planner=dict(planner),
            episodes=setting_int("eval_episodes", self.episodes, example=100,
                                 why="true-game rollouts per table row"),
            action=setting_choice("eval_action", self.action, EVAL_ACTIONS,
                                  why="the actions of the table's SR and CVR rollouts"),
            policy=setting_choice("eval_policy", self.policy, EVAL_POLICIES,
                                  why="the last solve's SAC policy, or planning on the "
                                      "learned game"))


@dataclass(frozen=True)
class GreedyBaseline:
    """M(C)E-greedy on a continuous game (``SACTask``'s ``baseline*``): given D-ICRL's
    learned reward, each candidate constraint set trained as a per-step penalty.

    Attributes:
        run: build it (a table row).
        penalty: reward units per step in a constrained cell.
        timesteps: SAC steps per greedy trial.
        epsilon, max_constraints: the stopping rule (:func:`check_greedy_stop`).
    """

    run: bool
    penalty: float
    timesteps: int
    epsilon: float | None
    max_constraints: int | None

    def __post_init__(self) -> None:
        epsilon, most = check_greedy_stop(self.epsilon, self.max_constraints)
        _frozen_set(
            self, run=setting_bool("baseline", self.run), epsilon=epsilon,
            max_constraints=most,
            penalty=setting_number("baseline_penalty", self.penalty, low=0, low_open=True,
                                   example=10.0,
                                   why="reward units per step in a constrained cell"),
            timesteps=setting_int("baseline_timesteps", self.timesteps, example=3000,
                                  why="SAC steps per greedy trial"))


@dataclass(frozen=True)
class SACSettings:
    """:class:`~dicrl_torch.runs.continuous.SACTask`'s settings, grouped and checked on
    construction; :meth:`from_keywords` builds them from the task's flat keyword
    arguments.

    Attributes:
        split, seed: demonstrations per learner; the run's seed.
        timesteps, n_eval_episodes: SAC steps and rollouts per inner solve.
        init_reward_weights, init_multiplier, init_cost_weights: ``η(0)``, ``ω_c(0)``
            (the trainer's rules).
        threshold: ``ω_c,j >= threshold`` marks a learned constraint.
        rollouts, warmup, last_solve, baseline: the groups.
    """

    split: tuple[int, ...]
    seed: int
    timesteps: int
    n_eval_episodes: int
    init_reward_weights: float
    init_multiplier: float
    init_cost_weights: float
    threshold: float
    rollouts: TableRollouts
    warmup: WarmUp
    last_solve: LastSolve
    baseline: GreedyBaseline

    def __post_init__(self) -> None:
        check_trainer_options(init_reward_weights=self.init_reward_weights,
                              init_multiplier=self.init_multiplier,
                              init_cost_weights=self.init_cost_weights)
        _frozen_set(
            self, **_split_and_seed(self.split, self.seed, "the clones and the evaluation"),
            timesteps=_sac_timesteps(self.timesteps),
            n_eval_episodes=setting_int("n_eval_episodes", self.n_eval_episodes, example=10,
                                        why="rollouts per estimate of μ_r and μ_c"),
            threshold=check_threshold(self.threshold),
            init_reward_weights=float(self.init_reward_weights),
            init_multiplier=float(self.init_multiplier),
            init_cost_weights=float(self.init_cost_weights))

    @classmethod
    def from_keywords(cls, *, split, seed, eval_episodes, eval_action, timesteps,
                      n_eval_episodes, warmup_timesteps, warmup_restarts, warmup_checks,
                      warmup_until_success, init_reward_weights, init_multiplier, init_cost_weights,
                      final_timesteps, final_checks, final_restarts, final_score,
                      final_margin, eval_policy, planner, threshold, baseline,
                      baseline_penalty, baseline_timesteps, baseline_epsilon,
                      baseline_max_constraints) -> SACSettings:
        """From ``SACTask``'s keyword arguments of the same names (``final_timesteps``
        None: ``timesteps``).

        Raises:
            InvalidSetting: the first setting out of range, naming its keyword.
        """
        inner = _sac_timesteps(timesteps)
        return cls(
            split=split, seed=seed, timesteps=inner, n_eval_episodes=n_eval_episodes,
            init_reward_weights=init_reward_weights, init_multiplier=init_multiplier,
            init_cost_weights=init_cost_weights, threshold=threshold,
            rollouts=TableRollouts(episodes=eval_episodes, action=eval_action,
                                   policy=eval_policy, planner=planner),
            warmup=WarmUp(timesteps=warmup_timesteps, restarts=warmup_restarts,
                          checks=warmup_checks, until_success=warmup_until_success),
            last_solve=LastSolve(timesteps=inner if final_timesteps is None
                                 else final_timesteps, checks=final_checks,
                                 restarts=final_restarts, score=final_score,
                                 margin=final_margin),
            baseline=GreedyBaseline(run=baseline, penalty=baseline_penalty,
                                    timesteps=baseline_timesteps, epsilon=baseline_epsilon,
                                    max_constraints=baseline_max_constraints))
