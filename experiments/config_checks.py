"""The entry points' config checks: every option fitting the environment (a basis, solver
or baseline of the grid world on the drone arena, or the reverse, is refused: the classes
say which kind of environment they serve, ``env_kind``), every key known, every value in
range, before any computation (a bad value would otherwise surface minutes later, deep in
the solver).

``check_config`` collects every problem and raises one :class:`ConfigError` naming, for
each, the key, the value and the fix. ``train.py`` exits with code 2 on it.
"""

from __future__ import annotations

import difflib
import inspect
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.utils import get_class, get_object
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.comm.distributed import DistributedCommunicator
from dicrl_torch.solvers.planning import PLAN_SIZES, check_plan_sizes


class ConfigError(ValueError):
    """The configuration has an unknown key or a value out of range."""


def _ge(lo):
    return lambda x: x >= lo


def _in_open(lo, hi):
    return lambda x: lo < x < hi


# key, type, condition, what it must be (and why), an example value. Checked before any
# computation: a bad value would otherwise surface minutes later, deep in the solver.
VALUE_RULES: list[tuple[str, type, Callable[[Any], bool] | None, str, str]] = [
    ("seed", int, _ge(0), "an int >= 0 (it seeds the demonstrations and evaluation)", "0"),
    ("n_demonstrations", int, _ge(1), "an int >= 1", "100"),
    ("eval_episodes", int, _ge(1), "an int >= 1 (evaluation episodes per table row)", "200"),
    ("eval_every", int, _ge(1),
     "an int >= 1 (outer iterations between the CR/CVR evaluations of the curves)", "5"),
    ("expert_temperature", float, _ge(0.0), "a number >= 0 (0: optimal experts)", "0.0"),
    ("checkpoint_every", int, _ge(1), "an int >= 1 (outer iterations between checkpoints)",
     "1"),
    ("resume", bool, None, "true or false", "true"),
    ("env.layout.n_experts", int, lambda x: x in (1, 2, 3),
     "1, 2 or 3 (the experts of the layout's table, taken in order)", "2"),
    ("env.model.horizon", int, _ge(1), "an int >= 1 (the horizon T, decisions per episode)",
     "40"),
    # γ = 1 is well defined over a finite horizon, and TabularGridModel accepts it.
    ("env.model.gamma", float, lambda x: 0 < x <= 1, "a number in (0, 1] (the discount γ)",
     "0.99"),
    ("env.model.p_success", float, lambda x: 0 < x <= 1,
     "a number in (0, 1] (the probability that a move succeeds)", "0.8"),
    ("algo.outer_iterations", int, _ge(1), "an int >= 1", "20"),
    ("algo.inner_steps", int, _ge(2), "an int >= 2 (K: Algorithm 2 takes K - 1 steps)", "6"),
    ("algo.inner_step", float, _in_open(0.0, math.inf),
     "a positive number (the constant step of inner_method=gradient_tracking)", "0.005"),
    ("algo.steps.alpha_bar", float, _in_open(0.0, math.inf),
     "a positive number (α(k) = ᾱ/(k+1))", "0.02"),
    ("algo.steps.multiplier_scale", float, _in_open(0.0, math.inf),
     "a positive number (the λ coordinate's step is scaled by it; 1: the paper's)", "1.0"),
    ("algo.steps.beta_bar", float, _in_open(0.0, 1.0),
     "a number in (0, 1) so that β(n) ∈ (0, 1) (Theorem 1)", "0.5"),
    ("algo.steps.beta_power", float, lambda x: 0.5 < x <= 1,
     "a number in (1/2, 1] so that Σβ = ∞ and Σβ² < ∞ (Theorem 1)", "0.6"),
    ("algo.lsca_curvature", float, _in_open(0.0, math.inf),
     "a positive number (ρ of the LSCA step)", "300.0"),
    ("algo.prune_accrued", bool, None, "true or false", "true"),
    ("algo.init_cost_weights", float, lambda x: 0 <= x <= 1,
     "a number in [0, 1] (ω_c(0) lives in [0, 1]^d)", "0.0"),
    ("algo.init_reward_weights", float, None, "a finite number", "0.0"),
    ("algo.init_multiplier", float, None, "a finite number (λ(0))", "-1.0"),
    ("algo.constraint_rule", str, lambda x: x in ("certificate", "threshold"),
     "'certificate' (the grid's certified set) or 'threshold' (the paper's ω_c >= "
     "threshold)", "certificate"),
    ("algo.certificate.temperature", float, _ge(0.0),
     "a number >= 0 (the certificate's experts; 0: optimal)", "0.0"),
    ("algo.certificate.min_probability", float, lambda x: 0 < x <= 1,
     "a number in (0, 1] (per-trajectory probability that certifies a feature)", "0.001"),
    ("algo.threshold", float, _in_open(0.0, 1.0),
     "a number in (0, 1) (ω_c,j >= threshold marks a learned constraint)", "0.5"),
    ("algo.prune_min_gain", float | None, _ge(0.0),
     "null (keep every constraint) or a number >= 0 (nats per trajectory)", "0.001"),
    ("algo.run_c_icrl", bool, None, "true or false", "true"),
    ("algo.c_icrl_beside_learners", bool, None, "true or false", "false"),
    ("algo.run_d_icrl", bool, None, "true or false", "true"),
    ("algo.inner_method", str, lambda x: x in ("paper", "gradient_tracking"),
     "'paper' or 'gradient_tracking'", "paper"),
    ("comm.timeout_s", float, _in_open(0.0, math.inf),
     "a positive number of seconds", "60"),
    ("baselines.epsilon", float | None, _ge(0.0),
     "null (BIC: ln(m)/(2m)) or a number >= 0 (nats per trajectory)", "0.023"),
    ("baselines.max_constraints", int | None, _ge(0),
     "null (no limit) or an int >= 0", "20"),
]

