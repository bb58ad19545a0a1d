"""What the entry points build from a Hydra config: the task of the configured
environment, the run's settings, the trainer's settings and the logger. The only code,
with ``config_checks``, that reads a config; everything is handed to the library
(:mod:`dicrl_torch.runs`) as built objects (docs/design.md §2).

Each environment's config group names its task builder, ``env.task._target_``: a function
``builder(cfg, rank=None)`` returning the run's task (``grid_task``, ``drone_task`` and
``mpe_task`` below for the shipped games). A game of your own registers itself the same
way, from its own config group and module, without a change here."""

from __future__ import annotations

import dataclasses
import functools
import shlex
import sys
from pathlib import Path
from typing import Any

import torch
from config_checks import is_simulated, shard_files_read_by, torchrun_rank
from hydra.utils import get_method, instantiate
from omegaconf import OmegaConf

from dicrl_torch.runs.checkpoints import training_config
from dicrl_torch.runs.runner import RunSettings, TrainerSpec


def build(cfg, **objects):
    """Instantiate ``cfg`` with built objects as keyword arguments."""
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
    layout = instantiate(cfg.env.layout)
    model = build(cfg.env.model, layout=layout)
    reward_basis = build(cfg.features.reward, model=model)
    return GridParts(
        layout=layout, model=model, solver=build(cfg.solver, model=model),
        reward_basis=reward_basis, cost_basis=build(cfg.features.cost, model=model),
        true_reward_weights=reward_basis.true_weights(tuple(cfg.env.true_reward_weights)))


def grid_task(cfg, rank: int | None = None):
    """The grid world's task as process ``rank`` sees it (None: the process that holds
    every shard). With ``shard_files``, a learner process reads only its own file and
    does not solve for the experts (rank 0 writes their rows)."""
    from dicrl_torch.runs.grid import GridTask

    split = list(cfg.split)
    if sum(split) != cfg.n_demonstrations:
        raise ValueError(f"split {split} sums to {sum(split)}, not n_demonstrations="
                         f"{cfg.n_demonstrations}; make them agree.")
    g = build_grid(cfg)
    files = cfg.get("shard_files")
    with_experts = files is None or rank in (None, 0)
    # Exact (float64) experts where it is cheap: the demonstrations do not depend on
    # the learners' solver precision.
    expert_solver = (build(cfg.solver, model=g.model, dtype=torch.float64)
                     if with_experts and g.model.n_pairs < 5_000_000 else None)
    a, b = cfg.algo, cfg.baselines
    return GridTask(
        layout=g.layout, model=g.model, solver=g.solver, reward_basis=g.reward_basis,
        cost_basis=g.cost_basis, true_reward_weights=g.true_reward_weights,
        expert_solver=expert_solver, expert_temperature=cfg.expert_temperature,
        split=split, seed=cfg.seed, eval_episodes=cfg.eval_episodes,
        shard_files=None if files is None else list(files),
        read_shards=None if files is None else shard_files_read_by(cfg, rank),
        with_experts=with_experts, constraint_rule=a.constraint_rule,
        certificate_temperature=a.certificate.temperature,
        certificate_min_probability=a.certificate.min_probability,
        threshold=a.threshold, prune_min_gain=a.prune_min_gain,
        baselines=list(b.run), baseline_max_constraints=b.max_constraints,
        baseline_epsilon=None if b.epsilon is None else float(b.epsilon))


def check_shard_contents(cfg) -> None:
    """Read ``shard_files`` once before anything is solved: a file that does not fit the
    run fails at start-up with the library's message, not minutes later."""
    from dicrl_torch.runs.grid import load_shard_files

    if cfg.get("shard_files") is None or task_builder(cfg) is not grid_task:
        return
    model = build(cfg.env.model, layout=instantiate(cfg.env.layout))
    load_shard_files(list(cfg.shard_files), list(cfg.split), model,
                     read=shard_files_read_by(cfg, torchrun_rank(cfg)))


def drone_dynamics(cfg):
    """The arena's :class:`DroneDynamics` from ``env.arena.dynamics`` (the defaults
    where the node is absent)."""
    from dicrl_torch.envs.drones import DroneDynamics

    node = OmegaConf.select(cfg, "env.arena.dynamics", default=None)
    return DroneDynamics() if node is None else instantiate(node)


def drone_env_factory(cfg):
    """The SAC solver's ``env_factory`` of the arena: :class:`JointDroneEnv` with the
    config's ``env.arena`` settings (the solver adds ``constrained``)."""
    from dicrl_torch.envs.drones import JointDroneEnv

    arena = OmegaConf.to_container(cfg.env.arena)
    arena["dynamics"] = drone_dynamics(cfg)
    return functools.partial(JointDroneEnv, **arena)


