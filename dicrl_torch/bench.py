"""Benchmarks, each printing one JSON line (docs/design.md §8).

``python -m dicrl_torch.bench solver --experts N [--grid G] ...``::

    {"pairs": int, "backward_sweep_s": float, "forward_sweep_s": float,
     "peak_rss_gb": float, "device": str, ...}

``backward_sweep_s`` / ``forward_sweep_s`` are the median seconds per time step over
``--repeat`` timed solves (after one warm-up solve, which also compiles kernels).

``python -m dicrl_torch.bench sac [--steps S] [--repeat R] [--learners E] ...``: the SAC solver at
``experiment=table2_quick``'s solver settings (:data:`TABLE2_QUICK_SOLVER`, the drone
arena with its demonstrations in every batch), each engine timed on ``--steps`` env
steps after learning has started, the engines alternated ``--repeat`` times in one
process on the same threads::

    {"loops": {"sb3": {"updates_per_s": float, "env_steps_per_s": float, ...},
               "lean": {...}},
     "ratio": {"updates_per_s": float, "env_steps_per_s": float}, "threads": int, ...}

``ratio`` is the lean loop's median over the SB3 loop's (today's loop before the lean one).

``python -m dicrl_torch.bench certificate --experts N [--candidates C] ...``: the hard solves
of the identifiability classes and the certificate (every undemonstrated feature but one
forbidden, :mod:`dicrl_torch.algos.identifiability`), on the full grid and on the cells the
mask leaves open, the same candidates, and the exact forward pass that follows each::

    {"full_solve_s": float, "open_solve_s": float, "forward_s": float,
     "ratio": {"solve": float}, "same_probabilities": bool, "open_cells": [int], ...}

medians per candidate over ``C`` candidates (after one untimed warm-up of each path, which
also compiles); ``same_probabilities``: both paths give every candidate's probability equal.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.accrual import AllButOne, Chain, Hits, Positive, killed_forward
from dicrl_torch.algos.greedy import cost_features_of
from dicrl_torch.algos.identifiability import demonstrated_mask
from dicrl_torch.demos.drone_demos import make_drone_demonstrations
from dicrl_torch.envs.drones import DroneDynamics, JointDroneEnv
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman
from dicrl_torch.solvers.factored.open_cells import solve_hard
from dicrl_torch.solvers.sac import SACConstrainedSolver
from dicrl_torch.solvers.sac.lean import learn_together

TABLE2_QUICK_SOLVER: dict[str, Any] = {
    "n_envs": 4, "gradient_steps": 4, "ent_coef": 0.1, "learning_rate": 1.0e-3,
    "gamma": 0.99, "batch_size": 256, "learning_starts": 1000, "buffer_size": 100_000,
    "net_arch": (64, 64), "tau": 0.02, "scale_observations": True,
    "per_agent_critics": True, "split_cost_critic": True, "demo_fraction": 0.25,
    "estimate_action": "sampled", "absorbing": True,
}
"""``experiment=table2_quick``'s ``solver.solver`` settings (tests/test_bench.py checks them
against the composed config), less ``engine``."""
TABLE2_QUICK_DYNAMICS = {"command_set": "disc", "max_speed": 1.5}
"""``experiment=table2_quick``'s drone dynamics (``env.arena.dynamics``)."""


def _peak_rss_gb() -> float:
    # ru_maxrss is in KiB on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def bench_solver(*, experts: int, grid: int = 9, horizon: int = 10, repeat: int = 3,
                 device: str = "cpu", compile: bool | str = "auto", seed: int = 0) -> dict:
    """Time the factored solver on the nominal ``grid x grid`` game (the 9x9 case uses
    the paper's layout; obstacles do not change the learner's model)."""
    layout = GridLayout.scobee(experts) if grid == 9 else GridLayout.open_grid(grid, experts)
    model = TabularGridModel(layout=layout, horizon=horizon, gamma=0.99)
    solver = FactoredSoftBellman(model=model, device=device, compile=compile)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    g = torch.Generator().manual_seed(seed)
    reward = rb().weighted(rb.true_weights()) + cb().weighted(
        torch.rand(cb.dim, generator=g, dtype=torch.float64)).scale(-5.0)
    bwd, fwd = [], []
    for rep in range(repeat + 1):
        sol = solver.solve(reward, forward=True)
        if rep > 0:  # the first solve warms up (and compiles)
            bwd.append(sol.timings["backward_s"] / horizon)
            fwd.append(sol.timings["forward_s"] / horizon)
    occ_total = float(sol.state_occupancy.sum())
    dev = solver.device
    device_name = str(dev) if dev.type == "cpu" else torch.cuda.get_device_name(dev)
    expected = sum(model.gamma**t for t in range(horizon))
    return {
        "pairs": model.n_pairs,
        "backward_sweep_s": statistics.median(bwd),
        "forward_sweep_s": statistics.median(fwd),
        "peak_rss_gb": round(_peak_rss_gb(), 3),
        "device": device_name,
        "experts": experts, "grid": grid, "horizon": horizon, "repeat": repeat,
        "compiled": solver.use_compile, "threads": torch.get_num_threads(),
        "backward_all_s": [round(x, 4) for x in bwd],
        "forward_all_s": [round(x, 4) for x in fwd],
        "occupancy_mass_error": abs(occ_total - expected),
    }