# Rules of the drone arena only (env=drones), and the grid world's keys it has not.
DRONE_RULES: list[tuple[str, type, Callable[[Any], bool] | None, str, str]] = [
    ("solver.timesteps", int, _ge(1), "an int >= 1 (SAC env steps per solve)", "2000"),
    ("solver.eval_action", str, lambda x: x in ("mean", "sampled"),
     "'mean' or 'sampled' (the actions of the table's SR and CVR rollouts)", "mean"),
    ("solver.final_timesteps", int, _ge(1),
     "an int >= 1 (SAC steps of the last solve, on the learned (η̄, ω_c))", "2000"),
    ("solver.final_checks", int, _ge(1),
     "an int >= 1 (scored chunks of the last solve; 1: no selection)", "1"),
    ("solver.final_restarts", int, _ge(1),
     "an int >= 1 (independent continuations of the last solve; 1: the solver's own)", "1"),
    ("solver.final_score", str, lambda x: x in ("penalised_return", "learned_success"),
     "'penalised_return' or 'learned_success' (how the last solve's chunks are ranked)",
     "learned_success"),
    ("solver.eval_policy", str, lambda x: x in ("sac", "plan"),
     "'sac' or 'plan' (the last solve's SAC policy, or planning on the learned game)", "sac"),
    ("solver.planner.horizon", int, _ge(1), "an int >= 1 (steps planned)", "30"),
    ("solver.planner.knot", int, _ge(1), "an int >= 1 dividing the horizon", "5"),
    ("solver.planner.replan", int, _ge(1),
     "an int >= 1 dividing the knot (steps between re-plans)", "5"),
    ("solver.planner.samples", int, _ge(1), "an int >= 1 (plans per round)", "256"),
    ("solver.planner.iterations", int, _ge(1), "an int >= 1 (rounds per step)", "4"),
    ("solver.planner.elites", int, _ge(1), "an int >= 1, at most samples", "25"),
    ("solver.planner.margin", float, lambda x: 0.0 <= x < 0.5,
     "a float in [0, 0.5) (metres the learned cells are grown by)", "0.1"),
    ("solver.planner.grid_step", float, lambda x: 0.0 < x <= 1.0,
     "a float in (0, 1] (metres between the grid value's centres)", "0.25"),
    ("solver.final_margin", float, lambda x: 0.0 <= x < 0.5,
     "a float in [0, 0.5) (metres the last solve's penalty cells are grown by; 0: none)",
     "0.2"),
    ("solver.warmup_timesteps", int, _ge(0), "an int >= 0 (SAC pre-training steps)",
     "30000"),
    ("solver.warmup_restarts", int, _ge(1),
     "an int >= 1 (warm-up lineages; the best-scored chunk is kept)", "3"),
    ("solver.warmup_checks", int, _ge(1), "an int >= 1 (scored chunks per warm-up lineage)",
     "3"),
    ("solver.n_eval_episodes", int, _ge(1), "an int >= 1 (rollouts per estimate)", "10"),
    ("env.arena.max_steps", int, _ge(1), "an int >= 1 (episode limit in steps)", "300"),
    ("baselines.penalty", float, _in_open(0.0, math.inf),
     "a positive number (reward units per step in a constrained cell)", "10.0"),
    ("baselines.timesteps", int, _ge(1), "an int >= 1 (SAC steps per greedy trial)", "3000"),
]
GRID_ONLY = ("env.model.", "env.layout.")
DRONE_BASELINE_KEYS = ("baselines.penalty", "baselines.timesteps")  # when one runs

