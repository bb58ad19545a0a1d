"""What the entry points build from a Hydra config: the task of the configured
environment, the run's settings, the trainer's settings and the logger. The only code,
with ``config_checks``, that reads a config; everything is handed to the library
(:mod:`dicrl_torch.runs`) as built objects (docs/design.md §2).

Each environment's config group names its task builder, ``env.task._target_``: a function
``builder(cfg, rank=None)`` returning the run's task (``grid_task``, ``drone_task`` and
``mpe_task`` below for the shipped games). A game of your own registers itself the same
way, from its own config group and module, without a change here.

The value rules live in the library's constructors: :func:`check_config` builds every
settings object of a config (which computes nothing) and reports each refused value under
its config key, with ``config_checks``' problems that span groups."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import shlex
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from config_checks import (
    ConfigError,
    cross_group_problems,
    env_fit,
    is_simulated,
    misfit_options,
    unknown_keys,
)
from hydra.utils import get_class, get_method, instantiate
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dicrl_torch.checks import InvalidSetting, setting_bool
from dicrl_torch.runs.checkpoints import training_config
from dicrl_torch.runs.runner import RunSettings, TrainerSpec
from dicrl_torch.runs.settings import GREEDY_BASELINE
from dicrl_torch.solvers.drone_planning import DronePlannerSettings

# ------------------------------------------------------------------ where values come from
# Library argument -> config key, for each object built from several groups. Reading the
# values and naming a refused one go through these tables; with the nodes built from their
# _target_ (OTHER_KEYS) they are the keys the entry points read: any other is refused.
GRID_TASK_KEYS = {
    "split": "split", "seed": "seed", "eval_episodes": "eval_episodes",
    "expert_temperature": "expert_temperature", "constraint_rule": "algo.constraint_rule",
    "certificate_temperature": "algo.certificate.temperature",
    "certificate_min_probability": "algo.certificate.min_probability",
    "certificate_network": "algo.certificate.network",
    "certificate_shard_fits": "algo.certificate.shard_fits",
    "threshold": "algo.threshold", "prune_min_gain": "algo.prune_min_gain",
    "baselines": "baselines.run", "baseline_epsilon": "baselines.epsilon",
    "baseline_max_constraints": "baselines.max_constraints"}
SAC_TASK_KEYS = {
    "split": "split", "seed": "seed", "eval_episodes": "eval_episodes",
    **{k: f"solver.{k}" for k in (
        "eval_action", "timesteps", "n_eval_episodes", "warmup_timesteps", "warmup_restarts",
        "warmup_checks", "warmup_until_success", "final_timesteps", "final_checks",
        "final_restarts", "final_score", "final_margin", "eval_policy", "planner")},
    **{k: f"algo.{k}" for k in ("init_reward_weights", "init_multiplier",
                                "init_cost_weights", "threshold")},
    "baseline": "baselines.run", "baseline_penalty": "baselines.penalty",
    "baseline_timesteps": "baselines.timesteps", "baseline_epsilon": "baselines.epsilon",
    "baseline_max_constraints": "baselines.max_constraints"}
PLANNER_KEYS = {f.name: f"solver.planner.{f.name}"
                for f in dataclasses.fields(DronePlannerSettings)}
RUN_KEYS = {"outer_iterations": "algo.outer_iterations", "eval_every": "eval_every",
            "checkpoint_every": "checkpoint_every", "resume": "resume",
            "run_d_icrl": "algo.run_d_icrl", "run_c_icrl": "algo.run_c_icrl"}
TRAINER_KEYS = {k: f"algo.{k}" for k in (
    "inner_steps", "inner_step", "lsca_curvature", "prune_accrued", "init_cost_weights",
    "init_reward_weights", "init_multiplier", "inner_method", "merge_stateful_inner")}
OTHER_KEYS = ("name", "n_demonstrations", "shard_files", "algo.c_icrl_beside_learners",
              "env", "features.reward", "features.cost", "solver.solver", "algo.steps",
              "graph.inner", "graph.outer", "comm", "logger")
READ_KEYS = {*GRID_TASK_KEYS.values(), *SAC_TASK_KEYS.values(), *PLANNER_KEYS.values(),
             *RUN_KEYS.values(), *TRAINER_KEYS.values(), *OTHER_KEYS}


_UNSET = object()  # what a key the config lacks reads as (None is a value)


@contextlib.contextmanager
def config_keys(keys: Mapping[str, str]) -> Iterator[None]:
    """Re-raise a value the library refuses (:class:`InvalidSetting`, naming its argument)
    under its config key: ``keys`` maps argument -> key."""
    try:
        yield
    except InvalidSetting as e:
        raise e.renamed(keys) from None


def node_keys(node) -> dict[str, str]:
    """Argument -> config key of the node's own keys (``gamma`` -> ``env.model.gamma``)."""
    path = node._get_full_key(None)
    return {k: f"{path}.{k}" if path else str(k) for k in node}


