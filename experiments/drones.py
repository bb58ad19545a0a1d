"""The drone arena's experiment (paper §6.2, Table 2), run by ``experiments/train.py``
when the configured env is the arena (``env=drones``: ``experiment=table2`` or
``experiment=table2_quick``).

The same D-ICRL trainer as the grid world drives it; only the learner model differs
(:class:`dicrl_torch.solvers.sac.SACLearnerModel`: one warm-started SAC solver per
learner). The steps:

1. 9 demonstrated pairs from the via-point planner, split 4/5 over two learners.
2. One SAC solver is pre-trained on ``η(0), ω_c(0)`` (``solver.warmup_timesteps``);
   every learner, and C-ICRL, starts from a clone of it (all start from the same
   ``η(0)``), so the warm-up is paid once.
3. D-ICRL (and C-ICRL: one learner, all pairs). A last solve of
   ``solver.final_timesteps`` on each learner's learned ``(η̄, ω_c)`` gives its policy,
   rolled out ``eval_episodes`` times in the TRUE game (violators freeze) with mean and
   with sampled actions: SR and CVR.
4. M(C)E-greedy given the reward learned by D-ICRL (learner 1's ``ω_r``), as in the
   paper (the arena's noise is small, so ME and MCE coincide: one row).
5. ``results.json``, the table in the paper's layout, Fig. 3b/3c analogues (PNG and
   TensorBoard).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from common import (
    TABLE2_COLUMNS,
    build,
    log_disagreement,
    make_logger,
    print_table,
    print_timings,
    results_record,
    trainer_settings,
    write_json,
)
from hydra.utils import instantiate

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.algos.greedy import SACGreedyConstraintInference
from dicrl_torch.demos.drone_demos import (
    DroneDemonstrations,
    make_drone_demonstrations,
    partition_drone_demonstrations,
    save_drone_demonstrations,
)
from dicrl_torch.envs.drones import render_arena
from dicrl_torch.metrics import false_negative_rate, false_positive_rate, learned_constraints
from dicrl_torch.solvers.sac import SACConstrainedSolver, SACLearnerModel


def derived_seed(seed: int, *keys: int) -> int:
    """An independent stream per purpose (learner, C-ICRL, evaluation) from one seed."""
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


@dataclass
class DroneProblem:
    """What the run builds from the config and its seed."""

    reward_basis: torch.nn.Module
    cost_basis: torch.nn.Module
    demos: DroneDemonstrations
    shards: list[DroneDemonstrations]
    true: np.ndarray  # [d] bool, the true constraint features


def build_drone_problem(cfg) -> DroneProblem:
    reward_basis = instantiate(cfg.features.reward)
    cost_basis = instantiate(cfg.features.cost)
    # The planner flies its pairs in the default arena (30 s): a shorter learner episode
    # limit (env.arena.max_steps) must not make it fail.
    demos = make_drone_demonstrations(cfg.n_demonstrations, rng=np.random.default_rng(cfg.seed))
    shards = partition_drone_demonstrations(demos, list(cfg.split))
    return DroneProblem(reward_basis=reward_basis, cost_basis=cost_basis, demos=demos,
                        shards=shards, true=cost_basis.true_constraints().numpy())


def pretrained_solver(cfg, p: DroneProblem) -> SACConstrainedSolver:
    """A solver trained ``solver.warmup_timesteps`` on the initial ``(η(0), ω_c(0))``."""
    solver = build(cfg.solver.solver, reward_basis=p.reward_basis, cost_basis=p.cost_basis,
                   seed=derived_seed(cfg.seed, 1), env_kwargs=dict(cfg.env.arena))
    a = cfg.algo
    eta0 = torch.full((solver.l_r + 1,), float(a.init_reward_weights), dtype=torch.float64)
    eta0[-1] = float(a.init_multiplier)
    cw0 = torch.full((solver.l_c,), float(a.init_cost_weights), dtype=torch.float64)
    steps = int(cfg.solver.warmup_timesteps)
    if steps:
        t0 = time.perf_counter()
        sol = solver.solve(eta0, cw0, steps)
        print(f"SAC warm-up: {steps} steps on η(0) in {time.perf_counter() - t0:.0f} s; in "
              f"the nominal game {float(sol.reached.double().mean()):.2f} of the drones reach "
              f"their door and {sol.violation_rate:.2f} cross a true constraint", flush=True)
    return solver


def make_drone_trainer(cfg, p: DroneProblem, base: SACConstrainedSolver, shards, counts,
                       communicator, stream: int) -> DICRL:
    """A trainer whose local learners each own a clone of ``base`` (seeded per learner
    and per ``stream``: 0 for D-ICRL, 1 for C-ICRL)."""
    solvers = [base.clone(derived_seed(cfg.seed, 2, stream, v)) for v in communicator.local_ids]
    for solver, shard in zip(solvers, shards, strict=True):  # both in local_ids order
        solver.set_demonstrations(shard)  # its own pairs only (solver.demo_fraction)
    model = SACLearnerModel(solvers=solvers, timesteps=int(cfg.solver.timesteps),
                            n_eval_episodes=int(cfg.solver.n_eval_episodes))
    return DICRL(learner_model=model, shards=shards, trajectory_counts=counts,
                 communicator=communicator, progress=True,
                 **trainer_settings(cfg, communicator.n_learners))


def log_outer(logger, run_of, trainer: DICRL, info: dict, p: DroneProblem,
              threshold: float) -> None:
    """Per outer iteration: FPR/FNR of each learner's ω_c (also kept in the history)."""
    n = info["outer_iteration"]
    info["FPR"], info["FNR"] = [], []
    for i, v in enumerate(trainer.local):
        learned = learned_constraints(trainer.state.cost_weights[i], threshold)
        fpr, fnr = false_positive_rate(learned, p.true), false_negative_rate(learned, p.true)
        info["FPR"].append(fpr)
        info["FNR"].append(fnr)
        logger.scalar(run_of(v), "eval/FPR", fpr, n)
        logger.scalar(run_of(v), "eval/FNR", fnr, n)
        logger.scalar(run_of(v), "outer/multiplier", info["multiplier"][i], n)
        logger.scalar(run_of(v), "outer/lga_norm", info["lga_norm"][i], n)
    if trainer.n_learners > 1:
        log_disagreement(logger, trainer, n)


