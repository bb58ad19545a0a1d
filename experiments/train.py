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

import json
import os
import shlex
import shutil
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
from checkpoints import (
    Checkpoints,
    Interrupted,
    StopOnSignal,
    evaluation_settings,
    interrupt_on_signals,
    progress_of,
    stoppable,
    training_config,
)
from common import (
    GridParts,
    build,
    build_grid,
    log_disagreement,
    make_logger,
    print_table,
    print_timings,
    results_record,
    trainer_settings,
    write_json,
)
from config_checks import (
    BASELINES,
    check_config,
    is_drone_run,
    is_simulated,
    shard_files_read_by,
    torchrun_rank,
)
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.algos.dicrl import DICRL, NonFiniteError
from dicrl_torch.algos.greedy import (
    GreedyConstraintInference,
    GreedyResult,
    ResumeMismatchError,
)
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


def constraint_map(p: Problem, names: list[str], title: str) -> np.ndarray:
    """PNG-ready map of the learned cell (and region) constraints ``names`` (red crosses)
    over the true obstacles (bright)."""
    heat = np.zeros(p.layout.n_cells)
    heat[obstacle_cells(p.layout)] = 1.0
    cells = constraint_cells(p.layout, names, p.cost_basis.region_cells)
    return render_grid(p.layout, heat=heat, constraint_cells=cells, title=title)


def evaluate_learners(name: str, trainer: DICRL, p: Problem, cfg, logger, run_of: RunOf,
                      out: Path, ckpt: Checkpoints, progress: bool = True) -> list[dict]:
    """Rows, constraint maps and final TensorBoard values of the trainer's local learners.

    The rows are checkpointed; a resumed run takes them from there instead of pruning
    and rolling out again (the trainer's ω_c then stays unpruned).
    """
    import matplotlib.image

    a = cfg.algo
    settings, n = evaluation_settings(cfg), trainer.state.outer_iteration
    saved = ckpt.evaluated_rows(name, n, settings)
    if saved is not None:
        print(f"{name}: rows evaluated after outer iteration {n} taken from {ckpt.path}")
    rows = []
    for i, v in enumerate(trainer.local):
        if saved is not None:
            row = saved[i]
        else:
            row = learner_row(trainer, i, p.ctx, a.threshold, a.prune_min_gain, progress)
            row["constraints"] = constraint_names(p.cost_basis, trainer.state.cost_weights[i],
                                                  a.threshold)
        img = constraint_map(p, row["constraints"],
                             f"{name} learner {v + 1}: learned cell constraints (x)")
        logger.image(run_of(v), "eval/constraint_map", img, a.outer_iterations)
        matplotlib.image.imsave(out / f"constraints_{name}_{v + 1}.png", img)
        logger.scalar(run_of(v), "eval/CR", row["CR_mean"], a.outer_iterations)
        logger.scalar(run_of(v), "eval/CVR", row["CVR"], a.outer_iterations)
        rows.append(row)
    if saved is None:
        ckpt.save_rows(name, n, settings, rows)
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


def run_greedy(name: str, greedy: GreedyConstraintInference, ckpt: Checkpoints,
               stop: StopOnSignal | None) -> GreedyResult:
    """One greedy baseline, checkpointed (as ``name``) after every candidate it evaluates
    and continued from its saved progress on resume.

    Raises:
        Interrupted: ``stop`` caught a signal; the last evaluated candidate is saved.
    """
    saved = ckpt.states(name)

    def save(record: dict) -> None:
        ckpt.save_state(name, {"greedy": record,
                               "outer_iteration": record["evaluated"] + record["finished"]})
        if stop is not None and stop.signum is not None:
            stop.training = False
            raise Interrupted(stop.signum, f"{name} saved {progress_of(ckpt.saved[name])}")

    try:
        with stoppable(stop):  # a first signal lets the current candidate finish
            return greedy.run(resume_from=saved[0]["greedy"] if saved else None,
                              on_step=save)
    except ResumeMismatchError as e:
        raise ResumeMismatchError(f"{e} (The progress is {name} in {ckpt.path}; resume with "
                                  f"the interrupted run's baselines.epsilon and "
                                  f"baselines.max_constraints.)") from e


