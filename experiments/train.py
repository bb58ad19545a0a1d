"""Train D-ICRL (and C-ICRL) on the grid world and report the paper's table.

    python experiments/train.py experiment=quick [seed=1] [graph=ring] [features/cost=per_expert]
    python experiments/train.py experiment=table1      # Table 1: + ME-greedy, MCE-greedy rows
    python experiments/train.py comm=distributed       # one process per learner (spawned here)
    torchrun --standalone --nproc_per_node N_L experiments/train.py comm=distributed

Writes into the Hydra run directory: ``results.json`` (DESIGN §8), TensorBoard runs
(``tb/learner<v>``, ``tb/c_icrl``, ``tb/network``; with ``baselines=greedy`` also
``tb/me_greedy``, ``tb/mce_greedy``, curves over greedy steps), learned-constraint maps (PNG) and
the demonstrations; prints the results table. This is one of the only places that
read a config: everything below is built here and handed to the library.

With ``comm=distributed`` learner ``v`` is process ``v`` (its rank): started here with
``spawn_learners`` or by ``torchrun`` (``N_L = len(split)`` processes). Every process
rebuilds the experts and demonstrations from the seed, keeps only its own shard, trains
with checkpoints in ``checkpoint_rank<v>.pt``, and writes its evaluated row to
``learner_rows/rank<v>.json`` (all processes need the same run directory: a shared file
system across machines). Rank 0 (torchrun) or the launching process (spawned) then runs
C-ICRL and the expert rows and merges everything into ``results.json``. The numbers are
bit for bit those of the default all-in-one-process ``comm=simulated``.

Robustness: the config is checked before anything is computed (unknown keys, values out
of range; exit code 2, nothing written). Checkpoints and results are written atomically
and a checkpoint from another configuration is refused on resume. With
``comm=simulated`` a first SIGINT/SIGTERM finishes the outer iteration, checkpoints it
and exits with 128 + the signal number, printing the exact command that resumes; a
second one stops at once. A NaN or inf stops the run (exit 1) naming the outer
iteration, the inner step and the learner.
"""

from __future__ import annotations

import copy
import difflib
import hashlib
import inspect
import json
import math
import os
import shlex
import shutil
import signal
import sys
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
import torch.distributed as dist
from common import (
    GridParts,
    atomic_write,
    build,
    build_grid,
    log_disagreement,
    make_logger,
    print_table,
    trainer_settings,
    write_json,
)
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class, get_object, instantiate
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.algos.dicrl import DICRL, NonFiniteError
from dicrl_torch.algos.greedy import GreedyConstraintInference
from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.comm.distributed import (
    ConfigMismatchError,
    DistributedCommunicator,
    LearnerProcessError,
    PeerFailureError,
    shard_for_rank,
    spawn_learners,
)
from dicrl_torch.demos import load_demonstrations, partition_demonstrations, save_demonstrations
from dicrl_torch.demos.experts import expert_solution, sample_trajectories
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.figures import (
    constraint_cells,
    metric_curves,
    obstacle_cells,
    save_png,
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
)

RunOf = Callable[[int], str]  # learner id -> TensorBoard run name


# ---------------------------------------------------------------------- config checks
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
    ("algo.threshold", float, _in_open(0.0, 1.0),
     "a number in (0, 1) (ω_c,j >= threshold marks a learned constraint)", "0.5"),
    ("algo.prune_min_gain", float | None, _ge(0.0),
     "null (keep every constraint) or a number >= 0 (nats per trajectory)", "0.001"),
    ("algo.run_c_icrl", bool, None, "true or false", "true"),
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
    ("solver.warmup_timesteps", int, _ge(0), "an int >= 0 (SAC pre-training steps)",
     "30000"),
    ("solver.n_eval_episodes", int, _ge(1), "an int >= 1 (rollouts per estimate)", "10"),
    ("env.arena.max_steps", int, _ge(1), "an int >= 1 (episode limit in steps)", "300"),
    ("baselines.penalty", float, _in_open(0.0, math.inf),
     "a positive number (reward units per step in a constrained cell)", "10.0"),
    ("baselines.timesteps", int, _ge(1), "an int >= 1 (SAC steps per greedy trial)", "3000"),
]
GRID_ONLY = ("env.model.", "env.layout.")

# The baselines' table rows (names as in the paper) and the greedy's demonstrator model.
BASELINES = {"ME-greedy": "me", "MCE-greedy": "mce"}
DRONE_BASELINES = ("M(C)E-greedy",)  # the arena is (nearly) deterministic: ME = MCE

