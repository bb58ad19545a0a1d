"""Your own game in one call: :func:`fit` trains D-ICRL's learners on your demonstrations
and returns what they learned (:class:`FitResult`), in the spirit of stable-baselines3's
``SAC("MlpPolicy", env).learn(n)``.

You bring three things (README, "Your own environment"):

1. an env factory ``make_env(constrained)`` returning your game as one gymnasium agent
   (e.g. a PettingZoo ``ParallelEnv`` wrapped in
   :class:`~dicrl_torch.envs.joint.JointAgentEnv`): ``constrained=False`` the nominal game
   the learners train in, ``True`` the true game the table's SR and CVR are measured in;
2. a reward and a cost feature basis over joint states ``[..., N, d_s]``
   (:mod:`dicrl_torch.features.continuous`);
3. the demonstrations (:class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations`
   or their ``.npz`` file).

Everything else defaults to the settings of ``experiment=mpe_quick`` (the constrained MPE
spread; ``configs/experiment/mpe_quick.yaml`` over ``configs/solver/sac.yaml``,
``configs/algo/dicrl.yaml`` and ``configs/graph/time_varying.yaml``): :data:`SAC_DEFAULTS`,
:data:`TASK_DEFAULTS`, :data:`DICRL_DEFAULTS`, each overridable key by key. :func:`fit`
only builds the run's pieces (a :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver`, a
:class:`~dicrl_torch.runs.continuous.SACTask`, a
:class:`~dicrl_torch.runs.runner.TrainerSpec` and
:class:`~dicrl_torch.runs.runner.RunSettings`) and hands them to
:func:`~dicrl_torch.runs.runner.run_all_in_one`, the runner of every experiment: build those
yourself for anything it does not expose (one process per learner, a task subclass with
your game's own metrics and pictures, as :class:`~dicrl_torch.runs.mpe.MPETask` does).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.dicrl import StepSizes
from dicrl_torch.checks import check_int, is_int
from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.comm.graphs import CompleteSchedule, TimeVaryingSchedule
from dicrl_torch.demos.continuous import ContinuousDemonstrations, load_continuous_demonstrations
from dicrl_torch.logger import NullLogger, TensorBoardLogger
from dicrl_torch.runs.checkpoints import training_config
from dicrl_torch.runs.continuous import SACTask, derived_seed
from dicrl_torch.runs.runner import RunSettings, TrainerSpec, run_all_in_one

__all__ = ["DICRL_DEFAULTS", "FINAL_RATIO", "SAC_DEFAULTS", "TASK_DEFAULTS", "WARMUP_RATIO",
           "FitResult", "fit"]

SAC_DEFAULTS: Mapping[str, Any] = MappingProxyType(dict(
    n_envs=4, gradient_steps=1, ent_coef=0.1, learning_rate=1e-3, gamma=0.99,
    estimate_action="sampled", batch_size=256, learning_starts=1000, buffer_size=100_000,
    net_arch=(64, 64), demo_fraction=0.25, demo_bc=0.0, demo_value_bound=False, tau=0.005,
    scale_observations=True, per_agent_critics=True, split_cost_critic=True, device="cpu",
    absorbing=False, engine="lean"))
""":class:`~dicrl_torch.solvers.sac.SACConstrainedSolver`'s keyword arguments
(``sac_kwargs`` overrides them): ``configs/solver/sac.yaml``'s ``solver`` with
``mpe_quick``'s overrides. ``per_agent_critics`` needs bases with ``agent_shares()``
(every :class:`~dicrl_torch.features.continuous.ContinuousFeatureBasis` has one)."""

TASK_DEFAULTS: Mapping[str, Any] = MappingProxyType(dict(
    n_eval_episodes=40, eval_action="mean", warmup_restarts=1, warmup_checks=1,
    warmup_until_success=None,
    final_checks=6, final_restarts=1, final_score="learned_success", final_margin=0.0,
    threshold=0.5))
""":class:`~dicrl_torch.runs.continuous.SACTask`'s other keyword arguments (``task_kwargs``
overrides them): ``configs/solver/sac.yaml`` with ``mpe_quick``'s overrides, and
``configs/algo/dicrl.yaml``'s ``threshold``. ``start_states`` (not here) defaults to the
demonstrations' first joint states: samples of the start distribution, whose cost features
no policy can avoid and which are thus no constraint (mpe_quick's task gives samples of
its start region; ``task_kwargs={"start_states": None}``: none)."""

DICRL_DEFAULTS: Mapping[str, Any] = MappingProxyType(dict(
    inner_steps=3, lsca_curvature=10.0, prune_accrued=True, init_reward_weights=1.0,
    init_multiplier=-5.0, init_cost_weights=0.0, inner_method="paper", inner_step=0.005,
    merge_stateful_inner=False,
    steps=MappingProxyType(dict(alpha_bar=0.002, beta_bar=0.5, beta_power=0.65,
                                multiplier_scale=10.0)),
    schedules=None))
"""The D-ICRL trainer's settings (``dicrl_kwargs`` overrides them):
``configs/algo/dicrl.yaml`` with ``mpe_quick``'s overrides. ``steps``: a
:class:`~dicrl_torch.algos.dicrl.StepSizes` or a dict of its fields (a dict overrides only
the fields it names). ``schedules``: ``n_learners -> (inner W(k), outer W̄(n))``; None:
``configs/graph/time_varying.yaml``'s (a time-varying inner graph of period 2, self-weight
0.5, seed 0; the complete outer graph). ``init_*``: ``η(0)``, ``ω_c(0)``, for the SAC
warm-up and the trainer alike."""

WARMUP_RATIO = 40
"""``warmup_timesteps`` defaults to this many times ``timesteps`` (mpe_quick: 40 000 / 1 000)."""
FINAL_RATIO = 24
"""``final_timesteps`` defaults to this many times ``timesteps`` (mpe_quick: 24 000 / 1 000)."""

# The keyword arguments fit sets itself, per mapping: the fix each message names.
_ARGUMENT = "pass it as fit's own {}=..."
_SHARED = "set it in dicrl_kwargs (the SAC warm-up and the trainer share it)"
_RESERVED: dict[str, dict[str, str]] = {
    "sac_kwargs": {"env_factory": _ARGUMENT.format("make_env"),
                   "reward_basis": _ARGUMENT.format("reward_basis"),
                   "cost_basis": _ARGUMENT.format("cost_basis"),
                   "seed": _ARGUMENT.format("seed")},
    "task_kwargs": {"solver": "fit builds it (its settings: sac_kwargs)",
                    "demos": _ARGUMENT.format("demonstrations"),
                    **{k: _ARGUMENT.format(k) for k in (
                        "split", "seed", "true_constraints", "eval_episodes", "timesteps",
                        "warmup_timesteps", "final_timesteps")},
                    "init_reward_weights": _SHARED, "init_multiplier": _SHARED,
                    "init_cost_weights": _SHARED},
    "dicrl_kwargs": {},
}


@dataclass(frozen=True)
class FitResult:
    """What :func:`fit` learned, and where the run lies.

    Attributes:
        out: the run directory (``results.json``, ``checkpoint.pt``, ``demos.npz``, one
            constraint strip per learner, ``cost_weights.png``).
        results: ``results.json``'s record (``methods``: a ``"D-ICRL"`` row per learner,
            ``"C-ICRL"``'s too when it ran).
        feature_names: ``[l_c]`` the cost basis's feature names.
        constraints: each D-ICRL learner's learned constraint set (``ω_c,j >=
            threshold``), as feature names in basis order.
        cost_weights: ``[N_L, l_c]`` float64 each learner's ``ω_c`` after training.
        reward_weights: ``[N_L, l_r]`` float64 each learner's averaged ``ω̄_r``.
        multipliers: ``[N_L]`` float64 each learner's averaged ``λ̄``.
    """

    out: Path
    results: dict
    feature_names: list[str]
    constraints: list[list[str]]
    cost_weights: torch.Tensor
    reward_weights: torch.Tensor
    multipliers: torch.Tensor

    @property
    def rows(self) -> list[dict]:
        """The D-ICRL learners' table rows (``FPR``, ``FNR``, ``CVR``, ``SR``, ...)."""
        return self.results["methods"]["D-ICRL"]["learners"]

    @property
    def constraint_masks(self) -> torch.Tensor:
        """``[N_L, l_c]`` bool: :attr:`constraints` as masks over the cost features."""
        masks = torch.zeros(len(self.constraints), len(self.feature_names), dtype=torch.bool)
        for v, names in enumerate(self.constraints):
            masks[v, [self.feature_names.index(n) for n in names]] = True
        return masks