def sac_task_settings(cfg) -> dict:
    """The keyword arguments every SAC-solved task takes (runs/continuous.py's
    ``SACTask``): the split, seed, evaluation, inner and last solves, η(0) and baseline."""
    s, a, b = cfg.solver, cfg.algo, cfg.baselines
    return dict(
        split=list(cfg.split), seed=cfg.seed, eval_episodes=cfg.eval_episodes,
        eval_action=s.eval_action, timesteps=s.timesteps, n_eval_episodes=s.n_eval_episodes,
        warmup_timesteps=s.warmup_timesteps, warmup_restarts=s.get("warmup_restarts", 1),
        warmup_checks=s.get("warmup_checks", 1), init_reward_weights=a.init_reward_weights,
        init_multiplier=a.init_multiplier, init_cost_weights=a.init_cost_weights,
        final_timesteps=s.final_timesteps, final_checks=s.final_checks,
        final_restarts=s.final_restarts, final_score=s.final_score,
        final_margin=s.get("final_margin", 0.0), eval_policy=s.get("eval_policy", "sac"),
        planner=OmegaConf.to_container(s.planner) if s.get("planner") else None,
        threshold=a.threshold,
        baseline=bool(b.run), baseline_penalty=b.get("penalty", 10.0),
        baseline_timesteps=b.get("timesteps", 3000),
        baseline_epsilon=None if b.epsilon is None else float(b.epsilon),
        baseline_max_constraints=b.max_constraints)


def drone_task(cfg, rank: int | None = None):
    """The drone arena's task (imports stable-baselines3: only for the arena)."""
    from dicrl_torch.runs.drones import DroneTask, derived_seed

    reward_basis = instantiate(cfg.features.reward)
    cost_basis = instantiate(cfg.features.cost)
    solver = build(cfg.solver.solver, reward_basis=reward_basis, cost_basis=cost_basis,
                   seed=derived_seed(cfg.seed, 1), env_factory=drone_env_factory(cfg))
    return DroneTask(solver=solver, reward_basis=reward_basis, cost_basis=cost_basis,
                     dynamics=drone_dynamics(cfg), **sac_task_settings(cfg))


def mpe_task(cfg, rank: int | None = None):
    """The constrained MPE spread's task (``env=mpe_spread``)."""
    from dicrl_torch.runs.mpe import build_mpe_task

    # ViaPointController's keyword arguments; the node's _target_ only lets config_checks
    # check its keys against the signature.
    expert = {k: v for k, v in OmegaConf.to_container(cfg.env.get("expert") or {}).items()
              if not k.startswith("_")}
    return build_mpe_task(
        layout=instantiate(cfg.env.layout), env=OmegaConf.to_container(cfg.env.arena),
        expert=expert,
        reward_basis=instantiate(cfg.features.reward),
        cost_basis=instantiate(cfg.features.cost),
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
    that holds every shard)."""
    return task_builder(cfg)(cfg, rank)


def run_settings(cfg) -> RunSettings:
    container = OmegaConf.to_container(cfg, resolve=True)
    a = cfg.algo
    return RunSettings(experiment=cfg.name, config=container,
                       training_config=training_config(container),
                       outer_iterations=a.outer_iterations, eval_every=cfg.eval_every,
                       checkpoint_every=cfg.checkpoint_every, resume=cfg.resume,
                       run_d_icrl=a.run_d_icrl, run_c_icrl=a.run_c_icrl)


def trainer_spec(cfg) -> TrainerSpec:
    """The :class:`~dicrl_torch.algos.dicrl.DICRL` settings of ``cfg.algo`` and
    ``cfg.graph``, whatever the environment and the number of learners."""
    a = cfg.algo

    def schedules(n_learners: int):
        return tuple(build(cfg.graph[k], n_learners=n_learners) for k in ("inner", "outer"))

    return TrainerSpec(
        schedules=schedules, steps=instantiate(a.steps), inner_step=a.inner_step,
        n_shards=len(cfg.split),
        options=dict(inner_steps=a.inner_steps, lsca_curvature=a.lsca_curvature,
                     prune_accrued=a.prune_accrued, init_cost_weights=a.init_cost_weights,
                     init_reward_weights=a.init_reward_weights,
                     init_multiplier=a.init_multiplier, inner_method=a.inner_method))


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
        self.c_icrl_beside_learners = bool(cfg.algo.run_c_icrl
                                           and cfg.algo.c_icrl_beside_learners)

    def __reduce__(self):
        return _experiment_from_yaml, (self.config_text, self.overrides)

    def task(self, rank: int | None = None):
        return build_task(self.cfg, rank)

    def settings(self) -> RunSettings:
        return run_settings(self.cfg)

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