# Keys of nodes without a _target_ (those with one are checked against its signature).
KNOWN_KEYS = {
    "": {"env", "features", "solver", "algo", "graph", "comm", "logger", "name", "seed",
         "n_demonstrations", "split", "eval_episodes", "eval_every", "expert_temperature",
         "checkpoint_every", "resume", "baselines", "shard_files"},
    "env": {"layout", "model", "true_reward_weights", "arena"},
    # the drones' solver node (the grid's has a _target_, checked against its signature)
    "solver": {"timesteps", "warmup_timesteps", "final_timesteps", "final_checks",
               "final_restarts", "final_score", "n_eval_episodes", "eval_action", "solver"},
    "features": {"reward", "cost"},
    "graph": {"inner", "outer"},
    "algo": {"outer_iterations", "inner_steps", "inner_method", "inner_step", "steps",
             "lsca_curvature", "prune_accrued", "init_cost_weights", "init_reward_weights",
             "init_multiplier", "threshold", "prune_min_gain", "run_c_icrl"},
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


def _unknown_keys(node, path: str, problems: list[str]) -> None:
    """Keys of ``node`` (and below) that nothing reads: a misspelt or stray override would
    otherwise be ignored (``+key=...`` gets past Hydra's struct mode)."""
    if not isinstance(node, DictConfig):
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
        _unknown_keys(node[key], f"{path}.{key}" if path else key, problems)


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


def is_simulated(cfg) -> bool:
    return not issubclass(get_class(cfg.comm._target_), DistributedCommunicator)


def check_config(cfg: DictConfig) -> None:
    """Refuse unknown keys and out-of-range values before anything is computed.

    Raises:
        ConfigError: listing every problem, each naming the key, the value and the fix.
    """
    problems: list[str] = []
    _unknown_keys(cfg, "", problems)
    drones = is_drone_run(cfg)
    rules = VALUE_RULES + DRONE_RULES if drones else VALUE_RULES
    for key, kind, ok, must, example in rules:
        if drones and key.startswith(GRID_ONLY):
            continue
        if OmegaConf.select(cfg, key, default="__missing__") == "__missing__":
            if key != "comm.timeout_s":  # only the distributed backend has a timeout
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
    run = OmegaConf.select(cfg, "baselines.run", default=None)
    names, example = (list(DRONE_BASELINES), "baselines=greedy_drones") if drones else \
        (list(BASELINES), "baselines=greedy")
    if not (OmegaConf.is_list(run) and all(isinstance(x, str) and x in names for x in run)
            and len(set(run)) == len(run)):
        problems.append(f"baselines.run={_plain(run)} is invalid: it must be a list of "
                        f"distinct names among {names} (the rows to add; [] for "
                        f"none); set e.g. {example} or baselines=none.")
    checks = OmegaConf.select(cfg, "solver.final_checks", default=None)
    final = OmegaConf.select(cfg, "solver.final_timesteps", default=None)
    if drones and _type_ok(checks, int) and _type_ok(final, int) and 1 <= final < checks:
        problems.append(f"solver.final_checks={checks} exceeds solver.final_timesteps={final}: "
                        f"each scored chunk needs at least one step; lower final_checks.")
    if drones and not is_simulated(cfg):
        problems.append("comm=distributed is not supported for the drone arena yet (its SAC "
                        "solvers are not checkpointed across processes); use comm=simulated.")
    if problems:
        raise ConfigError(f"{len(problems)} problem(s) in the configuration, nothing was "
                          f"computed:\n" + "\n".join(f"  - {p}" for p in problems))


def _plain(value):
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


# What a checkpoint's training state depends on. Left out: how the run is started,
# logged, evaluated or stopped (resume, logger, eval_episodes, eval_every, threshold, ...),
# and algo.outer_iterations, so that a finished run can be resumed to train for longer.
# The history's metrics (FPR/FNR/RFD every outer iteration, CR/CVR every eval_every) are
# evaluations: each was taken with the settings of the run that computed its iteration,
# and the same overrides on resume give the uninterrupted run's history exactly.
CHECKPOINT_KEYS = ("seed", "n_demonstrations", "split", "expert_temperature", "env", "features",
                   "solver", "graph", "algo")
CHECKPOINT_IGNORED = ("solver.progress", "algo.outer_iterations", "algo.threshold",
                      "algo.prune_min_gain", "algo.run_c_icrl")


def training_config(cfg) -> dict[str, Any]:
    """The flattened ``key -> value`` config that a checkpoint must match to resume."""
    flat: dict[str, Any] = {}

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif path not in CHECKPOINT_IGNORED:
            flat[path] = node

    container = OmegaConf.to_container(cfg, resolve=True)
    walk({k: container[k] for k in CHECKPOINT_KEYS if k in container}, "")
    if container.get("shard_files") is not None:
        # Own demonstrations: the state depends on the files' contents, not on their paths.
        flat["shard_files.sha256"] = [hashlib.sha256(Path(f).read_bytes()).hexdigest()[:16]
                                      if Path(f).is_file() else None
                                      for f in container["shard_files"]]
    return flat


# ---------------------------------------------------------------------- the problem
@dataclass
class Problem(GridParts):
    """What every process rebuilds identically from the config and its seed."""

    experts: Any  # None in a learner process on its own shard file (rank >= 1)
    nominal: Any
    demos: Demonstrations | None  # None: a learner process that read only its own file
    shards: list[Demonstrations | None]
    ctx: dict  # what evaluate() needs


def build_problem(cfg, rank: int | None = None) -> Problem:
    """The problem as process ``rank`` sees it (None: the process that holds every shard).

    With ``shard_files``, a learner process reads only the files
    :func:`shard_files_read_by` names: the other learners' entries of ``shards`` are None,
    and so is ``demos`` unless every file was read.
    """
    grid = build_grid(cfg)
    model, reward_basis, w_true = grid.model, grid.reward_basis, grid.true_reward_weights
    split = list(cfg.split)
    if sum(split) != cfg.n_demonstrations:
        raise ValueError(f"split {split} sums to {sum(split)}, not n_demonstrations="
                         f"{cfg.n_demonstrations}; make them agree.")
    # Experts: the demonstrations and the two reference rows. A learner process on its own
    # shard file needs neither (rank 0 writes the rows), nor their solves' minutes.
    experts = nominal = None
    if cfg.get("shard_files") is None or rank in (None, 0):
        exp_solver = build(cfg.solver, model=model, dtype=torch.float64) \
            if model.n_pairs < 5_000_000 else grid.solver
        experts = expert_solution(solver=exp_solver, reward_features=reward_basis(),
                                  reward_weights=w_true, temperature=cfg.expert_temperature)
        nominal = expert_solution(solver=exp_solver, reward_features=reward_basis(),
                                  reward_weights=w_true, constrained=False,
                                  temperature=cfg.expert_temperature)
    if cfg.get("shard_files") is None:
        demos = sample_trajectories(experts, cfg.n_demonstrations,
                                    np.random.default_rng(cfg.seed))
        shards = partition_demonstrations(demos, split)
    else:
        shards = load_shard_files(list(cfg.shard_files), split, model,
                                  read=shard_files_read_by(cfg, rank))
        demos = None if None in shards else concatenate(shards)
    ctx = {"model": model, "layout": grid.layout, "episodes": cfg.eval_episodes,
           "reward_table": grid.true_reward_table(), "seed": cfg.seed, "w_true": w_true,
           "true": grid.cost_basis.true_constraints().numpy()}
    return Problem(**vars(grid), experts=experts, nominal=nominal, demos=demos,
                   shards=shards, ctx=ctx)


def load_shard_files(files: list[str], split: list[int], model,
                     read: list[int] | None = None) -> list[Demonstrations | None]:
    """Learner ``v``'s demonstrations from ``files[v]``, checked against the learners' model
    (cells, actions, experts, horizon, start cells) and ``split``, before any solve.

    Args:
        read: the learners whose files are read (default: all); the others' entries are None.

    Raises:
        ValueError: naming the file, what does not match and the fix.
    """
    read = list(range(len(files))) if read is None else read
    shards: list[Demonstrations | None] = [None] * len(files)
    for v in read:
        shards[v] = load_demonstrations(files[v], n_cells=model.n_cells,
                                        n_actions=model.n_actions, n_experts=model.n_experts,
                                        horizon=model.horizon)
    if len(read) == len(files):
        counts = [s.n_trajectories for s in shards]
        if counts != split:
            raise ValueError(f"shard_files hold {counts} trajectories, but split={split}; set "
                             f"split=[{','.join(map(str, counts))}] "
                             f"n_demonstrations={sum(counts)}.")
    for v in read:
        if shards[v].n_trajectories != split[v]:
            raise ValueError(f"demonstrations file '{files[v]}' holds "
                             f"{shards[v].n_trajectories} trajectories, but split[{v}]="
                             f"{split[v]}; set split to the files' trajectory counts.")
    start = np.asarray(model.start_state)
    for f, shard in ((files[v], shards[v]) for v in read):
        # P0 puts every expert in its start cell: a trajectory starting elsewhere was
        # recorded on another layout, and its likelihood would be 0.
        wrong = np.nonzero((shard.states[:, 0] != start).any(1))[0]
        if wrong.size:
            k = int(wrong[0])
            raise ValueError(f"demonstrations file '{f}': trajectory {k} starts in cells "
                             f"{shard.states[k, 0].tolist()}, but this layout's experts start "
                             f"in {start.tolist()}; use demonstrations recorded on this "
                             f"layout, or the env.layout they were recorded on.")
    return shards


def check_shard_contents(cfg) -> None:
    """Read ``shard_files`` once before anything is solved: a file that does not fit the run
    fails at start-up with :func:`load_shard_files`' message, not minutes later."""
    if is_drone_run(cfg) or cfg.get("shard_files") is None:
        return
    model = build(cfg.env.model, layout=instantiate(cfg.env.layout))
    load_shard_files(list(cfg.shard_files), list(cfg.split), model,
                     read=shard_files_read_by(cfg, torchrun_rank(cfg)))


def concatenate(shards: list[Demonstrations]) -> Demonstrations:
    """All learners' trajectories, in learner order (C-ICRL's and the baselines' data)."""
    return Demonstrations(states=np.concatenate([s.states for s in shards]),
                          actions=np.concatenate([s.actions for s in shards]),
                          n_cells=shards[0].n_cells, n_actions=shards[0].n_actions)


def announce(cfg, p: Problem, out: Path) -> None:
    """Printed (and the demonstrations saved) once per run, by the main process."""
    split = list(cfg.split)
    if p.demos is not None and cfg.get("shard_files") is None:  # files: already on disk
        save_demonstrations(out / "demos.npz", p.demos)
    make_baselines(cfg, p, progress=False)  # a baseline that cannot run fails now, not later
    print(f"{p.layout.n_experts} experts, {len(split)} learners holding {split} demonstrations;"
          f" {p.model.n_pairs:,} state-action pairs")


def make_trainer(cfg, p: Problem, shards: list[Demonstrations], communicator,
                 trajectory_counts: list[int], progress: bool = True) -> DICRL:
    """The trainer of the learners ``communicator.local_ids`` (holding ``shards``)."""
    return DICRL(solver=p.solver, reward_basis=p.reward_basis, cost_basis=p.cost_basis,
                 shards=shards, trajectory_counts=trajectory_counts, communicator=communicator,
                 progress=progress, **trainer_settings(cfg, communicator.n_learners))


# ---------------------------------------------------------------------- evaluation
def evaluate(policy, ctx) -> dict:
    # Every row is rolled out with the same random numbers (a generator seeded from the
    # config): a row depends neither on the process that evaluates it nor on the rows
    # evaluated before it, and all methods are compared on common random numbers.
    ev = rollout_true_cmg(policy=policy, model=ctx["model"], layout=ctx["layout"],
                          reward_table=ctx["reward_table"], n_episodes=ctx["episodes"],
                          rng=torch.Generator().manual_seed(ctx["seed"]))
    return {"CR_mean": ev.cr_mean, "CR_std": ev.cr_std, "CVR": ev.cvr}


def learner_row(trainer: DICRL, i: int, ctx, threshold: float,
                prune_min_gain: float | None, progress: bool = True) -> dict:
    """The table row of local learner ``i`` (prunes its constraints first, if asked)."""
    raw = learned_constraints(trainer.state.cost_weights[i], threshold)
    extra = {"FPR_before_pruning": false_positive_rate(raw, ctx["true"]),
             "FNR_before_pruning": false_negative_rate(raw, ctx["true"])}
    if prune_min_gain is not None:
        # The pruned set explains the learner's data to within min_gain nats per trajectory.
        cw, pruned = trainer.prune_constraints(i, threshold, prune_min_gain, progress=progress)
        trainer.state.cost_weights[i] = cw
        extra["pruned"] = len(pruned)
    learned = learned_constraints(trainer.state.cost_weights[i], threshold)
    row = evaluate(trainer.policy(i).soft_bellman.policy_at, ctx)
    row.update(extra)
    row.update(FPR=false_positive_rate(learned, ctx["true"]),
               FNR=false_negative_rate(learned, ctx["true"]),
               RFD=reward_function_distance(trainer.state.eta_bar[i, :-1], ctx["w_true"]),
               SR=None, multiplier=float(trainer.state.eta_bar[i, -1]),
               n_learned=int(learned.sum()))
    return row


def constraint_names(cost_basis, cost_weights, threshold: float) -> list[str]:
    """Names of the features that ``cost_weights`` ``[d]`` marks as constraints
    (``ω_c,j >= threshold``): kept in the table rows, so that the figures of a distributed
    run, drawn by one process, know every learner's constraints."""
    return [name for name, w in zip(cost_basis.names, cost_weights.tolist(), strict=True)
            if w >= threshold]


def constraint_map(layout, names: list[str], title: str) -> np.ndarray:
    """PNG-ready map of the learned cell constraints ``names`` (red crosses) over the
    true obstacles (bright)."""
    heat = np.zeros(layout.n_cells)
    heat[obstacle_cells(layout)] = 1.0
    return render_grid(layout, heat=heat, constraint_cells=constraint_cells(layout, names),
                       title=title)


def evaluate_learners(name: str, trainer: DICRL, p: Problem, cfg, logger, run_of: RunOf,
                      out: Path, progress: bool = True) -> list[dict]:
    """Rows, constraint maps and final TensorBoard values of the trainer's local learners."""
    import matplotlib.image

    a = cfg.algo
    rows = []
    for i, v in enumerate(trainer.local):
        row = learner_row(trainer, i, p.ctx, a.threshold, a.prune_min_gain, progress)
        row["constraints"] = constraint_names(p.cost_basis, trainer.state.cost_weights[i],
                                              a.threshold)
        img = constraint_map(p.layout, row["constraints"],
                             f"{name} learner {v + 1}: learned cell constraints (x)")
        logger.image(run_of(v), "eval/constraint_map", img, a.outer_iterations)
        matplotlib.image.imsave(out / f"constraints_{name}_{v + 1}.png", img)
        logger.scalar(run_of(v), "eval/CR", row["CR_mean"], a.outer_iterations)
        logger.scalar(run_of(v), "eval/CVR", row["CVR"], a.outer_iterations)
        rows.append(row)
    return rows


def make_baselines(cfg, p: Problem, progress: bool = True) -> dict[str, GreedyConstraintInference]:
    """The requested greedy baselines (``baselines.run``), by row name, built (and so
    checked: e.g. a cost basis that is not non-negative) but not run.

    As in the paper, they are given the TRUE reward and all demonstrations pooled; the
    candidate constraints are the configured cost basis, the model the problem's solver.
    """
    b = cfg.baselines
    reward = p.reward_basis().weighted(p.ctx["w_true"])
    eps = None if b.epsilon is None else float(b.epsilon)
    return {name: GreedyConstraintInference(
                solver=p.solver, reward=reward, cost_basis=p.cost_basis,
                demonstrations=p.demos, model=BASELINES[name], epsilon=eps,
                max_constraints=b.max_constraints, progress=progress)
            for name in b.run}


def run_baselines(cfg, p: Problem, logger, out: Path) -> tuple[dict, dict]:
    """Run the requested greedy baselines: their table rows and per-step histories.

    Every greedy step (a constraint added) logs ``eval/FPR``, ``eval/FNR`` and
    ``greedy/log_likelihood`` at step ``k`` = constraints added so far, under the run
    ``me_greedy`` / ``mce_greedy``; the final policy is evaluated as the other rows.
    """
    import matplotlib.image

    methods, histories = {}, {}
    for name, greedy in make_baselines(cfg, p).items():
        res = greedy.run()
        run = name.lower().replace("-", "_")
        mask = torch.zeros_like(res.constraint_mask)
        history = []
        for k, ll in enumerate(res.log_likelihood):
            if k:
                mask[res.added[k - 1]] = True
            fpr, fnr = (false_positive_rate(mask, p.ctx["true"]),
                        false_negative_rate(mask, p.ctx["true"]))
            history.append({"step": k, "added": res.added_names[k - 1] if k else None,
                            "log_likelihood": ll,
                            "improvement": res.improvement[k - 1] if k else None,
                            "FPR": fpr, "FNR": fnr})
            logger.scalar(run, "eval/FPR", fpr, k)
            logger.scalar(run, "eval/FNR", fnr, k)
            logger.scalar(run, "greedy/log_likelihood", ll, k)
        k = len(res.added)
        row = evaluate(res.solution.policy_at, p.ctx)
        row.update(FPR=false_positive_rate(res.constraint_mask, p.ctx["true"]),
                   FNR=false_negative_rate(res.constraint_mask, p.ctx["true"]),
                   RFD=None, SR=None, n_learned=k, stop_reason=res.stop_reason)
        row["constraints"] = constraint_names(p.cost_basis, res.constraint_mask.double(), 0.5)
        img = constraint_map(p.layout, row["constraints"], f"{name}: learned cell constraints (x)")
        logger.image(run, "eval/constraint_map", img, k)
        matplotlib.image.imsave(out / f"constraints_{name}.png", img)
        logger.scalar(run, "eval/CR", row["CR_mean"], k)
        logger.scalar(run, "eval/CVR", row["CVR"], k)
        methods[name] = {"D": "×", "NATR": "×", "learners": [row]}
        histories[name] = history
    return methods, histories


# ---------------------------------------------------------------------- training
class Checkpoints:
    """Trainer states by name in one file, written atomically (to a temporary file, then
    renamed: a crash leaves the previous checkpoint intact).

    Args:
        path: the checkpoint file.
        resume: load ``path`` if it exists.
        keep_previous: also keep each name's previous save (``<name>:previous``), so that
            learner processes whose last saves are one save apart can agree on a state.
        crash_tags: extra names for the ``DICRL_CRASH_AFTER=<name>:<n>`` fault injection
            (tests): the process sends itself SIGKILL (or ``DICRL_CRASH_SIGNAL``, e.g.
            ``TERM``) right after saving ``n``, once.
        config: :func:`training_config` of this run; a checkpoint written under another one
            is refused on resume (its state would silently continue another problem).

    Raises:
        ValueError: the checkpoint cannot be read, or was written under another config.
    """

    def __init__(self, path: Path, resume: bool, *, keep_previous: bool = False,
                 crash_tags: tuple[str, ...] = (), config: dict | None = None) -> None:
        self.path, self.keep_previous, self.crash_tags = path, keep_previous, crash_tags
        self.config, self.crashed = config, False
        self.saved: dict = {}
        if resume and path.exists():
            self.saved = self._load(path)
            for state in self.saved.values():
                self._check_config(state.get("run_config"))
            done = {k: v["outer_iteration"] for k, v in self.saved.items()
                    if not k.endswith(":previous")}
            print(f"resuming from {path} (outer iterations done: {done})")
        elif resume:
            print(f"resume=true but no checkpoint {path.name} in {path.parent}; starting "
                  f"from scratch")

    def _check_config(self, saved: dict | None) -> None:
        if self.config is None or saved is None or saved == self.config:
            return
        keys = sorted(k for k in set(saved) | set(self.config)
                      if saved.get(k, "<unset>") != self.config.get(k, "<unset>"))
        diff = "; ".join(f"{k}: {saved.get(k, '<unset>')!r} in the checkpoint, "
                         f"{self.config.get(k, '<unset>')!r} now" for k in keys[:6])
        raise ValueError(
            f"{self.path} was written with a different configuration ({diff}"
            f"{'; ...' if len(keys) > 6 else ''}). Resume with the overrides of the "
            f"interrupted run, or start a new run without resume=true (in another "
            f"hydra.run.dir).")

    @staticmethod
    def _load(path: Path) -> dict:
        try:
            # weights_only: tensors and plain containers, never arbitrary pickled objects
            saved = torch.load(path, weights_only=True)
        except Exception as e:
            raise ValueError(
                f"{path} cannot be read as a checkpoint ({type(e).__name__}: "
                f"{str(e).strip().splitlines()[0] if str(e).strip() else ''}); it is not one "
                f"this program wrote. Delete it to start over, or point hydra.run.dir at the "
                f"run it belongs to.") from e
        if not (isinstance(saved, dict) and all(isinstance(v, dict) and "outer_iteration" in v
                                                for v in saved.values())):
            raise ValueError(f"{path} holds no trainer states ({type(saved).__name__}), so it "
                             f"is not a checkpoint of this program; delete it to start over.")
        return saved

    def states(self, name: str) -> list[dict]:
        """The saved states of ``name``, newest first."""
        return [self.saved[k] for k in (name, f"{name}:previous") if k in self.saved]

    def save(self, name: str, trainer: DICRL) -> None:
        n = trainer.state.outer_iteration
        last = self.saved.get(name)
        if self.keep_previous and last is not None and last["outer_iteration"] != n:
            self.saved[f"{name}:previous"] = last
        # A copy: the trainer goes on changing its history list and, when pruning, ω_c in
        # place, and this state may be written again (with another name's save).
        self.saved[name] = {**copy.deepcopy(trainer.state_dict()), "run_config": self.config}
        atomic_write(self.path, lambda tmp: torch.save(self.saved, tmp))
        crash = os.environ.get("DICRL_CRASH_AFTER")  # fault injection for tests
        if not self.crashed and crash in {f"{tag}:{n}" for tag in (name, *self.crash_tags)}:
            self.crashed = True
            sig = getattr(signal, "SIG" + os.environ.get("DICRL_CRASH_SIGNAL", "KILL"))
            os.kill(os.getpid(), sig)


def policy_of(solution) -> Callable:
    """The ``policy_at`` of what ``DICRL.policy`` returns: a learner model's solution
    wrapping its soft-Bellman solution (``.soft_bellman``), or that solution itself."""
    return getattr(solution, "soft_bellman", solution).policy_at


def rollouts_due(done: int, cfg) -> bool:
    """Whether the curves get CR/CVR rollouts after ``done`` outer iterations: the first
    (where the curves start), every ``eval_every``-th and the last."""
    return done == 1 or done % cfg.eval_every == 0 or done == cfg.algo.outer_iterations


def outer_metrics(trainer: DICRL, ctx, threshold: float, rollouts: bool) -> dict[str, list]:
    """This outer iteration's metrics of the local learners, lists in local order.

    FPR and FNR (of ``ω_c >= threshold``, before the final pruning) and RFD always; CR
    (mean return) and CVR when ``rollouts``: ``ctx["episodes"]`` episodes of each
    learner's policy in the true CMG, with the table rows' common random numbers.
    """
    learned = [learned_constraints(w, threshold) for w in trainer.state.cost_weights]
    metrics = {"FPR": [false_positive_rate(m, ctx["true"]) for m in learned],
               "FNR": [false_negative_rate(m, ctx["true"]) for m in learned],
               "RFD": [reward_function_distance(eta[:-1], ctx["w_true"])
                       for eta in trainer.state.eta_bar]}
    if rollouts:
        rows = [evaluate(policy_of(trainer.policy(i)), ctx) for i in range(len(trainer.local))]
        metrics.update(CR=[r["CR_mean"] for r in rows], CVR=[r["CVR"] for r in rows])
    return metrics


def log_outer(logger, run_of: RunOf, trainer: DICRL, info: dict, log_network: bool) -> None:
    """TensorBoard values of the history entry ``info`` (with :func:`outer_metrics`)."""
    n = info["outer_iteration"]
    for i, v in enumerate(trainer.local):
        for tag, key in (("outer/multiplier", "multiplier"), ("outer/lga_norm", "lga_norm"),
                         ("eval/FPR", "FPR"), ("eval/FNR", "FNR"), ("eval/RFD", "RFD"),
                         ("eval/CR", "CR"), ("eval/CVR", "CVR")):
            if key in info:  # CR and CVR: only where rollouts_due
                logger.scalar(run_of(v), tag, info[key][i], n)
    if trainer.n_learners > 1:
        log_disagreement(logger if log_network else None, trainer, n)



class Interrupted(Exception):
    """SIGINT or SIGTERM stopped the run.

    Attributes:
        signum: the signal.
        saved: what was checkpointed on the way out (None: stopped at once; the last
            atomic checkpoint stays valid).
    """

    def __init__(self, signum: int, saved: str | None = None) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum, self.saved = signum, saved


class StopOnSignal:
    """SIGINT/SIGTERM handling of the all-in-one-process run (a context manager).

    The first signal during training lets the current outer iteration finish (a state
    in the middle of one is no consistent checkpoint; an iteration takes seconds), then
    :func:`train` checkpoints it and raises :class:`Interrupted`. A second signal, or one
    outside training, raises at once: every checkpoint is written atomically, so the
    last one stays valid, and everything after training is recomputed on resume.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.training = False
        self._previous: dict = {}

    def __enter__(self) -> StopOnSignal:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, frame) -> None:
        if self.training and self.signum is None:
            self.signum = signum
            print(f"\n{signal.Signals(signum).name} received: stopping after this outer "
                  f"iteration, with a checkpoint (send it again to stop at once)",
                  file=sys.stderr, flush=True)
            return
        raise Interrupted(signum)


def interrupt_on_signals() -> None:
    """SIGINT/SIGTERM raise :class:`Interrupted` at once (learner processes of a
    distributed run). A learner cannot finish its outer iteration alone: the others
    would wait for it at the next exchange. Its checkpoints are written atomically, so
    the last one stays valid, and resume lets a learner that is one save behind catch up.
    """

    def handle(signum: int, frame) -> None:
        raise Interrupted(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handle)


def train(name: str, trainer: DICRL, ckpt: Checkpoints, logger, run_of: RunOf, cfg,
          ctx, log_network: bool, stop: StopOnSignal | None = None) -> None:
    """Train to ``algo.outer_iterations`` with TensorBoard values and checkpoints.

    Raises:
        Interrupted: ``stop`` caught a signal; the last outer iteration is checkpointed.
    """
    a = cfg.algo
    # The trainer logs its inner/ scalars itself (each learner's own inner process).
    trainer.logger, trainer.run_name = logger, run_of

    def after_outer(t: DICRL, info: dict) -> None:
        # Into the history entry (info is trainer.history[-1]), before the checkpoint that
        # keeps it: results.json's curves (dicrl_torch.figures) and a resumed run's history
        # come from there. Lists per local learner, as "multiplier": a distributed run's
        # per-rank histories merge by concatenation (merge_learner_rows).
        info.update(outer_metrics(t, ctx, a.threshold,
                                  rollouts_due(t.state.outer_iteration, cfg)))
        log_outer(logger, run_of, t, info, log_network)
        if t.state.outer_iteration % cfg.checkpoint_every == 0:
            ckpt.save(name, t)
        if stop is not None and stop.signum is not None:
            stop.training = False  # a further signal now interrupts the save: still safe
            ckpt.save(name, t)
            raise Interrupted(stop.signum, f"{name} saved after outer iteration "
                                           f"{t.state.outer_iteration}")

    if stop is not None:
        stop.training = True
    try:
        trainer.train(a.outer_iterations, callback=after_outer)
    finally:
        if stop is not None:
            stop.training = False
    ckpt.save(name, trainer)


def finish(cfg, out: Path, p: Problem, d_icrl: dict, logger, ckpt: Checkpoints,
           t_start: float, c_icrl_comm, stop: StopOnSignal | None = None) -> None:
    """C-ICRL, the baselines (``baselines.run``) and the expert rows (in this process),
    then ``results.json`` and the table.

    ``d_icrl``: the D-ICRL ``learners`` rows, ``history`` and final ``disagreement``.
    """
    a = cfg.algo
    split = list(cfg.split)
    methods: dict = {"D-ICRL": {"D": "✓" if len(split) > 1 else "×", "NATR": "✓",
                                "learners": d_icrl["learners"]}}
    histories = {"D-ICRL": d_icrl["history"]}
    if a.run_c_icrl:
        pooled = p.demos  # every learner's trajectories, in learner order
        c = make_trainer(cfg, p, [pooled], c_icrl_comm, [pooled.n_trajectories])
        if states := ckpt.states("C-ICRL"):
            c.load_state_dict(states[0])
        train("C-ICRL", c, ckpt, logger, lambda v: "c_icrl", cfg, p.ctx, log_network=False,
              stop=stop)
        methods["C-ICRL"] = {"D": "×", "NATR": "✓", "learners": evaluate_learners(
            "C-ICRL", c, p, cfg, logger, lambda v: "c_icrl", out)}
        histories["C-ICRL"] = c.history
    baseline_rows, baseline_histories = run_baselines(cfg, p, logger, out)
    methods.update(baseline_rows)  # before the experts: the paper's row order
    histories.update(baseline_histories)
    for name, sol in (("Experts (ground truth)", p.experts), ("Experts (nominal)", p.nominal)):
        row = evaluate(sol.policy_at, p.ctx)
        row.update(FPR=None, FNR=None, RFD=0.0, SR=None)
        methods[name] = {"learners": [row]}

    results = {
        "experiment": cfg.name, "wall_s": time.perf_counter() - t_start,
        "methods": {k: {"learners": v["learners"]} for k, v in methods.items()},
        "consensus_max_pairwise_cost_distance": d_icrl["disagreement"],
        "history": {k: [{**h, "seconds": None} for h in hist]  # timings vary run to run
                    for k, hist in histories.items()},
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    write_json(out / "results.json", results)
    # After results.json: a figure that fails to draw loses no result.
    figures = write_figures(cfg, out, p, methods, results["history"], logger)
    logger.close()
    print()
    print_table(methods)
    print(f"\nwall time {results['wall_s']:.0f} s; consensus max ‖ω_c − ω_c'‖ = "
          f"{results['consensus_max_pairwise_cost_distance']:.1e}")
    print(f"results, TensorBoard runs (tb/) and figures in {out.resolve()}")
    print("figures:\n" + "\n".join(f"  {path.resolve()}" for path in figures))


def write_figures(cfg, out: Path, p: Problem, methods: dict, histories: dict,
                  logger) -> list[Path]:
    """The paper's Fig. 2 for this run, as PNG in ``out`` and TensorBoard images of the
    run ``figures``: 2a, the experts' visitation with the true constraints; 2b, the
    same with each bi-level learner's learned constraints (after pruning); 2c-2g, the
    metric curves over outer iterations, greedy baselines and experts as reference lines.

    ``methods``: the table (rows by method), ``histories``: ``results.json``'s history.
    Bi-level methods are those with an outer-iteration history; methods without a
    history are expert rows.
    """
    bilevel = [k for k in methods if k in histories and k not in BASELINES]
    colour = "colour: share of expert trajectories entering the cell"
    held = p.demos
    if held is None:  # torchrun's rank 0 with private shard files reads only its own
        held = next(s for s in p.shards if s is not None)
        colour += " (learner 1's file)"
    visits = state_visitation(held.states, p.layout.n_cells)
    images = {"fig2a_true_visitation": visitation_heatmap(
        p.layout, visits, constraint_cells=obstacle_cells(p.layout),
        title=f"Fig. 2a: the true CMG, its constraints (x)\n{colour}")}
    panels = []
    for name in bilevel:
        rows = methods[name]["learners"]
        for v, row in enumerate(rows):
            who = f"{name} learner {v + 1}" if len(rows) > 1 else name
            # Action and collision constraints have no cell to cross: named in the title.
            off_grid = [n for n in row["constraints"] if not constraint_cells(p.layout, [n])]
            listed = ", ".join(off_grid[:4]) + (f" and {len(off_grid) - 4} more"
                                                if len(off_grid) > 4 else "")
            panels.append(visitation_heatmap(
                p.layout, visits, constraint_cells=constraint_cells(p.layout, row["constraints"]),
                title=f"Fig. 2b: {who}, learned constraints (x)\n"
                      f"not on a cell: {listed or 'none'}\n"
                      f"FPR {row['FPR']:.2f}, FNR {row['FNR']:.2f} (after pruning)\n{colour}"))
    if panels:
        images["fig2b_learned_constraints"] = side_by_side(panels)
    if bilevel:
        images["fig2c-g_metric_curves"] = metric_curves(
            {k: histories[k] for k in bilevel},
            final_rows={k: methods[k]["learners"] for k in bilevel},
            baselines={k: methods[k]["learners"][0] for k in BASELINES if k in methods},
            experts={k: m["learners"][0] for k, m in methods.items() if k not in histories},
            title=f"{cfg.name}: {p.layout.n_experts} expert(s), {len(cfg.split)} learner(s) "
                  f"holding {list(cfg.split)} of {cfg.n_demonstrations} demonstrations "
                  f"(CR, CVR: {cfg.eval_episodes} episodes every {cfg.eval_every} outer "
                  f"iterations)")
    paths = []
    for tag, img in images.items():
        paths.append(save_png(out / f"{tag}.png", img))
        logger.image("figures", tag, img, cfg.algo.outer_iterations)
    return paths


# ---------------------------------------------------------------------- all in one process
def run_simulated(cfg, out: Path, t_start: float) -> None:
    with StopOnSignal() as stop:
        # The checkpoint is read (and checked against the config) before any computation.
        ckpt = Checkpoints(out / "checkpoint.pt", cfg.resume, config=training_config(cfg))
        p = build_problem(cfg)
        announce(cfg, p, out)
        split = list(cfg.split)
        logger = make_logger(cfg, out)
        trainer = make_trainer(cfg, p, p.shards, build(cfg.comm, n_learners=len(split)), split)
        if states := ckpt.states("D-ICRL"):
            trainer.load_state_dict(states[0])
        run_of = lambda v: f"learner{v}"  # noqa: E731
        train("D-ICRL", trainer, ckpt, logger, run_of, cfg, p.ctx, log_network=True, stop=stop)
        gap = trainer.disagreement()  # of the trained ω_c: pruning below is local
        rows = evaluate_learners("D-ICRL", trainer, p, cfg, logger, run_of, out)
        d_icrl = {"learners": rows, "history": trainer.history, "disagreement": gap}
        finish(cfg, out, p, d_icrl, logger, ckpt, t_start, build(cfg.comm, n_learners=1), stop)


# ---------------------------------------------------------------------- one process per learner
def gather_objects(comm: DistributedCommunicator, obj) -> list:
    """Every process's ``obj``, in rank order: small control values (the run directory,
    checkpoint iterations), never learner data."""
    objs: list = [None] * comm.n_learners
    try:
        dist.all_gather_object(objs, obj)
    except Exception as e:
        raise PeerFailureError(
            f"Learner {comm.rank} of {comm.n_learners}: exchanging control values failed "
            f"({type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else e})."
            f" A learner process died or never joined; check its log.") from e
    return objs


def resume_learner(comm: DistributedCommunicator, ckpt: Checkpoints, trainer: DICRL) -> None:
    """Load the newest checkpointed outer iteration that every learner has.

    A learner that dies between the last exchange of an outer iteration and its
    checkpoint is one save behind the others; they then use their previous save.
    """
    have = {int(sd["outer_iteration"]): sd for sd in ckpt.states("D-ICRL")}
    every = gather_objects(comm, sorted(have))
    start = min(max(h, default=0) for h in every)
    if start == 0:
        if any(every) and comm.rank == 0:
            print(f"learners {[r for r, h in enumerate(every) if not h]} have no checkpoint; "
                  f"every learner starts from scratch")
        return
    lacking = [r for r, h in enumerate(every) if start not in h]
    if lacking:
        raise ValueError(
            f"The learners' checkpoints share no outer iteration (saved: "
            f"{dict(enumerate(every))}); learners {lacking} have none at {start}. Delete "
            f"checkpoint_rank*.pt in the run directory to start over.")
    trainer.load_state_dict(have[start])
    if comm.rank == 0:
        print(f"D-ICRL learners continue after outer iteration {start}")


def run_learner(comm: DistributedCommunicator, cfg, out: Path, p: Problem,
                run_id: str) -> None:
    """Learner ``comm.rank``: train on its own shard, evaluate its row, write it to
    ``learner_rows/rank<r>.json`` and wait for the others."""
    rank, split = comm.rank, list(cfg.split)
    shard = shard_for_rank(p.shards, rank, world_size=comm.n_learners)
    trainer = make_trainer(cfg, p, [shard], comm, split, progress=rank == 0)
    ckpt = Checkpoints(out / f"checkpoint_rank{rank}.pt", cfg.resume, keep_previous=True,
                       crash_tags=(f"D-ICRL@rank{rank}",), config=training_config(cfg))
    resume_learner(comm, ckpt, trainer)
    logger = make_logger(cfg, out)
    run_of = lambda v: f"learner{v}"  # noqa: E731
    train("D-ICRL", trainer, ckpt, logger, run_of, cfg, p.ctx, log_network=rank == 0)
    gap = trainer.disagreement()  # of the trained ω_c, as in the simulated run
    rows = evaluate_learners("D-ICRL", trainer, p, cfg, logger, run_of, out,
                             progress=rank == 0)
    logger.close()
    write_json(out / "learner_rows" / f"rank{rank}.json", {
        "run_id": run_id, "rank": rank, "world_size": comm.n_learners, "row": rows[0],
        "history": [{**h, "seconds": None} for h in trainer.history], "disagreement": gap})
    comm.barrier()


def merge_learner_rows(out: Path, n_learners: int, run_id: str) -> dict:
    """The D-ICRL rows, history and disagreement of :func:`run_learner`'s files."""
    parts = []
    for r in range(n_learners):
        path = out / "learner_rows" / f"rank{r}.json"
        part = json.loads(path.read_text()) if path.exists() else None
        if part is None or part["run_id"] != run_id:
            why = "is missing" if part is None else "is from another run"
            raise FileNotFoundError(
                f"{path} {why}. Every learner writes its row into the run directory: "
                f"give all processes the same one (multi-node runs: hydra.run.dir on a "
                f"shared file system).")
        parts.append(part)
    # One history entry per outer iteration; per-learner lists are concatenated in rank
    # order (learner id == rank), the rest (iteration, inner processes) is global.
    history = [{k: [x for part in parts for x in part["history"][j][k]]
                if isinstance(v, list) else v for k, v in entry.items()}
               for j, entry in enumerate(parts[0]["history"])]
    return {"learners": [part["row"] for part in parts], "history": history,
            "disagreement": parts[0]["disagreement"]}