# The baselines' table rows (names as in the paper) and the greedy's demonstrator model.
BASELINES = {"ME-greedy": "me", "MCE-greedy": "mce"}
DRONE_BASELINES = ("M(C)E-greedy",)  # the arena is (nearly) deterministic: ME = MCE

# Keys of nodes without a _target_ (those with one are checked against its signature).
KNOWN_KEYS = {
    "": {"env", "features", "solver", "algo", "graph", "comm", "logger", "name", "seed",
         "n_demonstrations", "split", "eval_episodes", "eval_every", "expert_temperature",
         "checkpoint_every", "resume", "baselines", "shard_files"},
    # "env" is the game's own (its nodes with a _target_ are checked against signatures)
    # the drones' solver node (the grid's has a _target_, checked against its signature)
    "solver": {"timesteps", "warmup_timesteps", "warmup_restarts", "warmup_checks",
               "final_timesteps", "final_checks",
               "final_restarts", "final_score", "final_margin", "n_eval_episodes",
               "eval_action", "eval_policy", "planner", "solver"},
    "solver.planner": {"horizon", "knot", "replan", "samples", "iterations", "elites",
                       "margin", "grid_step"},
    "features": {"reward", "cost"},
    "graph": {"inner", "outer"},
    "algo": {"outer_iterations", "inner_steps", "inner_method", "inner_step", "steps",
             "lsca_curvature", "prune_accrued", "init_cost_weights", "init_reward_weights",
             "init_multiplier", "constraint_rule", "certificate", "threshold",
             "prune_min_gain", "run_c_icrl", "run_d_icrl", "c_icrl_beside_learners"},
    "algo.certificate": {"temperature", "min_probability"},
    "baselines": {"run", "epsilon", "max_constraints", "penalty", "timesteps"},
}
_HYDRA_KEYS = {"_target_", "_partial_", "_args_", "_recursive_", "_convert_"}


def _type_ok(value, kind) -> bool:
    if value is None:
        return kind == float | None or kind == int | None
    kind = {float | None: float, int | None: int}.get(kind, kind)
    if kind is bool or kind is str:
        return isinstance(value, kind)
    if isinstance(value, bool):  # bool is an int to Python, never a number here
        return False
    if kind is int:
        return isinstance(value, int)
    return isinstance(value, int | float) and math.isfinite(value)