def evaluate_true_game(solver: SACConstrainedSolver, cfg) -> tuple[dict, list[np.ndarray]]:
    """SR and CVR of the solver's current policy in the TRUE game, on common random
    numbers (the same episode seeds for every row and both action modes).

    The table's SR and CVR use ``solver.eval_action``: ``mean`` flies the policy's mean
    action (how an SAC policy is deployed; SB3's ``evaluate_policy`` default), ``sampled``
    flies the stochastic MCE policy itself. The row holds both (``SR_mean``,
    ``SR_sampled``, ...); the figure shows the table's."""
    evs = {mode: solver.evaluate(int(cfg.eval_episodes), deterministic=mode == "mean",
                                 true_game=True, trajectories=True,
                                 rng=np.random.default_rng(derived_seed(cfg.seed, 3)))
           for mode in ("mean", "sampled")}
    row = {"CR_mean": None, "CR_std": None, "RFD": None}
    for mode, ev in evs.items():
        row[f"SR_{mode}"], row[f"CVR_{mode}"] = ev.success_rate, ev.violation_rate
    shown = evs[str(cfg.solver.eval_action)]
    row.update(SR=shown.success_rate, CVR=shown.violation_rate)
    return row, shown.paths


def constraint_row(mask: np.ndarray, p: DroneProblem) -> dict:
    names = [p.cost_basis.names[j] for j in np.flatnonzero(mask)]
    return {"FPR": false_positive_rate(mask, p.true), "FNR": false_negative_rate(mask, p.true),
            "n_learned": int(mask.sum()), "constraints": names}


def figure(name: str, mask, paths, out: Path, logger, run: str, step: int) -> None:
    """Fig. 3c analogue: learned constraint cells and rollouts of the learned policy."""
    import matplotlib.image

    img = render_arena(trajectories=paths[:9], constraint_cells=np.asarray(mask, dtype=bool),
                       title=f"{name}: learned constraints (hatched) and 9 rollouts")
    logger.image(run, "eval/constraint_map", img, step)
    path = out / f"fig3c_{name.lower().replace(' ', '_').replace('(', '').replace(')', '')}.png"
    matplotlib.image.imsave(path, img)


def run_icrl(name: str, trainer: DICRL, cfg, p: DroneProblem, logger, run_of,
             out: Path) -> list[dict]:
    """Train, then the table rows (and figures) of the trainer's learners."""
    a = cfg.algo
    trainer.logger, trainer.run_name = logger, run_of  # its inner/ scalars
    trainer.train(a.outer_iterations, callback=lambda t, info: log_outer(
        logger, run_of, t, info, p, a.threshold))
    rows = []
    for i, v in enumerate(trainer.local):
        mask = learned_constraints(trainer.state.cost_weights[i], a.threshold)
        # The learned policy is the inner problem's solution at the learned (η̄, ω_c): a
        # last solve, `solver.final_timesteps` long, brings SAC closer to it.
        solver = trainer.learner_model.solvers[i]
        kept = solver.solve_keeping_best(
            trainer.state.eta_bar[i], trainer.state.cost_weights[i],
            int(cfg.solver.final_timesteps), checks=int(cfg.solver.final_checks),
            restarts=int(cfg.solver.final_restarts),
            deterministic=cfg.solver.eval_action == "mean",
            constraints=mask if cfg.solver.final_score == "learned_success" else None)
        row, paths = evaluate_true_game(solver, cfg)
        row.update(constraint_row(mask, p), multiplier=float(trainer.state.eta_bar[i, -1]),
                   reward_weights=trainer.state.eta_bar[i, :-1].tolist(),
                   policy_timesteps=kept.timesteps,
                   final_checks=solver.last_checks)
        label = f"{name} learner {v + 1}" if trainer.n_learners > 1 else name
        figure(label, mask, paths, out, logger, run_of(v), a.outer_iterations)
        for key in ("SR", "CVR"):
            logger.scalar(run_of(v), f"eval/{key}", row[key], a.outer_iterations)
        for check in solver.last_checks:  # the last solve's chunk scores, per restart
            suffix = f"/restart{check['restart']}" if check["restart"] else ""
            for key in ("penalised_return", "success_under_constraints"):
                if check[key] is not None:
                    logger.scalar(run_of(v), f"final/{key}{suffix}", check[key],
                                  check["timesteps"])
        rows.append(row)
    return rows