def fit(
    *, make_env: Callable[..., Any], reward_basis: torch.nn.Module,
    cost_basis: torch.nn.Module, demonstrations: Any, split: int | Sequence[int],
    out: str | os.PathLike[str], seed: int = 0, outer_iterations: int = 6,
    timesteps: int = 1000, warmup_timesteps: int | None = None,
    final_timesteps: int | None = None, eval_episodes: int = 100,
    true_constraints: Any = None, sac_kwargs: Mapping[str, Any] | None = None,
    task_kwargs: Mapping[str, Any] | None = None,
    dicrl_kwargs: Mapping[str, Any] | None = None, run_c_icrl: bool = False,
    resume: bool = False, logger: Any = None, experiment: str | None = None,
) -> FitResult:
    """Learn your game's constraints from demonstrations shared over learners: D-ICRL
    (the paper's Algorithms 1-2) with SAC inner solvers, every learner in this process.

    Writes into ``out`` what ``experiments/train.py`` writes into its run directory
    (``results.json``, ``checkpoint.pt`` after every outer iteration, ``demos.npz``, the
    constraint strips and figures) and prints the results table.

    Args:
        make_env: ``make_env(constrained=False)`` the nominal game the learners train in
            (they do not know the constraints), ``make_env(constrained=True)`` the true
            game of the table's SR and CVR: one gymnasium agent acting for every agent
            (:class:`~dicrl_torch.envs.joint.JointAgentEnv` wraps a PettingZoo
            ``ParallelEnv``), ``info["state"]`` the joint state ``[N, d_s]``, and per
            agent ``violated`` (and ``reached``, with goals) in its step info.
        reward_basis: joint states ``[..., N, d_s]`` -> reward features ``[..., l_r]``.
        cost_basis: joint states ``[..., N, d_s]`` -> cost features ``[..., l_c]``; the
            learned constraint sets are subsets of its features, by name.
        demonstrations: the experts' episodes (states ``[m, T+1, N, d_s]``, actions
            ``[m, T, N, d_a]``): a ``ContinuousDemonstrations`` (e.g. of
            :func:`~dicrl_torch.demos.continuous.record_demonstrations`), anything with
            ``to_continuous()``, or the path of their ``.npz`` file; checked against the
            env's spaces before anything trains.
        split: demonstrations per learner, in order (summing to ``m``), e.g. ``[10, 10]``;
            or the number of learners, which then share them as evenly as they divide
            (the first ones one more).
        out: the run directory (created).
        seed: the run's only source of randomness.
        outer_iterations: D-ICRL's outer iterations (``algo.outer_iterations``).
        timesteps: SAC steps per inner solve (``solver.timesteps``).
        warmup_timesteps: SAC steps of the warm-up on ``η(0), ω_c(0)`` that every learner
            starts from; None: :data:`WARMUP_RATIO` x ``timesteps``.
        final_timesteps: SAC steps of each learner's last solve on its learned game (the
            evaluated policy); None: :data:`FINAL_RATIO` x ``timesteps``.
        eval_episodes: true-game episodes per table row.
        true_constraints: ``[l_c]`` bool (array or tensor), the cost features that are true
            constraints of your game, e.g. ``PositionCellBasis.true_constraints()``; None:
            no ground truth (FPR and FNR are then None).
        sac_kwargs: overrides of :data:`SAC_DEFAULTS` (any keyword argument of
            ``SACConstrainedSolver`` but ``env_factory``, the bases and ``seed``).
        task_kwargs: overrides of :data:`TASK_DEFAULTS` (any keyword argument of
            ``SACTask`` that ``fit`` does not take itself, e.g. ``baseline=True`` for the
            M(C)E-greedy row, or ``start_states`` ``[P, N, d_s]`` spanning your start
            distribution's support; default: the demonstrations' first states).
        dicrl_kwargs: overrides of :data:`DICRL_DEFAULTS`.
        run_c_icrl: also train C-ICRL, one learner holding every demonstration (the
            paper's centralized comparison row; about doubles the run).
        resume: continue from ``out``'s checkpoint (refused when it was written with
            other settings); a finished run resumed with more ``outer_iterations`` trains
            on.
        logger: None (nothing logged), ``"tensorboard"`` (event files under ``out/tb``)
            or a :mod:`dicrl_torch.logger` logger.
        experiment: the run's name in ``results.json``; None: ``out``'s name.

    Returns:
        The learned sets and weights per learner and the results record.

    Raises:
        ValueError: a setting out of range or of the wrong kind, an unknown or
            reserved key in a ``*_kwargs`` mapping, a basis the SAC settings cannot use,
            demonstrations that do not fit the env or ``split``, or a checkpoint of other
            settings on ``resume``; the message names the value and the fix.
        FileNotFoundError: ``demonstrations`` names a file that does not exist.
        dicrl_torch.runs.signals.Interrupted: SIGINT/SIGTERM stopped the run after a
            checkpoint; ``resume=True`` continues it.
    """
    from dicrl_torch.solvers.sac import SACConstrainedSolver  # stable-baselines3: here only

    t_start = time.perf_counter()
    if not callable(make_env):
        raise ValueError(f"make_env must be callable as make_env(constrained=False) -> your "
                         f"joint env, got {type(make_env).__name__}; e.g. def make_env("
                         f"constrained=False): return JointAgentEnv(MyGame(constrained="
                         f"constrained)).")
    seed = check_int("seed", seed, 0)
    resume, run_c_icrl = _flag("resume", resume), _flag("run_c_icrl", run_c_icrl)
    out = Path(out)
    run_logger = _logger(logger, out)
    outer_iterations = check_int("outer_iterations", outer_iterations)
    timesteps = check_int("timesteps", timesteps)
    warmup_timesteps = (WARMUP_RATIO * timesteps if warmup_timesteps is None
                        else check_int("warmup_timesteps", warmup_timesteps, 0))
    final_timesteps = (FINAL_RATIO * timesteps if final_timesteps is None
                       else check_int("final_timesteps", final_timesteps))
    sac = _merged("sac_kwargs", SAC_DEFAULTS, sac_kwargs,
                  _parameters(SACConstrainedSolver))
    task = _merged("task_kwargs", TASK_DEFAULTS, task_kwargs, _parameters(SACTask))
    algo = _merged("dicrl_kwargs", DICRL_DEFAULTS, dicrl_kwargs, set(DICRL_DEFAULTS))
    steps = _step_sizes(algo["steps"])
    schedules = algo["schedules"] or _default_schedules
    if not callable(schedules):
        raise ValueError(f"dicrl_kwargs['schedules'] must be callable as n_learners -> "
                         f"(inner, outer) mixing schedules, or None, got "
                         f"{type(schedules).__name__}.")
    if sac["per_agent_critics"]:
        for role, basis in (("reward_basis", reward_basis), ("cost_basis", cost_basis)):
            if not callable(getattr(basis, "agent_shares", None)):
                raise ValueError(
                    f"{role} {type(basis).__name__} has no agent_shares(), which the default "
                    f"per-agent critics need; subclass dicrl_torch.features.continuous."
                    f"ContinuousFeatureBasis (or wrap a network in ModuleBasis), or pass "
                    f"sac_kwargs={{'per_agent_critics': False}}.")
    solver = SACConstrainedSolver(env_factory=make_env, reward_basis=reward_basis,
                                  cost_basis=cost_basis, seed=derived_seed(seed, 1), **sac)
    demos = _demonstrations(demonstrations, solver.spec)
    split = _split(split, demos)
    init = {k: algo[k] for k in ("init_reward_weights", "init_multiplier",
                                 "init_cost_weights")}
    if "start_states" not in task:  # P0's support as the demonstrations sample it
        task["start_states"] = _start_states(demos)
    run_task = SACTask(solver=solver, demos=demos, split=split, seed=seed,
                       true_constraints=_mask(true_constraints), eval_episodes=eval_episodes,
                       timesteps=timesteps, warmup_timesteps=warmup_timesteps,
                       final_timesteps=final_timesteps, **init, **task)
    spec = TrainerSpec(
        schedules=schedules, steps=steps, inner_step=float(algo["inner_step"]),
        n_shards=len(split),
        options=dict(inner_steps=algo["inner_steps"], lsca_curvature=algo["lsca_curvature"],
                     prune_accrued=algo["prune_accrued"], inner_method=algo["inner_method"],
                     merge_stateful_inner=algo["merge_stateful_inner"]))
    name = out.resolve().name if experiment is None else str(experiment)
    config = _run_config(name=name, seed=seed, split=split, demos=demos,
                         env=(make_env, solver.spec),
                         reward_basis=reward_basis, cost_basis=cost_basis, sac=sac, task=task,
                         algo={**algo, "steps": dataclasses.asdict(steps)},
                         timesteps=(timesteps, warmup_timesteps, final_timesteps),
                         outer_iterations=outer_iterations, eval_episodes=eval_episodes,
                         run_c_icrl=run_c_icrl)
    flat = training_config(config)
    flat["demonstrations.sha256"] = config["demonstrations"]["sha256"]
    settings = RunSettings(experiment=name, config=config, training_config=flat,
                           outer_iterations=outer_iterations, resume=resume,
                           run_c_icrl=run_c_icrl)
    out.mkdir(parents=True, exist_ok=True)
    results = run_all_in_one(run_task, settings, spec, out=out, t_start=t_start,
                             logger=run_logger,
                             communicator=lambda n: SimulatedCommunicator(n_learners=n))
    return _result(out, results, list(cost_basis.names))