def _unknown_keys(node, path: str, problems: list[str], skip: frozenset[str] = frozenset()
                  ) -> None:
    """Keys of ``node`` (and below) that nothing reads: a misspelt or stray override would
    otherwise be ignored (``+key=...`` gets past Hydra's struct mode). Nodes at the paths
    ``skip`` (options that do not fit the environment) are not looked into."""
    if not isinstance(node, DictConfig) or path in skip:
        return
    keys = set(node.keys())
    known, reader = KNOWN_KEYS.get(path), f"'{path}'" if path else "the top level"
    if "_target_" in node:
        target = node["_target_"]
        try:
            params = inspect.signature(get_object(target)).parameters
        except Exception as e:  # noqa: BLE001 - any import failure is a config error
            problems.append(f"{path}._target_={target!r} cannot be imported ({e}); fix the "
                            f"class path.")
            return
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            known = None
        else:
            known, reader = set(params) | _HYDRA_KEYS, target
    if known is not None:
        for key in sorted(keys - known):
            full = f"{path}.{key}" if path else key
            close = difflib.get_close_matches(key, sorted(known - _HYDRA_KEYS), n=1)
            hint = f"did you mean '{close[0]}'? Remove" if close else "remove"
            problems.append(f"unknown key '{full}': {reader} takes no option '{key}'; "
                            f"{hint} it or fix its spelling.")
    for key in keys:
        _unknown_keys(node[key], f"{path}.{key}" if path else key, problems, skip)


def _check_layout(cfg, problems: list[str]) -> None:
    """The grid layout's own checks (start sets off obstacles and disjoint, cells inside the
    grid, ...) as config problems: building it takes microseconds."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        instantiate(cfg.env.layout)
    except (ValueError, TypeError, InstantiationException) as e:
        cause = e.__cause__ if isinstance(e, InstantiationException) and e.__cause__ else e
        problems.append(f"env.layout: {cause}")


def _check_shard_files(cfg, drones: bool, problems: list[str]) -> None:
    """``shard_files``: null, or one existing ``.npz`` per learner, each listed once. Their
    contents are checked when loaded (:func:`load_shard_files`), still before any solve."""
    files = cfg.get("shard_files")
    if files is None:
        return
    if drones:
        problems.append("shard_files is for the grid world; the arena's demonstrations come "
                        "from its planner. Set shard_files=null.")
        return
    if not (OmegaConf.is_list(files) and len(files) >= 1
            and all(isinstance(f, str) and f for f in files)):
        problems.append(f"shard_files={_plain(files)} is invalid: it must be null or a list of "
                        f".npz paths, one per learner; set e.g. shard_files=[a.npz,b.npz].")
        return
    split = cfg.get("split")
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


def torchrun_rank(cfg) -> int | None:
    """This process's learner id when torchrun started it for ``comm=distributed``."""
    if is_drone_run(cfg) or "RANK" not in os.environ:
        return None
    try:
        simulated = is_simulated(cfg)
    except Exception:  # noqa: BLE001 - a bad comm target is reported by the key checks
        return None
    return None if simulated else int(os.environ["RANK"])


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


def is_drone_run(cfg) -> bool:
    """The drone arena (``env=drones``) rather than the grid world."""
    return OmegaConf.select(cfg, "env.arena", default=None) is not None


def is_mpe_run(cfg) -> bool:
    """The constrained MPE spread (``env=mpe_spread``): a continuous game like the arena,
    told apart by its layout."""
    return is_drone_run(cfg) and env_game(cfg.env) == "mpe_spread"


def is_simulated(cfg) -> bool:
    return not issubclass(get_class(cfg.comm._target_), DistributedCommunicator)


# ---------------------------------------------------------------- options of the environment
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
# The environment kinds (the ``env_kind`` of the classes) and how the messages name them.
KIND_WORDS = {"grid": "the grid world",
              "continuous": "the continuous games (the drone arena, the MPE spread)"}
# The config groups whose options serve one kind of environment, and what an option is.
# Bases built for one continuous game (their class's ``game``) and how messages name it.
GAME_WORDS = {"drones": "the drone arena", "mpe_spread": "the MPE spread"}
SPREAD_LAYOUT = "dicrl_torch.envs.mpe.SpreadLayout"
KIND_GROUPS = {"features/reward": "a basis", "features/cost": "a basis",
               "solver": "a solver", "baselines": "baselines"}