def read(cfg, keys: Mapping[str, str], skip: Sequence[str] = ()) -> dict[str, Any]:
    """The values ``cfg`` sets of ``keys`` (argument -> config key) as plain Python, by
    argument; keys it lacks, and those under the paths ``skip``, are left out (the
    library's defaults apply)."""
    values = {}
    for arg, key in keys.items():
        value = OmegaConf.select(cfg, key, default=_UNSET)
        if value is not _UNSET and not any(key.startswith(f"{p}.") for p in skip):
            values[arg] = OmegaConf.to_container(value, resolve=True) \
                if OmegaConf.is_config(value) else value
    return values


def build(cfg, **objects):
    """Instantiate ``cfg`` with built objects as keyword arguments; a value the class
    refuses is reported under its config key."""
    with config_keys(node_keys(cfg)):
        return instantiate(cfg, _partial_=True)(**objects)


@dataclasses.dataclass
class GridParts:
    """The grid world's pieces as every grid entry point builds them from the config."""

    layout: Any
    model: Any
    solver: Any
    reward_basis: Any
    cost_basis: Any
    true_reward_weights: Any  # [N * l_r] ω_rE in the reward basis' layout

    def true_reward_table(self):
        """``[N, S1]`` each expert's true reward in each cell (the reward is a state's)."""
        return self.reward_basis().weighted(self.true_reward_weights).local[:, :, 0]


def build_grid(cfg) -> GridParts:
    """Layout, the learner's model, the solver and both feature bases from ``cfg``."""
    layout = build(cfg.env.layout)
    model = build(cfg.env.model, layout=layout)
    reward_basis = build(cfg.features.reward, model=model)
    return GridParts(
        layout=layout, model=model, solver=build(cfg.solver, model=model),
        reward_basis=reward_basis, cost_basis=build(cfg.features.cost, model=model),
        true_reward_weights=reward_basis.true_weights(tuple(cfg.env.true_reward_weights)))


def grid_task_settings(cfg, skip: Sequence[str] = ()) -> dict:
    """:class:`~dicrl_torch.runs.grid.GridTask`'s settings keywords (``GRID_TASK_KEYS``)."""
    return read(cfg, GRID_TASK_KEYS, skip)


def grid_task(cfg, rank: int | None = None):
    """The grid world's task as process ``rank`` sees it (None: the process that holds
    every shard). With ``shard_files``, a learner process reads only its own file and
    does not solve for the experts (rank 0 writes their rows)."""
    from dicrl_torch.runs.grid import GridTask

    g = build_grid(cfg)
    files = cfg.get("shard_files")
    with_experts = files is None or rank in (None, 0)
    # Exact (float64) experts where it is cheap: the demonstrations do not depend on
    # the learners' solver precision.
    expert_solver = (build(cfg.solver, model=g.model, dtype=torch.float64)
                     if with_experts and g.model.n_pairs < 5_000_000 else None)
    with config_keys(GRID_TASK_KEYS):
        return GridTask(
            layout=g.layout, model=g.model, solver=g.solver, reward_basis=g.reward_basis,
            cost_basis=g.cost_basis, true_reward_weights=g.true_reward_weights,
            expert_solver=expert_solver, with_experts=with_experts,
            shard_files=None if files is None else list(files),
            read_shards=None if files is None else shard_files_read_by(cfg, rank),
            **grid_task_settings(cfg))