# ---------------------------------------------------------------------- the pieces
def _default_schedules(n_learners: int) -> tuple[TimeVaryingSchedule, CompleteSchedule]:
    """``configs/graph/time_varying.yaml``: the inner graph time-varying (period 2,
    self-weight 0.5, seed 0), the outer one complete."""
    return (TimeVaryingSchedule(n_learners=n_learners, period=2, self_weight=0.5, seed=0),
            CompleteSchedule(n_learners=n_learners))


def _parameters(cls: type) -> set[str]:
    """The keyword arguments of ``cls``'s constructor."""
    return {p for p in inspect.signature(cls.__init__).parameters if p != "self"}


def _merged(what: str, defaults: Mapping[str, Any], given: Mapping[str, Any] | None,
            allowed: set[str]) -> dict[str, Any]:
    """``defaults`` updated by ``given``, whose keys must be ``allowed`` and not set by
    ``fit`` itself."""
    if given is None:
        given = {}
    if not isinstance(given, Mapping):
        raise ValueError(f"{what} must be a dict of keyword arguments or None, got "
                         f"{type(given).__name__}; e.g. {what}={{...}}.")
    reserved = _RESERVED[what]
    for key in given:
        if key in reserved:
            raise ValueError(f"{what} must not set {key!r}: {reserved[key]}.")
        if key not in allowed:
            raise ValueError(f"{what} has an unknown key {key!r}; the keys it takes are "
                             f"{sorted(allowed - set(reserved))}.")
    merged = {**defaults, **given}
    if isinstance(merged.get("steps"), Mapping):
        merged["steps"] = dict(merged["steps"])
    return merged