def env_kind(env) -> str:
    """The kind of the environment node ``env`` (``cfg.env``, or an env option):
    ``"continuous"`` (a game with ``arena`` settings: the drones, the MPE spread) or
    ``"grid"``."""
    return "continuous" if OmegaConf.select(env, "arena", default=None) is not None else "grid"


def class_env_kind(cls: type) -> str | None:
    """The kind of environment ``cls`` serves: its ``env_kind`` attribute, which the
    feature bases (:class:`dicrl_torch.features.base.Basis`) and the solvers declare.
    None: a class that declares none, not checked."""
    return getattr(cls, "env_kind", None)


def _target_of(node) -> str | None:
    """The class path of an option's node: its ``_target_`` (the drones' solver node: its
    ``solver._target_``)."""
    for key in ("_target_", "solver._target_"):
        target = OmegaConf.select(node, key, default=None) if OmegaConf.is_dict(node) else None
        if isinstance(target, str):
            return target
    return None


def _identity(group: str, node) -> Any:
    """What tells an option of ``group`` apart: its baseline rows or its class path."""
    if group == "baselines":
        run = OmegaConf.select(node, "run", default=None) if OmegaConf.is_dict(node) else None
        return tuple(run) if OmegaConf.is_list(run) else None
    return _target_of(node)


def option_kind(group: str, node) -> str | None:
    """The kind of environment the option ``node`` of ``group`` serves (None: any, or
    unknown): that of its class, or for baselines that of its rows."""
    if group == "baselines":
        run = _identity(group, node)
        for kind, names in (("grid", BASELINES), ("continuous", DRONE_BASELINES)):
            if run and all(isinstance(x, str) and x in names for x in run):
                return kind
        return None
    target = _target_of(node)
    if target is None:
        return None
    try:
        return class_env_kind(get_class(target))
    except Exception:  # noqa: BLE001 - an import failure is reported by the key checks
        return None


def _options(group: str) -> dict[str, DictConfig]:
    return {p.stem: OmegaConf.load(p) for p in sorted((CONFIGS / group).glob("*.yaml"))}


def _default_options() -> set[tuple[str, str]]:
    """(group, option) pairs that train.yaml or an experiment chooses: the suggested fixes
    name them first."""
    chosen = set()
    for path in [CONFIGS / "train.yaml", *sorted((CONFIGS / "experiment").glob("*.yaml"))]:
        for entry in OmegaConf.load(path).get("defaults", []):
            if OmegaConf.is_dict(entry):
                for key, option in entry.items():
                    chosen.add((str(key).removeprefix("override").strip().lstrip("/"),
                                str(option)))
    return chosen


def _targets(node, path: str = "") -> dict[str, str]:
    if not OmegaConf.is_dict(node):
        return {}
    found = {path: node["_target_"]} if "_target_" in node else {}
    for key in node:
        if key != "_target_":
            found.update(_targets(node[key], f"{path}.{key}"))
    return found


def _env_name(cfg, kind: str) -> str:
    """``env=<option>`` of the configured environment (its option found by its classes),
    or the options of its kind."""
    envs = {o: n for o, n in _options("env").items() if env_kind(n) == kind}
    same = [o for o, n in envs.items() if _targets(n) == _targets(cfg.env)]
    return f"env={same[0]}" if len(same) == 1 else "env=" + " or env=".join(envs)


def env_game(env) -> str | None:
    """The game of a continuous environment node (``"drones"`` or ``"mpe_spread"``), for
    the bases built for one game only (their class's ``game``); None for the grid world."""
    if OmegaConf.select(env, "layout._target_", default=None) == SPREAD_LAYOUT:
        return "mpe_spread"
    return "drones" if env_kind(env) == "continuous" else None