def torchrun_rank(cfg) -> int | None:
    """This process's learner id when torchrun started it for ``comm=distributed``."""
    if env_fit(cfg.env)[0] == "continuous" or "RANK" not in os.environ or is_simulated(cfg):
        return None
    return int(os.environ["RANK"])


def shard_files_read_by(cfg, rank: int | None) -> list[int]:
    """Which of ``shard_files`` a process reads. A learner process (``rank``) reads only its
    own, so on several machines a file need only lie on its learner's machine. The process
    that finishes the run (``rank`` None, or torchrun's rank 0) reads every file when it
    pools them for C-ICRL or the baselines."""
    n = len(cfg.shard_files)
    pools = bool(cfg.algo.run_c_icrl) or bool(
        OmegaConf.select(cfg, "baselines.run", default=None))
    if rank is None or (rank == 0 and pools):
        return list(range(n))
    return [rank] if rank < n else []


def shard_file_problems(cfg) -> list[str]:
    """``shard_files`` (of the grid world): null, or one existing ``.npz`` per learner,
    each listed once, that this process can read. Their contents are checked when loaded
    (:func:`check_shard_contents`), still before any solve."""
    files, split = cfg.get("shard_files"), cfg.get("split")
    if files is None or env_fit(cfg.env)[0] != "grid":
        return []
    if not (OmegaConf.is_list(files) and files and all(isinstance(f, str) and f for f in files)):
        return [f"shard_files={_plain(files)} is invalid: it must be null or a list of .npz "
                f"paths, one per learner; set e.g. shard_files=[a.npz,b.npz]."]
    problems = []
    if OmegaConf.is_list(split) and len(files) != len(split):
        problems.append(f"shard_files lists {len(files)} files but split={_plain(split)} has "
                        f"{len(split)} learners; give one file per learner, in learner order.")
    if len(set(files)) != len(files):
        problems.append(f"shard_files={_plain(files)} lists a file twice; each learner holds "
                        f"its own share of the demonstrations.")
    rank = torchrun_rank(cfg)
    reads = shard_files_read_by(cfg, rank)
    missing = [files[v] for v in reads if not Path(files[v]).is_file()]
    if missing:
        who = "" if rank is None else f"learner process {rank}: "
        pooled = "" if rank != 0 or len(reads) == 1 else (
            " Rank 0 reads every file because it pools them for C-ICRL and the baselines; "
            "make them reachable from its machine, or set algo.run_c_icrl=false "
            "baselines=none.")
        problems.append(f"{who}shard_files: no such file {', '.join(missing)} (relative paths "
                        f"are taken from the directory the run is started in, "
                        f"{Path.cwd()}).{pooled}")
    return problems


def check_shard_contents(cfg) -> None:
    """Read ``shard_files`` once before anything is solved: a file that does not fit the
    run fails at start-up with the library's message, not minutes later."""
    from dicrl_torch.runs.grid import load_shard_files

    if cfg.get("shard_files") is None or task_builder(cfg) is not grid_task:
        return
    model = build(cfg.env.model, layout=build(cfg.env.layout))
    load_shard_files(list(cfg.shard_files), list(cfg.split), model,
                     read=shard_files_read_by(cfg, torchrun_rank(cfg)))


def drone_dynamics(cfg):
    """The arena's :class:`DroneDynamics` from ``env.arena.dynamics`` (the defaults
    where the node is absent)."""
    from dicrl_torch.envs.drones import DroneDynamics

    node = OmegaConf.select(cfg, "env.arena.dynamics", default=None)
    return DroneDynamics() if node is None else build(node)