def _step_sizes(steps: Any) -> StepSizes:
    """``steps`` (a StepSizes or a dict of some of its fields) over mpe_quick's."""
    if isinstance(steps, StepSizes):
        return steps
    fields = {f.name for f in dataclasses.fields(StepSizes)}
    if not isinstance(steps, Mapping) or set(steps) - fields:
        raise ValueError(f"dicrl_kwargs['steps'] must be a StepSizes or a dict of its fields "
                         f"{sorted(fields)}, got {steps!r}.")
    return StepSizes(**{**DICRL_DEFAULTS["steps"], **steps})


def _demonstrations(demos: Any, spec: Any) -> Any:
    """A ``.npz`` path read for the env's ``N`` and ``d_s``; anything else as given
    (``SACTask`` checks it against the env)."""
    if isinstance(demos, str | os.PathLike):
        n, d_s = spec.state_shape
        return load_continuous_demonstrations(demos, n_agents=n, state_dim=d_s)
    return demos


def _split(split: Any, demos: Any) -> list[int]:
    """``split`` as episodes per learner; an int ``n``: ``n`` learners sharing them."""
    if not is_int(split):
        return split  # SACTask checks the list, naming the fix
    n_learners = check_int("split (as the number of learners)", split)
    m = _n_episodes(demos)
    if m is not None and n_learners > m:
        raise ValueError(f"split={n_learners} learners, but there are only {m} "
                         f"demonstrations; give at most {m} learners.")
    if m is None:
        return [split]  # SACTask refuses the demonstrations, naming the fix
    return [len(part) for part in np.array_split(np.arange(m), n_learners)]