def option_game(group: str, node) -> str | None:
    """The one game the option ``node`` of ``group`` is built for (its class's ``game``),
    or None: any game of its kind."""
    target = _target_of(node) if group != "baselines" else None
    if target is None:
        return None
    try:
        return getattr(get_class(target), "game", None)
    except Exception:  # noqa: BLE001 - an import failure is reported by the key checks
        return None


def misfit_options(cfg) -> dict[str, str]:
    """The options of ``KIND_GROUPS`` that serve another kind of environment than the
    configured one, or another game of its kind, each with its problem: the config path
    of the option's node -> what it is, whose, and the options of the group that fit."""
    kind, game, problems = env_kind(cfg.env), env_game(cfg.env), {}
    defaults = None
    for group, noun in KIND_GROUPS.items():
        path = group.replace("/", ".")
        node = OmegaConf.select(cfg, path, default=None)
        theirs = option_kind(group, node)
        if theirs is None:
            continue
        their_game = option_game(group, node) if theirs == kind else None
        if theirs == kind and their_game in (None, game):
            continue
        options = _options(group)
        defaults = _default_options() if defaults is None else defaults
        name = next((f"{group}={o}" for o, n in options.items()
                     if _identity(group, n) == _identity(group, node)), None)
        if name is None:
            if group == "baselines":  # rows of its own: the rows' check names the fix
                continue
            name = f"{path}._target_={_target_of(node)}"
        fit = sorted((o for o, n in options.items() if option_kind(group, n) == kind
                      and option_game(group, n) in (None, game)),
                     key=lambda o: ((group, o) not in defaults, o))
        fit += [o for o, n in options.items() if option_kind(group, n) is None]
        fix = (f"use {group}={fit[0]}" + (f" (or {', '.join(fit[1:])})" if fit[1:] else "")
               if fit else f"no {group} option serves it; add one")
        verb = "are" if group == "baselines" else "is"
        whose = (KIND_WORDS.get(theirs, theirs) if their_game is None
                 else f"{GAME_WORDS.get(their_game, their_game)} only")
        problems[path] = (f"{name} {verb} {noun} of {whose}; with {_env_name(cfg, kind)} "
                          f"{fix}.")
    return problems


def _check_launch(cfg, problems: list[str]) -> None:
    """How the processes were started must fit ``comm`` and ``split``: torchrun starts one
    process per learner, each running only its own (``comm=distributed``)."""
    world = os.environ.get("WORLD_SIZE")
    if world is None or not world.isdigit():
        return
    try:
        simulated = is_simulated(cfg)
    except Exception:  # noqa: BLE001 - a bad comm target is reported by the key checks
        return
    split = cfg.get("split")
    if simulated and int(world) > 1:
        problems.append(f"Started as one of WORLD_SIZE={world} processes (torchrun?) with "
                        f"comm={cfg.comm._target_}, which runs every learner in each "
                        f"process; add comm=distributed.")
    elif (not simulated and "RANK" in os.environ and OmegaConf.is_list(split)
          and int(world) != len(split)):
        problems.append(f"torchrun started WORLD_SIZE={world} processes but "
                        f"split={_plain(split)} has {len(split)} learners (one process per "
                        f"learner); run torchrun with --nproc_per_node {len(split)} (times "
                        f"the nodes), or change split.")


