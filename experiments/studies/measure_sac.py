"""Measure the SAC-style constrained solver's throughput (env steps and gradient updates).

    .venv/bin/python experiments/studies/measure_sac.py         # n_envs 1 and 4, 3 repeats
    .venv/bin/python experiments/studies/measure_sac.py --n-envs 4 --gradient-steps 1 4
    .venv/bin/python experiments/studies/measure_sac.py --steps 4000 --device cuda

For each ``n_envs`` and ``--gradient-steps`` (per vectorised env step; ``n_envs`` of them
is one update per env step; the configs use 1): a solver with the default
hyper-parameters (batch 256, 64x64 networks, cell-occupancy cost basis with 201
features), a warm-up until learning has started, then ``--steps`` more env steps timed.
Prints one JSON line per setting with the median over ``--repeat`` runs of env steps/s
and gradient updates/s, on one torch thread.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time

import numpy as np
import torch

from dicrl_torch.envs.drones import JointDroneEnv
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.solvers.sac import SACConstrainedSolver


def one_run(n_envs: int, steps: int, device: str, seed: int, gradient_steps: int,
            per_agent_critics: bool, engine: str) -> tuple[float, float]:
    solver = SACConstrainedSolver(engine=engine,
        env_factory=JointDroneEnv, reward_basis=DoorLocationRewardBasis(),
        cost_basis=CellOccupancyCostBasis(), seed=seed, n_envs=n_envs, device=device,
        learning_starts=256, n_eval_episodes=1, gradient_steps=gradient_steps,
        per_agent_critics=per_agent_critics)
    eta = np.array([1.0, 0.5, 1.0, 0.5, -1.0])
    wc = np.full(solver.l_c, 0.1)
    solver.solve(eta, wc, 512, n_eval_episodes=1)  # warm-up: past learning_starts
    updates0 = solver.n_updates
    t0 = time.perf_counter()
    solver.engine.learn(steps)
    dt = time.perf_counter() - t0
    updates = solver.n_updates - updates0
    solver.close()
    return steps / dt, updates / dt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-envs", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--gradient-steps", type=int, nargs="+", default=[1],
                        help="gradient steps per vectorised env step (n_envs: one per env step)")
    parser.add_argument("--engine", default="lean", choices=("lean", "sb3"))
    parser.add_argument("--per-agent-critics", action="store_true",
                        help="one soft-Q column per drone (experiment=table2's solver)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for n_envs, gradient_steps in itertools.product(args.n_envs, args.gradient_steps):
        runs = [one_run(n_envs, args.steps, args.device, seed, gradient_steps,
                        args.per_agent_critics, args.engine) for seed in range(args.repeat)]
        print(json.dumps({
            "n_envs": n_envs, "gradient_steps": gradient_steps,
            "per_agent_critics": args.per_agent_critics, "device": args.device,
            "engine": args.engine,
            "threads": args.threads,
            "env_steps_per_s": round(statistics.median(r[0] for r in runs), 1),
            "grad_steps_per_s": round(statistics.median(r[1] for r in runs), 1),
            "runs": [[round(a, 1), round(b, 1)] for a, b in runs],
        }))


if __name__ == "__main__":
    main()