def run_baselines(cfg, p: Problem, logger, out: Path, ckpt: Checkpoints,
                  stop: StopOnSignal | None = None) -> tuple[dict, dict, dict]:
    """Run the requested greedy baselines: their table rows, per-step histories and
    seconds (every resumed segment counted).

    Every greedy step (a constraint added) logs ``eval/FPR``, ``eval/FNR`` and
    ``greedy/log_likelihood`` at step ``k`` = constraints added so far, under the run
    ``me_greedy`` / ``mce_greedy``; the final policy is evaluated as the other rows.
    """
    import matplotlib.image

    methods, histories, seconds = {}, {}, {}
    for name, greedy in make_baselines(cfg, p).items():
        res = run_greedy(name, greedy, ckpt, stop)
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
        img = constraint_map(p, row["constraints"], f"{name}: learned cell constraints (x)")
        logger.image(run, "eval/constraint_map", img, k)
        matplotlib.image.imsave(out / f"constraints_{name}.png", img)
        logger.scalar(run, "eval/CR", row["CR_mean"], k)
        logger.scalar(run, "eval/CVR", row["CVR"], k)
        methods[name] = {"D": "×", "NATR": "×", "learners": [row]}
        histories[name] = history
        seconds[name] = res.seconds
    return methods, histories, seconds


# ---------------------------------------------------------------------- training
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


def log_history_entry(logger, run_of: RunOf, local: list[int], info: dict,
                      learners: list[int] | None = None) -> None:
    """The ``outer/`` and ``eval/`` values of the history entry ``info`` (with
    :func:`outer_metrics`) for the local learners ``local`` (or those of them in
    ``learners``)."""
    n = info["outer_iteration"]
    for i, v in enumerate(local):
        if learners is not None and v not in learners:
            continue
        for tag, key in (("outer/multiplier", "multiplier"), ("outer/lga_norm", "lga_norm"),
                         ("eval/FPR", "FPR"), ("eval/FNR", "FNR"), ("eval/RFD", "RFD"),
                         ("eval/CR", "CR"), ("eval/CVR", "CVR")):
            if key in info:  # CR and CVR: only where rollouts_due
                logger.scalar(run_of(v), tag, info[key][i], n)


def log_outer(logger, run_of: RunOf, trainer: DICRL, info: dict, log_network: bool) -> None:
    """TensorBoard values of the history entry ``info`` just computed."""
    log_history_entry(logger, run_of, trainer.local, info)
    if trainer.n_learners > 1:
        log_disagreement(logger if log_network else None, trainer, info["outer_iteration"])


def replay_history(logger, run_of: RunOf, trainer: DICRL) -> None:
    """Write a resumed trainer's checkpointed history into the learner runs that have no
    values yet: a checkpoint carried to another directory, checkout or machine arrives
    without its event files, and its curves would otherwise start where it resumed. The
    inner/ values and the network's distances are not in the history."""
    fresh = [v for v in trainer.local if not logger.has_run(run_of(v))]
    if not fresh:
        return
    for info in trainer.history:
        log_history_entry(logger, run_of, trainer.local, info, learners=fresh)



def train(name: str, trainer: DICRL, ckpt: Checkpoints, logger, run_of: RunOf, cfg,
          ctx, log_network: bool, stop: StopOnSignal | None = None) -> None:
    """Train to ``algo.outer_iterations`` with TensorBoard values and checkpoints.

    Raises:
        Interrupted: ``stop`` caught a signal; the last outer iteration is checkpointed.
    """
    a = cfg.algo
    replay_history(logger, run_of, trainer)
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

    with stoppable(stop):
        trainer.train(a.outer_iterations, callback=after_outer)
    ckpt.save(name, trainer)