def _time_sac(engine: str, steps: int, seed: int, device: str, demos: Any,
              learners: int) -> dict[str, float]:
    """One timing: ``learners`` fresh solvers at :data:`TABLE2_QUICK_SOLVER` with
    ``engine``, trained past ``learning_starts`` (untimed), then ``steps`` env steps each,
    timed: the lean ones as one ensemble, as learners sharing a process train, SB3's one
    after the other. Rates are per learner."""
    dynamics = DroneDynamics(**TABLE2_QUICK_DYNAMICS)
    solvers = []
    for k in range(learners):
        solver = SACConstrainedSolver(
            env_factory=lambda constrained: JointDroneEnv(constrained=constrained,
                                                          dynamics=dynamics),
            reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(),
            seed=seed * 1000 + k, device=device, n_eval_episodes=1, engine=engine,
            **TABLE2_QUICK_SOLVER)
        solver.set_demonstrations(demos)
        solver.set_weights(np.array([1.0, 1.0, 1.0, 1.0, -5.0]), np.full(solver.l_c, 0.1))
        solver.engine.learn(TABLE2_QUICK_SOLVER["learning_starts"] + 256)
        solvers.append(solver)
    updates, t0 = sum(s.n_updates for s in solvers), time.perf_counter()
    if engine == "lean":
        learn_together([s.engine for s in solvers], steps)
    else:
        for solver in solvers:
            solver.engine.learn(steps)
    dt = time.perf_counter() - t0
    updates = sum(s.n_updates for s in solvers) - updates
    for solver in solvers:
        solver.close()
    return {"updates_per_s": updates / dt / learners,
            "env_steps_per_s": steps * learners / dt / learners, "seconds": dt,
            "updates": updates}


def bench_sac(*, steps: int = 2000, repeat: int = 3, device: str = "cpu", seed: int = 0,
              learners: int = 1, loops: tuple[str, ...] = ("sb3", "lean")) -> dict:
    """Time each SAC engine (``loops``) ``repeat`` times with ``learners`` learners in the
    process, alternating the engines so that both see the same machine; medians (per
    learner) and the last loop's ratio over the first."""
    demos = make_drone_demonstrations(4, rng=np.random.default_rng(seed),
                                      dynamics=DroneDynamics(**TABLE2_QUICK_DYNAMICS))
    runs: dict[str, list[dict[str, float]]] = {loop: [] for loop in loops}
    for rep in range(repeat):
        for loop in loops:
            runs[loop].append(_time_sac(loop, steps, seed + rep, device, demos, learners))
    medians = {loop: {key: statistics.median(r[key] for r in rs)
                      for key in ("updates_per_s", "env_steps_per_s")}
               for loop, rs in runs.items()}
    for loop, rs in runs.items():
        medians[loop]["all_updates_per_s"] = [round(r["updates_per_s"], 1) for r in rs]
    base, new = medians[loops[0]], medians[loops[-1]]
    dev = torch.device(device)
    return {
        "loops": medians,
        "ratio": {key: new[key] / base[key] for key in ("updates_per_s", "env_steps_per_s")},
        "steps": steps, "repeat": repeat, "threads": torch.get_num_threads(),
        "device": str(dev) if dev.type == "cpu" else torch.cuda.get_device_name(dev),
        "settings": "experiment=table2_quick solver.solver", "learners": learners,
    }