def drone_env_factory(cfg):
    """The SAC solver's ``env_factory`` of the arena: :class:`JointDroneEnv` with the
    config's ``env.arena`` settings (the solver adds ``constrained``)."""
    from dicrl_torch.envs.drones import JointDroneEnv

    arena = OmegaConf.to_container(cfg.env.arena)
    arena["dynamics"] = drone_dynamics(cfg)
    return functools.partial(JointDroneEnv, **arena)


def sac_task_settings(cfg, skip: Sequence[str] = ()) -> dict:
    """The keyword arguments every SAC-solved task takes (runs/continuous.py's
    ``SACTask``; ``SAC_TASK_KEYS``): the split, seed, evaluation, inner and last solves,
    η(0) and baseline.

    Raises:
        InvalidSetting: ``baselines.run`` names another row than the continuous games'
            one greedy row.
    """
    settings = read(cfg, SAC_TASK_KEYS, skip)
    if "baseline" in settings:  # the table's rows: none, or the one greedy row
        rows = settings["baseline"]
        if rows not in ([], [GREEDY_BASELINE]):
            raise InvalidSetting("baselines.run", rows, f"a list of distinct names among "
                                 f"{[GREEDY_BASELINE]} (the rows to add; [] for none)",
                                 "[M(C)E-greedy]")
        settings["baseline"] = bool(rows)
    return settings


def drone_task(cfg, rank: int | None = None):
    """The drone arena's task (imports stable-baselines3: only for the arena)."""
    from dicrl_torch.runs.drones import DroneTask, derived_seed

    reward_basis = build(cfg.features.reward)
    cost_basis = build(cfg.features.cost)
    solver = build(cfg.solver.solver, reward_basis=reward_basis, cost_basis=cost_basis,
                   seed=derived_seed(cfg.seed, 1), env_factory=drone_env_factory(cfg))
    with config_keys({**SAC_TASK_KEYS, **PLANNER_KEYS}):
        return DroneTask(solver=solver, reward_basis=reward_basis, cost_basis=cost_basis,
                         dynamics=drone_dynamics(cfg), **sac_task_settings(cfg))


def mpe_task(cfg, rank: int | None = None):
    """The constrained MPE spread's task (``env=mpe_spread``)."""
    from dicrl_torch.runs.mpe import build_mpe_task

    # ViaPointController's keyword arguments; the node's _target_ only lets config_checks
    # check its keys against the signature.
    expert = {k: v for k, v in OmegaConf.to_container(cfg.env.get("expert") or {}).items()
              if not k.startswith("_")}
    with config_keys({**SAC_TASK_KEYS, **node_keys(cfg.env.arena)}):
        return build_mpe_task(
            layout=build(cfg.env.layout), env=OmegaConf.to_container(cfg.env.arena),
            expert=expert, reward_basis=build(cfg.features.reward),
            cost_basis=build(cfg.features.cost),
            solver=instantiate(cfg.solver.solver, _partial_=True), **sac_task_settings(cfg))


def task_builder(cfg):
    """The function ``env.task._target_`` names: ``builder(cfg, rank=None) -> task``."""
    target = OmegaConf.select(cfg, "env.task._target_", default=None)
    if not isinstance(target, str):
        raise ValueError("env.task._target_ is missing: an environment's config group names "
                         "its task builder, e.g. env.task._target_=common.grid_task (a "
                         "function builder(cfg, rank=None) returning the task).")
    return get_method(target)


def build_task(cfg, rank: int | None = None):
    """The configured environment's task, as process ``rank`` sees it (None: the process
    that holds every shard); a value its task refuses is named by its config key (a game of
    your own that passes :func:`sac_task_settings` to its task too)."""
    with config_keys(SAC_TASK_KEYS if env_fit(cfg.env)[0] == "continuous"
                     else GRID_TASK_KEYS):
        return task_builder(cfg)(cfg, rank)