def finish(cfg, out: Path, p: Problem, d_icrl: dict, logger, ckpt: Checkpoints,
           t_start: float, c_icrl_comm, stop: StopOnSignal | None = None) -> None:
    """C-ICRL, the baselines (``baselines.run``) and the expert rows (in this process),
    then ``results.json`` and the table.

    ``d_icrl``: the D-ICRL ``learners`` rows, ``history`` and final ``disagreement``;
    None when ``algo.run_d_icrl=false``.
    """
    a = cfg.algo
    methods: dict = {}
    histories: dict = {}
    if d_icrl is not None:
        methods["D-ICRL"] = {"D": "✓" if len(cfg.split) > 1 else "×", "NATR": "✓",
                             "learners": d_icrl["learners"]}
        histories["D-ICRL"] = d_icrl["history"]
    if a.run_c_icrl:
        pooled = p.demos  # every learner's trajectories, in learner order
        c = make_trainer(cfg, p, [pooled], c_icrl_comm, [pooled.n_trajectories])
        if states := ckpt.states("C-ICRL"):
            c.load_state_dict(states[0])
        train("C-ICRL", c, ckpt, logger, lambda v: "c_icrl", cfg, p.ctx, log_network=False,
              stop=stop)
        methods["C-ICRL"] = {"D": "×", "NATR": "✓", "learners": evaluate_learners(
            "C-ICRL", c, p, cfg, logger, lambda v: "c_icrl", out, ckpt)}
        histories["C-ICRL"] = c.history
    baseline_rows, baseline_histories, baseline_seconds = run_baselines(cfg, p, logger, out,
                                                                         ckpt, stop)
    methods.update(baseline_rows)  # before the experts: the paper's row order
    histories.update(baseline_histories)
    for name, sol in (("Experts (ground truth)", p.experts), ("Experts (nominal)", p.nominal)):
        row = evaluate(sol.policy_at, p.ctx)
        row.update(FPR=None, FNR=None, RFD=0.0, SR=None)
        methods[name] = {"learners": [row]}

    results = results_record(cfg, t_start=t_start, methods=methods,
                             disagreement=None if d_icrl is None else d_icrl["disagreement"],
                             histories=histories, baseline_seconds=baseline_seconds)
    write_json(out / "results.json", results)
    # After results.json: a figure that fails to draw loses no result.
    figures = write_figures(cfg, out, p, methods, results["history"], logger)
    logger.close()
    print()
    print_table(methods)
    print_timings(results, resumed=cfg.resume)
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
            off_grid = [n for n in row["constraints"]
                        if not constraint_cells(p.layout, [n], p.cost_basis.region_cells)]
            listed = ", ".join(off_grid[:4]) + (f" and {len(off_grid) - 4} more"
                                                if len(off_grid) > 4 else "")
            panels.append(visitation_heatmap(
                p.layout, visits, constraint_cells=constraint_cells(
                    p.layout, row["constraints"], p.cost_basis.region_cells),
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
        d_icrl = None
        if cfg.algo.run_d_icrl:
            trainer = make_trainer(cfg, p, p.shards, build(cfg.comm, n_learners=len(split)),
                                   split)
            if states := ckpt.states("D-ICRL"):
                trainer.load_state_dict(states[0])
            run_of = lambda v: f"learner{v}"  # noqa: E731
            train("D-ICRL", trainer, ckpt, logger, run_of, cfg, p.ctx, log_network=True,
                  stop=stop)
            gap = trainer.disagreement()  # of the trained ω_c: pruning below is local
            rows = evaluate_learners("D-ICRL", trainer, p, cfg, logger, run_of, out, ckpt)
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
    rows = evaluate_learners("D-ICRL", trainer, p, cfg, logger, run_of, out, ckpt,
                             progress=rank == 0)
    logger.close()
    write_json(out / "learner_rows" / f"rank{rank}.json", {
        "run_id": run_id, "rank": rank, "world_size": comm.n_learners, "row": rows[0],
        "history": trainer.history, "disagreement": gap})
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