def _n_episodes(demos: Any) -> int | None:
    if callable(getattr(demos, "to_continuous", None)):
        demos = demos.to_continuous()
    return demos.n_trajectories if isinstance(demos, ContinuousDemonstrations) else None


def _start_states(demos: Any) -> torch.Tensor | None:
    """``[m, N, d_s]`` the demonstrations' first joint states: draws of the start
    distribution P0, so the cost features positive there are accrued whatever the policy
    and are no constraint (:meth:`~dicrl_torch.algos.models.SACLearnerModel.start_features`);
    None where the demonstrations are not readable (``SACTask`` then refuses them)."""
    if callable(getattr(demos, "to_continuous", None)):
        demos = demos.to_continuous()
    if not isinstance(demos, ContinuousDemonstrations):
        return None
    return torch.tensor(np.asarray(demos.states[:, 0]), dtype=torch.float64)  # a copy


def _mask(true_constraints: Any) -> np.ndarray | None:
    """A ground-truth mask as numpy (a tensor is moved to the CPU); ``SACTask`` checks it."""
    if true_constraints is None:
        return None
    if isinstance(true_constraints, torch.Tensor):
        return true_constraints.detach().cpu().numpy()
    return np.asarray(true_constraints)


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {value!r}.")
    return bool(value)