def bench_certificate(*, experts: int, candidates: int = 3, demonstrations: int = 100,
                      horizon: int = 40, compile: bool | str = "auto", seed: int = 0) -> dict:
    """Time ``candidates`` hard solves on the full grid and on the open cells (module
    docstring), on the paper's layout with ``demonstrations`` optimal ones."""
    model = TabularGridModel(layout=GridLayout.scobee(experts), horizon=horizon, gamma=0.99)
    solver = FactoredSoftBellman(model=model, compile=compile)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    reward = rb().weighted(rb.true_weights())
    demos = sample_trajectories(
        expert_solution(solver=solver, reward_features=rb(), reward_weights=rb.true_weights(),
                        temperature=0.0), demonstrations, np.random.default_rng(seed))
    unseen = ~demonstrated_mask(cost_basis=cb, model=model, demonstrations=demos)
    features, _ = cost_features_of(cb, model)
    pos = Positive(features)
    masks, chain = AllButOne(features, unseen, pos, model), Chain(model, solver.device)
    d0 = model.initial_distribution().reshape(-1).to(solver.device)

    times: dict[str, list[float]] = {"full": [], "open": [], "forward": []}
    probabilities: dict[str, list[float]] = {"full": [], "open": []}
    open_cells = []
    todo = torch.nonzero(unseen).flatten().tolist()[:candidates + 1]
    for n, j in enumerate(todo):
        mask, terminal = masks(j)
        target = torch.zeros(features.dim, dtype=torch.bool)
        target[j] = True
        hits = Hits(features, target, model, solver.device, False, pos)
        for path in ("full", "open"):
            t0 = time.perf_counter()
            sol = solve_hard(solver, reward + mask, terminal, open_cells=path == "open")
            t1 = time.perf_counter()
            p = killed_forward(sol, hits, d0, chain)
            if n > 0:  # the first candidate warms up (and compiles)
                times[path].append(t1 - t0)
                times["forward"].append(time.perf_counter() - t1)
                probabilities[path].append(p)
                if path == "open":
                    open_cells.append(sol.solution.solver.model.n_cells - 1
                                      if sol.index is not None else model.n_cells)
    full_s, open_s = statistics.median(times["full"]), statistics.median(times["open"])
    return {
        "full_solve_s": full_s, "open_solve_s": open_s,
        "forward_s": statistics.median(times["forward"]), "ratio": {"solve": full_s / open_s},
        "same_probabilities": probabilities["full"] == probabilities["open"],
        "open_cells": open_cells, "cells": model.n_cells, "pairs": model.n_pairs,
        "experts": experts, "candidates": len(open_cells), "demonstrations": demonstrations,
        "compiled": solver.use_compile, "threads": torch.get_num_threads(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dicrl_torch.bench")
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("solver", help="time the factored soft-Bellman solver")
    p.add_argument("--experts", type=int, required=True, choices=(1, 2, 3))
    p.add_argument("--grid", type=int, default=9, help="side G of a nominal GxG grid")
    p.add_argument("--horizon", type=int, default=10, help="time steps per sweep")
    p.add_argument("--repeat", type=int, default=3, help="timed solves (median reported)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--compile", default="auto", choices=("auto", "on", "off"))
    q = sub.add_parser("sac", help="time the SAC solver's loops (SB3's and the lean one)")
    q.add_argument("--steps", type=int, default=2000, help="timed env steps per run")
    q.add_argument("--repeat", type=int, default=3, help="runs per loop (median reported)")
    q.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    q.add_argument("--threads", type=int, default=1, help="torch threads (1: as the runs)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--learners", type=int, default=1,
                   help="learners in the process (the lean ones trained as one ensemble)")
    c = sub.add_parser("certificate", help="time the certificate's hard solves, full grid "
                                           "and open cells")
    c.add_argument("--experts", type=int, default=3, choices=(1, 2, 3))
    c.add_argument("--candidates", type=int, default=3, help="timed candidates (median)")
    c.add_argument("--demonstrations", type=int, default=100)
    c.add_argument("--horizon", type=int, default=40)
    args = parser.parse_args(argv)
    if args.what == "certificate":
        if min(args.candidates, args.demonstrations, args.horizon) < 1:
            parser.error("--candidates, --demonstrations and --horizon must be >= 1")
        print(json.dumps(bench_certificate(experts=args.experts, candidates=args.candidates,
                                           demonstrations=args.demonstrations,
                                           horizon=args.horizon)), flush=True)
        return 0
    if args.what == "sac":
        if args.steps < 4 or min(args.repeat, args.threads, args.learners) < 1:
            parser.error("--steps must be >= 4, --repeat, --threads and --learners >= 1")
        if args.device == "cuda" and not torch.cuda.is_available():
            parser.error("--device cuda requested but CUDA is not available")
        torch.set_num_threads(args.threads)
        print(json.dumps(bench_sac(steps=args.steps, repeat=args.repeat, device=args.device,
                                   seed=args.seed, learners=args.learners)), flush=True)
        return 0
    if args.grid < 2:
        parser.error("--grid must be >= 2")
    if args.horizon < 1 or args.repeat < 1:
        parser.error("--horizon and --repeat must be >= 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda requested but CUDA is not available")
    compile_ = {"auto": "auto", "on": True, "off": False}[args.compile]
    result = bench_solver(experts=args.experts, grid=args.grid, horizon=args.horizon,
                          repeat=args.repeat, device=args.device, compile=compile_)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