def run_settings(cfg) -> RunSettings:
    """The run's :class:`RunSettings` (``RUN_KEYS``), the config stored with it."""
    container = OmegaConf.to_container(cfg, resolve=True)
    with config_keys(RUN_KEYS):
        return RunSettings(experiment=cfg.name, config=container,
                           training_config=training_config(container), **read(cfg, RUN_KEYS))


def trainer_spec(cfg) -> TrainerSpec:
    """The :class:`~dicrl_torch.algos.dicrl.DICRL` settings of ``cfg.algo`` and
    ``cfg.graph``, whatever the environment and the number of learners."""
    options = read(cfg, TRAINER_KEYS)

    def schedules(n_learners: int):
        return tuple(build(cfg.graph[k], n_learners=n_learners) for k in ("inner", "outer"))

    with config_keys(TRAINER_KEYS):
        return TrainerSpec(schedules=schedules, steps=build(cfg.algo.steps),
                           inner_step=options.pop("inner_step", None), n_shards=len(cfg.split),
                           options=options)


def c_icrl_beside_learners(cfg) -> bool:
    """``algo.c_icrl_beside_learners``, when C-ICRL runs at all."""
    beside = setting_bool("algo.c_icrl_beside_learners",
                          OmegaConf.select(cfg, "algo.c_icrl_beside_learners", default=False),
                          example=False)
    return beside and cfg.algo.run_c_icrl is True


# ------------------------------------------------------------------ checking a config
def settings_problems(cfg, skip: Sequence[str] = ()) -> list[str]:
    """Build every settings object of ``cfg`` (nothing is computed: no solve, no
    demonstration, no training) and return what their constructors refuse, each under
    its config key; a constructor names the first value it refuses. The keys under
    ``skip`` (options of another environment, reported already) keep the defaults."""
    problems: list[str] = []

    def attempt(make: Callable[[], Any], where: str, keys: Mapping[str, str] | None = None
                ) -> Any:
        try:
            with config_keys(keys or {}):
                return make()
        except InvalidSetting as e:
            problems.append(str(e))
        except (ValueError, TypeError, OmegaConfBaseException) as e:
            # a rule of several values (a layout's start regions), a key the config lacks
            problems.append(f"{where}: {e}")
        return None

    attempt(lambda: run_settings(cfg), "the run's settings")
    attempt(lambda: trainer_spec(cfg), "the trainer's settings")
    attempt(lambda: c_icrl_beside_learners(cfg), "algo")
    comm_keys = {**node_keys(cfg.comm), **{  # and those of a nested node (compression)
        f"{k}.{kk}": f"comm.{k}.{kk}" for k, v in cfg.comm.items() if OmegaConf.is_dict(v)
        for kk in v}}
    attempt(lambda: get_class(cfg.comm._target_).check_settings(
        **read(cfg, node_keys(cfg.comm))), "comm", comm_keys)
    if env_fit(cfg.env)[0] == "grid":
        from dicrl_torch.runs.grid import GridTask

        layout = attempt(lambda: build(cfg.env.layout), "env.layout")
        if layout is not None:
            attempt(lambda: build(cfg.env.model, layout=layout), "env.model")
        attempt(lambda: GridTask.check_settings(**grid_task_settings(cfg, skip)),
                "the grid task's settings", GRID_TASK_KEYS)
    elif "solver" not in skip:  # the SAC settings (those of a grid solver: reported)
        from dicrl_torch.runs.continuous import SACTask

        attempt(lambda: SACTask.check_settings(**sac_task_settings(cfg, skip)),
                "the SAC task's settings", SAC_TASK_KEYS)
        planner = read(cfg, {"planner": "solver.planner"}).get("planner") or {}
        planner = {k: v for k, v in planner.items() if k in PLANNER_KEYS}  # others: unknown
        attempt(lambda: DronePlannerSettings(**planner), "solver.planner", PLANNER_KEYS)
        env_check = ENV_CHECKS.get(attempt(lambda: task_builder(cfg), "env.task"))
        if env_check is not None:
            attempt(lambda: env_check(cfg), "env", node_keys(cfg.env.arena))
    return problems