def check_config(cfg: DictConfig) -> None:
    """Refuse options of another environment, unknown keys and out-of-range values
    before anything is computed.

    Raises:
        ConfigError: listing every problem, each naming the key, the value and the fix.
    """
    # An option of another environment first: its keys are not checked (they would be
    # checked against the wrong class or rules); those of the fitting option will be.
    misfits = misfit_options(cfg)
    problems: list[str] = list(misfits.values())
    _unknown_keys(cfg, "", problems, skip=frozenset(misfits))
    drones = is_drone_run(cfg)
    run = OmegaConf.select(cfg, "baselines.run", default=None)
    rules = VALUE_RULES + DRONE_RULES if drones else VALUE_RULES
    for key, kind, ok, must, example in rules:
        if (drones and key.startswith(GRID_ONLY)) or key.startswith(
                tuple(f"{path}." for path in misfits)):
            continue
        if OmegaConf.select(cfg, key, default="__missing__") == "__missing__":
            # only the distributed backend has a timeout; only a drone baseline that runs
            # a penalty and timesteps
            if key != "comm.timeout_s" and not (key in DRONE_BASELINE_KEYS and not run):
                problems.append(f"'{key}' is missing; set it, e.g. {key}={example}.")
            continue
        value = OmegaConf.select(cfg, key)
        if not _type_ok(value, kind) or (ok is not None and value is not None and not ok(value)):
            problems.append(f"{key}={value!r} is invalid: it must be {must}; set e.g. "
                            f"{key}={example}.")
    split = cfg.get("split")
    if not (OmegaConf.is_list(split) and len(split) >= 1
            and all(_type_ok(x, int) and x >= 1 for x in split)):
        problems.append(f"split={_plain(split)} is invalid: it must be a non-empty list of "
                        f"ints >= 1, one per learner (a learner without trajectories has "
                        f"nothing to learn from); set e.g. split=[10,20,30,40].")
    elif _type_ok(cfg.get("n_demonstrations"), int) and sum(split) != cfg.n_demonstrations:
        problems.append(f"split={_plain(split)} sums to {sum(split)}, not n_demonstrations="
                        f"{cfg.n_demonstrations}; make them agree (e.g. n_demonstrations="
                        f"{sum(split)}).")
    _check_shard_files(cfg, drones, problems)
    if not drones and "env" not in misfits and not problems:
        _check_layout(cfg, problems)
    names, example = (list(DRONE_BASELINES), "baselines=greedy_drones") if drones else \
        (list(BASELINES), "baselines=greedy")
    if "baselines" not in misfits and not (
            OmegaConf.is_list(run) and all(isinstance(x, str) and x in names for x in run)
            and len(set(run)) == len(run)):
        problems.append(f"baselines.run={_plain(run)} is invalid: it must be a list of "
                        f"distinct names among {names} (the rows to add; [] for "
                        f"none); set e.g. {example} or baselines=none.")
    if drones and OmegaConf.select(cfg, "algo.constraint_rule", default=None) == "certificate":
        problems.append("algo.constraint_rule=certificate needs the grid world's exact "
                        "solver (one solve per unseen feature); the drone arena keeps the "
                        "paper's rule: set algo.constraint_rule=threshold.")
    checks = OmegaConf.select(cfg, "solver.final_checks", default=None)
    final = OmegaConf.select(cfg, "solver.final_timesteps", default=None)
    if drones and _type_ok(checks, int) and _type_ok(final, int) and 1 <= final < checks:
        problems.append(f"solver.final_checks={checks} exceeds solver.final_timesteps={final}: "
                        f"each scored chunk needs at least one step; lower final_checks.")
    plan = {k: OmegaConf.select(cfg, f"solver.planner.{k}", default=None)
            for k in PLAN_SIZES}
    if drones and all(_type_ok(v, int) and v >= 1 for v in plan.values()):
        try:  # the planner's own rule, before training rather than at the evaluation
            check_plan_sizes(**plan)
        except ValueError as e:
            problems.append(f"solver.planner: {e}")
    if OmegaConf.select(cfg, "algo.run_d_icrl", default=True) is False:
        if drones and OmegaConf.select(cfg, "baselines.run", default=None):
            problems.append("algo.run_d_icrl=false leaves the drone arena's greedy baseline "
                            "without its reward (D-ICRL's learned one, as in the paper); set "
                            "algo.run_d_icrl=true or baselines=none.")
        elif not is_simulated(cfg):
            problems.append("algo.run_d_icrl=false trains no learner processes, so "
                            "comm=distributed has nothing to run; use comm=simulated.")
    _check_launch(cfg, problems)
    if problems:
        raise ConfigError(f"{len(problems)} problem(s) in the configuration, nothing was "
                          f"computed:\n" + "\n".join(f"  - {p}" for p in problems))


def _plain(value):
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