def run_greedy(cfg, p: DroneProblem, base: SACConstrainedSolver, reward_weights, logger,
               out: Path) -> tuple[dict, list]:
    """M(C)E-greedy given D-ICRL's learned reward, on all pairs (the paper's protocol)."""
    b = cfg.baselines
    greedy = SACGreedyConstraintInference(
        solver=base.clone(derived_seed(cfg.seed, 4)), reward_weights=reward_weights,
        demonstrations=p.demos, penalty=float(b.penalty), timesteps=int(b.timesteps),
        epsilon=None if b.epsilon is None else float(b.epsilon),
        max_constraints=b.max_constraints, progress=True)
    res = greedy.run()
    mask = res.constraint_mask.numpy()
    row, paths = evaluate_true_game(greedy.solver, cfg)
    row.update(constraint_row(mask, p), stop_reason=res.stop_reason)
    history = []
    sel = np.zeros_like(mask)
    for k, ll in enumerate(res.log_likelihood):
        if k:
            sel[res.added[k - 1]] = True
        fpr, fnr = false_positive_rate(sel, p.true), false_negative_rate(sel, p.true)
        history.append({"step": k, "added": res.added_names[k - 1] if k else None,
                        "log_likelihood": ll, "FPR": fpr, "FNR": fnr})
        logger.scalar("mce_greedy", "eval/FPR", fpr, k)
        logger.scalar("mce_greedy", "eval/FNR", fnr, k)
        logger.scalar("mce_greedy", "greedy/log_likelihood", ll, k)
    figure("M(C)E-greedy", mask, paths, out, logger, "mce_greedy", len(res.added))
    return row, history


def expert_row(p: DroneProblem) -> dict:
    """The demonstrations themselves (flown in the true game): SR 1, CVR 0 by design."""
    return {"CR_mean": None, "CR_std": None, "RFD": None, "FPR": None, "FNR": None,
            "SR": 1.0, "CVR": 0.0}


def run_drones(cfg, out: Path, t_start: float) -> None:
    import matplotlib.image

    if cfg.resume:
        raise ValueError("resume=true is not supported for the drone arena yet (the SAC "
                         "solvers' state is not checkpointed); rerun without resume.")
    split = list(cfg.split)
    p = build_drone_problem(cfg)
    save_drone_demonstrations(out / "demos.npz", p.demos)
    print(f"2 drones, {len(split)} learners holding {split} demonstrated pairs; "
          f"{p.cost_basis.dim} cost features, {int(p.true.sum())} of them true constraints",
          flush=True)
    logger = make_logger(cfg, out)
    fig3b = render_arena(trajectories=[s[:, :, :2] for s in p.demos.states],
                         constraint_cells=p.true,
                         title="Demonstrations and the true constraint cells")
    matplotlib.image.imsave(out / "fig3b_demonstrations.png", fig3b)
    logger.image("network", "figures/fig3b_demonstrations", fig3b, 0)
    base = pretrained_solver(cfg, p)

    methods: dict = {}
    histories: dict = {}
    d = make_drone_trainer(cfg, p, base, p.shards, split,
                           build(cfg.comm, n_learners=len(split)), stream=0)
    methods["D-ICRL"] = {"D": "✓" if len(split) > 1 else "×", "NATR": "✓",
                         "learners": run_icrl("D-ICRL", d, cfg, p, logger,
                                              lambda v: f"learner{v}", out)}
    histories["D-ICRL"] = d.history
    if cfg.algo.run_c_icrl:
        c = make_drone_trainer(cfg, p, base, [p.demos], [p.demos.n_pairs],
                               build(cfg.comm, n_learners=1), stream=1)
        methods["C-ICRL"] = {"D": "×", "NATR": "✓", "learners": run_icrl(
            "C-ICRL", c, cfg, p, logger, lambda v: "c_icrl", out)}
        histories["C-ICRL"] = c.history
    if cfg.baselines.run:
        reward = d.state.eta_bar[0, :-1]
        row, histories["M(C)E-greedy"] = run_greedy(cfg, p, base, reward, logger, out)
        methods["M(C)E-greedy"] = {"D": "×", "NATR": "×", "learners": [row]}
    methods["Experts (ground truth)"] = {"learners": [expert_row(p)]}
    logger.close()
    results = results_record(cfg, t_start=t_start, methods=methods,
                             disagreement=d.disagreement(), histories=histories)
    write_json(out / "results.json", results)
    print()
    print_table(methods, TABLE2_COLUMNS)
    print_timings(results, resumed=False)  # drone runs do not resume
    print(f"results, TensorBoard runs (tb/) and figures in {out.resolve()}")