def _logger(logger: Any, out: Path) -> Any:
    if logger is None:
        return NullLogger()
    if logger == "tensorboard":
        return TensorBoardLogger(out / "tb")
    missing = [m for m in ("scalar", "image", "has_run", "close")
               if not callable(getattr(logger, m, None))]
    if isinstance(logger, str) or missing:
        raise ValueError(f"logger must be None, 'tensorboard' or a dicrl_torch.logger logger "
                         f"(scalar, image, has_run, close), got {logger!r}.")
    return logger


# ---------------------------------------------------------------------- the record
def _plain(value: Any) -> Any:
    """``value`` as JSON: containers and scalars as they are, anything else by name."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, torch.device):
        return str(value)
    return _qualname(value)


def _qualname(obj: Any) -> str:
    """``module.Name`` of a function, class or method, ``partial(...)`` of a
    ``functools.partial``, and of anything else its class's."""
    if isinstance(obj, functools.partial):
        return f"partial({_qualname(obj.func)})"
    target = obj if hasattr(obj, "__qualname__") else type(obj)
    return f"{getattr(target, '__module__', None)}.{target.__qualname__}"


def _basis_record(basis: Any) -> dict[str, Any]:
    names = [str(n) for n in getattr(basis, "names", [])]
    return {"class": _qualname(basis), "dim": len(names),
            "names_sha256": hashlib.sha256("\n".join(names).encode()).hexdigest()[:16]}


