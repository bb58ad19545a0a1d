"""Measure ME-greedy and MCE-greedy on the grid world (paper §6.1 baselines).

    .venv/bin/python experiments/studies/measure_greedy.py        # 1 expert, p = 1.0 and 0.8
    .venv/bin/python experiments/studies/measure_greedy.py --expert-temperature 1.0  # soft
    .venv/bin/python experiments/studies/measure_greedy.py --experts 2 --one-step  # one step
    .venv/bin/python experiments/studies/measure_greedy.py --cost regions --expert-temperature 1.0
                                   # Scobee's own setting: wall colours, soft experts

For each dynamics (deterministic, 20% slip) and each model (ME, MCE): 100 demonstrations
of the optimal experts (``expert_solution``, seed ``--seed``), the greedy with the true
reward, then FPR, the recovered fraction of the *reachable* true constraints (see
``dicrl_torch.algos.greedy.reachable_constraints``), the number of constraints added,
wall time, CR / CVR of the final model's policy over 200 episodes in the true CMG, and
the mean log-likelihood of the learned set next to that of the true constraint set.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from dicrl_torch.algos.greedy import GreedyConstraintInference, reachable_constraints
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    GoalClosenessRewardBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.metrics import false_negative_rate, false_positive_rate, rollout_true_cmg
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

COST_BASES = {"shared": SharedIndicatorCostBasis, "regions": RegionIndicatorCostBasis}


def build(n_experts: int, p_success: float, seed: int, expert_temperature: float,
          n_demos: int, cost: str = "shared"):
    layout = GridLayout.scobee(n_experts)
    model = TabularGridModel(layout=layout, horizon=40, gamma=0.99, p_success=p_success)
    # float64 is free on one expert (729 pairs); float32 on two (531,441 pairs).
    dtype = torch.float64 if n_experts == 1 else torch.float32
    solver = FactoredSoftBellman(model=model, dtype=dtype)
    rb, cb = GoalClosenessRewardBasis(model), COST_BASES[cost](model)
    w_true = rb.true_weights()
    exp_solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    experts = expert_solution(solver=exp_solver, reward_features=rb(), reward_weights=w_true,
                              temperature=expert_temperature)
    demos = sample_trajectories(experts, n_demos, np.random.default_rng(seed))
    return layout, model, solver, rb, cb, rb().weighted(w_true), demos, experts


def run_one(args, p_success: float, kind: str) -> dict:
    layout, model, solver, rb, cb, reward, demos, experts = build(
        args.experts, p_success, args.seed, args.expert_temperature, args.demos, args.cost)
    true = cb.true_constraints()
    reach = reachable_constraints(solver=solver, reward=reward, cost_basis=cb, true_mask=true)
    greedy = GreedyConstraintInference(solver=solver, reward=reward, cost_basis=cb,
                                       demonstrations=demos, model=kind, epsilon=args.epsilon)
    res = greedy.run()
    learned = res.constraint_mask
    ev = rollout_true_cmg(policy=res.solution.policy_at, model=model, layout=layout,
                          reward_table=reward.local[:, :, 0], n_episodes=200,
                          rng=torch.Generator().manual_seed(args.seed))
    ll_true = greedy.mean_log_likelihood(greedy.solve(true)[0])
    ev_e = rollout_true_cmg(policy=experts.policy_at, model=model, layout=layout,
                            reward_table=reward.local[:, :, 0], n_episodes=200,
                            rng=torch.Generator().manual_seed(args.seed))
    return {
        "p_success": p_success, "model": kind.upper(), "epsilon": round(greedy.epsilon, 4),
        "FPR": round(false_positive_rate(learned, true), 3),
        "FNR": round(false_negative_rate(learned, true), 3),
        "reachable": [cb.names[j] for j in torch.nonzero(reach).flatten().tolist()],
        "recovered_reachable": round(float((learned & reach).sum() / reach.sum()), 3),
        "n_added": len(res.added), "added": res.added_names,
        "gains": [round(g, 4) for g in res.improvement],
        "stop": res.stop_reason, "wall_s": round(res.seconds, 2), "solves": greedy.solves,
        "CR_mean": round(ev.cr_mean, 2), "CR_std": round(ev.cr_std, 2), "CVR": ev.cvr,
        "ll_learned": round(res.log_likelihood[-1], 3), "ll_true_set": round(ll_true, 3),
        "experts_CR_mean": round(ev_e.cr_mean, 2), "experts_CVR": ev_e.cvr,
    }


def one_step(args) -> dict:
    """Wall time of one greedy step (solve + accruals + log-likelihood) per model."""
    out = {}
    layout, model, solver, rb, cb, reward, demos, _ = build(
        args.experts, 0.8, args.seed, args.expert_temperature, args.demos, args.cost)
    for kind in ("me", "mce"):
        g = GreedyConstraintInference(solver=solver, reward=reward, cost_basis=cb,
                                      demonstrations=demos, model=kind, max_constraints=1)
        t0 = time.perf_counter()
        sel = torch.zeros(cb.dim, dtype=torch.bool)
        sol, _ = g.solve(sel)
        t1 = time.perf_counter()
        sol.feature_expectation(g.features)
        ll = g.mean_log_likelihood(sol)
        t2 = time.perf_counter()
        out[kind.upper()] = {"pairs": model.n_pairs, "solve_s": round(t1 - t0, 2),
                             "backward_s": round(sol.timings["backward_s"], 2),
                             "forward_s": round(sol.timings["forward_s"], 2),
                             "likelihood_and_accrual_s": round(t2 - t1, 2),
                             "step_s": round(t2 - t0, 2), "mean_ll": round(ll, 2),
                             "threads": torch.get_num_threads(), "dtype": str(solver.dtype)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--experts", type=int, default=1, choices=(1, 2, 3))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--demos", type=int, default=100)
    ap.add_argument("--epsilon", type=float, default=None,
                    help="nats per trajectory (default: ln(m)/(2m))")
    ap.add_argument("--expert-temperature", type=float, default=0.0)
    ap.add_argument("--cost", choices=sorted(COST_BASES), default="shared",
                    help="candidate features: shared cells/actions/collision, or those "
                         "plus Scobee's wall colours (regions)")
    ap.add_argument("--one-step", action="store_true", help="only time one greedy step")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.one_step:
        print(json.dumps(one_step(args)))
        return
    for p in (1.0, 0.8):
        for kind in ("me", "mce"):
            print(json.dumps(run_one(args, p, kind)), flush=True)


if __name__ == "__main__":
    main()