def spawned_learner(rank: int, world_size: int, init_method: str, cfg_yaml: str,
                    out_dir: str, run_id: str) -> None:
    """Body of a learner process started by :func:`spawn_learners`."""
    from tqdm import tqdm

    # tqdm's default multiprocessing lock would be a named semaphore here (spawned
    # process), which the process's final os._exit leaks; a thread lock suffices.
    tqdm.set_lock(threading.RLock())
    interrupt_on_signals()
    cfg = OmegaConf.create(cfg_yaml)
    comm = build(cfg.comm, init_method=init_method, rank=rank, world_size=world_size)
    comm.check_same_config(cfg_yaml)
    run_learner(comm, cfg, Path(out_dir), build_problem(cfg, rank=rank), run_id)
    comm.close()


def run_spawned(cfg, out: Path, t_start: float) -> None:
    """``python experiments/train.py comm=distributed``: one learner process per shard."""
    split = list(cfg.split)
    p = build_problem(cfg)
    announce(cfg, p, out)
    cfg_yaml = OmegaConf.to_yaml(cfg, resolve=True)
    threads = int(os.environ.get("DICRL_THREADS", max(1, torch.get_num_threads() // len(split))))
    run_id = uuid.uuid4().hex
    print(f"starting {len(split)} learner processes ({threads} thread(s) each)", flush=True)
    interrupt_on_signals()  # on a signal, spawn_learners stops every learner on its way out
    try:
        # No overall time limit: every wait between learners is bounded by comm.timeout_s,
        # and once one process fails the others are stopped after a grace period.
        spawn_learners(spawned_learner, len(split), args=(cfg_yaml, str(out), run_id),
                       timeout_s=float("inf"), num_threads=threads)
    except LearnerProcessError as e:
        first = e.tracebacks.get(e.first_failed) if e.first_failed is not None else None
        if first:
            print(first, file=sys.stderr)
        print(f"error: {e}\n{resume_hint(out)}", file=sys.stderr, flush=True)
        sys.exit(1)
    except Interrupted as e:
        print(f"\ninterrupted by {e}: every learner process was stopped; no results.json "
              f"was written. {resume_hint(out)}", file=sys.stderr, flush=True)
        sys.exit(128 + e.signum)
    finish(cfg, out, p, merge_learner_rows(out, len(split), run_id), make_logger(cfg, out),
           Checkpoints(out / "checkpoint.pt", cfg.resume, config=training_config(cfg)),
           t_start, SimulatedCommunicator(n_learners=1))


def resume_command(out: Path) -> str:
    """The exact command line that continues this run from its checkpoints."""
    try:
        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # no Hydra context (a spawned learner process)
        task = []
    keep = [o for o in task if not o.startswith(("resume=", "hydra.run.dir="))]
    return shlex.join([sys.executable, sys.argv[0], *keep, "resume=true",
                       f"hydra.run.dir={out}"])


def resume_hint(out: Path) -> str:
    return (f"The last checkpoints (checkpoint_rank<r>.pt) are in {out}; continue with the "
            f"same overrides plus resume=true hydra.run.dir={out}:\n  {resume_command(out)}")


def agree_on_run_dir(comm: DistributedCommunicator, out: Path) -> tuple[Path, str]:
    """Rank 0's run directory and a run id. Hydra names the default directory after the
    second it started in, which can differ between the processes torchrun starts; the
    others' (still empty) directories are removed."""
    root, run_id = gather_objects(comm, (str(out.resolve()), uuid.uuid4().hex))[0]
    root = Path(root)
    if root != out.resolve():
        if out.is_dir() and {q.name for q in out.iterdir()} <= {".hydra", "train.log"}:
            shutil.rmtree(out, ignore_errors=True)
        root.mkdir(parents=True, exist_ok=True)
    return root, run_id


def run_torchrun(cfg, out: Path, t_start: float) -> None:
    """A process started by torchrun: learner ``RANK``; rank 0 also finishes the run."""
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    split = list(cfg.split)
    if world_size != len(split):
        raise ValueError(
            f"torchrun started WORLD_SIZE={world_size} processes but split={split} has "
            f"{len(split)} learners (one process per learner); run torchrun with "
            f"--nproc_per_node {len(split)} (times the nodes), or change split.")
    interrupt_on_signals()
    try:
        comm = build(cfg.comm, rank=rank, world_size=world_size)  # init_method env://
        comm.check_same_config(OmegaConf.to_yaml(cfg, resolve=True))
        out, run_id = agree_on_run_dir(comm, out)
        p = build_problem(cfg, rank=rank)
        if rank == 0:
            announce(cfg, p, out)
        run_learner(comm, cfg, out, p, run_id)
        comm.close()
    except Exception as e:
        # Exit at once, without tearing down a process group with a dead peer (can hang).
        if not isinstance(e, PeerFailureError | ConfigMismatchError | Interrupted):
            traceback.print_exc()
        what = (f"interrupted by {e}" if isinstance(e, Interrupted)
                else f"{type(e).__name__}: {e}")
        print(f"error: learner {rank}: {what}\n{resume_hint(out)}", file=sys.stderr,
              flush=True)
        sys.stdout.flush()
        os._exit(128 + e.signum if isinstance(e, Interrupted) else 1)
    if rank == 0:
        finish(cfg, out, p, merge_learner_rows(out, world_size, run_id),
               make_logger(cfg, out),
               Checkpoints(out / "checkpoint.pt", cfg.resume, config=training_config(cfg)),
               t_start, SimulatedCommunicator(n_learners=1))


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    t_start = time.perf_counter()
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        check_config(cfg)
        check_shard_contents(cfg)
    except ValueError as e:  # a ConfigError, or a shard file that does not fit the run
        print(f"error: {e}", file=sys.stderr, flush=True)
        sys.exit(2)
    torch.set_num_threads(int(os.environ.get("DICRL_THREADS", torch.get_num_threads())))
    if is_drone_run(cfg):
        from drones import run_drones  # imports stable-baselines3: only for the arena

        run_drones(cfg, out, t_start)
    elif is_simulated(cfg):
        if int(os.environ.get("WORLD_SIZE", "1")) > 1:
            raise ValueError(f"Started as one of WORLD_SIZE={os.environ['WORLD_SIZE']} "
                             f"processes (torchrun?) with comm={cfg.comm._target_}, which runs "
                             f"every learner in each process; add comm=distributed.")
        try:
            run_simulated(cfg, out, t_start)
        except Interrupted as e:
            what = (f"checkpoint {e.saved}" if e.saved else
                    "stopped at once; the last checkpoint written stays valid")
            print(f"\ninterrupted by {e} ({what}). Checkpoints are in "
                  f"{out / 'checkpoint.pt'}; no results.json was written. Resume with:\n"
                  f"  {resume_command(out)}", file=sys.stderr, flush=True)
            sys.exit(128 + e.signum)  # the shell's convention for "killed by a signal"
        except NonFiniteError as e:
            # The checkpoints hold only finite states; rerun with the changes it suggests.
            print(f"error: {e}\nno results.json was written.", file=sys.stderr, flush=True)
            sys.exit(1)
    elif "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        run_torchrun(cfg, out, t_start)
    else:
        run_spawned(cfg, out, t_start)


if __name__ == "__main__":
    main()