def _spread_env(cfg):
    """The MPE spread's nominal game as the config sets it (its settings' checks)."""
    from dicrl_torch.envs.mpe import ConstrainedSpread

    return ConstrainedSpread(layout=build(cfg.env.layout), constrained=False,
                             **OmegaConf.to_container(cfg.env.arena))


# The shipped games' environments, built by check_config for their checks (a game of your
# own has its own builder: its environment's values are checked when its task is built).
ENV_CHECKS: dict[Callable, Callable] = {
    drone_task: lambda cfg: drone_env_factory(cfg)(constrained=False), mpe_task: _spread_env}


def check_config(cfg) -> None:
    """Refuse a configuration before anything is computed: options of another
    environment, keys nothing reads, groups that clash (``config_checks``), shard files
    that are not there, and every value a library constructor refuses
    (:func:`settings_problems`).

    Raises:
        ConfigError: listing every problem, each naming the key, the value and the fix.
    """
    misfits = misfit_options(cfg)
    problems = [*misfits.values(), *unknown_keys(cfg, READ_KEYS, skip=frozenset(misfits)),
                *settings_problems(cfg, tuple(misfits)), *cross_group_problems(cfg, misfits),
                *shard_file_problems(cfg)]
    problems = list(dict.fromkeys(problems))  # a value two objects refuse, once
    if problems:
        raise ConfigError(f"{len(problems)} problem(s) in the configuration, nothing was "
                          f"computed:\n" + "\n".join(f"  - {p}" for p in problems))


def make_logger(cfg, out: Path):
    return instantiate(cfg.logger, **({"root": out / "tb"} if "TensorBoard" in
                                      cfg.logger._target_ else {}))


class ConfigExperiment:
    """A run as :func:`dicrl_torch.runs.launch.launch` sees it, built from ``cfg``; it
    pickles as the resolved config, so a spawned learner process rebuilds the same pieces.

    Args:
        cfg: the composed ``train`` config.
        overrides: the command line's overrides (for the resume command).
    """

    def __init__(self, cfg, overrides: tuple[str, ...] = ()) -> None:
        self.cfg, self.overrides = cfg, tuple(overrides)
        self.config_text = OmegaConf.to_yaml(cfg, resolve=True)
        self.n_learners = len(cfg.split)
        self.distributed = not is_simulated(cfg)
        self.c_icrl_beside_learners = c_icrl_beside_learners(cfg)

    def __reduce__(self):
        return _experiment_from_yaml, (self.config_text, self.overrides)

    def task(self, rank: int | None = None):
        return build_task(self.cfg, rank)

    @functools.cache  # noqa: B019 - one per run; its training config hashes shard files
    def settings(self) -> RunSettings:
        return run_settings(self.cfg)

    @functools.cache  # noqa: B019 - one per run
    def trainer(self) -> TrainerSpec:
        return trainer_spec(self.cfg)

    def logger(self, out: Path):
        return make_logger(self.cfg, out)

    def communicator(self, **objects):
        return build(self.cfg.comm, **objects)

    def resume_command(self, out: Path) -> str:
        keep = [o for o in self.overrides if not o.startswith(("resume=", "hydra.run.dir="))]
        script = (sys.argv[0] if sys.argv[0].endswith("train.py")
                  else str(Path(__file__).with_name("train.py")))
        return shlex.join([sys.executable, script, *keep, "resume=true",
                           f"hydra.run.dir={out}"])


def _experiment_from_yaml(config_text: str, overrides: tuple[str, ...]) -> ConfigExperiment:
    return ConfigExperiment(OmegaConf.create(config_text), overrides)


def _plain(value):
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value