def _demos_sha256(demos: Any) -> str:
    """The demonstrations' contents (the learned state depends on them, not on a path)."""
    if callable(getattr(demos, "to_continuous", None)):
        demos = demos.to_continuous()
    h = hashlib.sha256()
    for field in ("states", "actions", "lengths"):
        h.update(np.ascontiguousarray(getattr(demos, field)).tobytes())
    return h.hexdigest()[:16]


def _run_config(*, name: str, seed: int, split: list[int], demos: Any, env: tuple[Any, Any],
                reward_basis: Any, cost_basis: Any, sac: dict, task: dict, algo: dict,
                timesteps: tuple[int, int, int], outer_iterations: int, eval_episodes: int,
                run_c_icrl: bool) -> dict[str, Any]:
    """The run's settings in the Hydra config's layout (``results.json``'s ``config``;
    :func:`~dicrl_torch.runs.checkpoints.training_config` of it guards a resume)."""
    inner, warmup, final = timesteps
    make_env, spec = env
    threshold = task.pop("threshold")
    starts = task.pop("start_states", None)
    task["start_states"] = None if starts is None else f"[{len(starts)} joint states]"
    schedules = algo.pop("schedules")
    graph = ({"inner": {"_target_": "dicrl_torch.comm.graphs.TimeVaryingSchedule",
                        "period": 2, "self_weight": 0.5, "seed": 0},
              "outer": {"_target_": "dicrl_torch.comm.graphs.CompleteSchedule"}}
             if schedules is None else {"schedules": _qualname(schedules)})
    return _plain({
        "name": name, "seed": seed, "n_demonstrations": sum(split), "split": split,
        "eval_episodes": eval_episodes,
        "demonstrations": {"sha256": _demos_sha256(demos)},
        "env": {"make_env": _qualname(make_env), "name": spec.name,
                "state_shape": list(spec.state_shape), "action_dim": spec.action_dim},
        "features": {"reward": _basis_record(reward_basis), "cost": _basis_record(cost_basis)},
        "solver": {"timesteps": inner, "warmup_timesteps": warmup,
                   "final_timesteps": final, **task, "solver": sac},
        "algo": {**algo, "outer_iterations": outer_iterations, "threshold": threshold,
                 "run_c_icrl": run_c_icrl},
        "graph": graph, "comm": {"_target_": "dicrl_torch.comm.communicator.SimulatedCommunicator"},
    })


def _result(out: Path, results: dict, feature_names: list[str]) -> FitResult:
    rows = results["methods"]["D-ICRL"]["learners"]
    history = results["history"]["D-ICRL"]
    return FitResult(
        out=out, results=results, feature_names=feature_names,
        constraints=[list(row["constraints"]) for row in rows],
        cost_weights=torch.tensor(history[-1]["cost_weights"], dtype=torch.float64),
        reward_weights=torch.tensor([row["reward_weights"] for row in rows],
                                    dtype=torch.float64),
        multipliers=torch.tensor([row["multiplier"] for row in rows], dtype=torch.float64))
