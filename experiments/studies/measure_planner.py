"""Measure planning learners' cost: ``solver.eval_policy=plan`` on the true game.

    .venv/bin/python experiments/studies/measure_planner.py           # table2, 40 episodes
    .venv/bin/python experiments/studies/measure_planner.py --episodes 16 experiment=table2_quick
    .venv/bin/python experiments/studies/measure_planner.py solver.planner.samples=128 \\
        solver.planner.iterations=3

Builds the configured drone task (Hydra overrides as for ``train.py``; default
``experiment=table2``), gives its planner the true constraint set and a door-seeking reward
(what a learner holding the exact set would plan on: ``ω_r = 1``, ``λ = -10``) and flies
``--episodes`` true-game episodes on the evaluation's common starts, ``--repeat`` times.
Prints one JSON line: SR, CVR, the median seconds, planned env steps per second (every
episode's steps until it ends) and a checksum of the flown paths (equal checksums: equal
flights). No training runs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

EXPERIMENTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXPERIMENTS))  # the entry points' common.py (studies/__init__.py)
from common import drone_task  # noqa: E402

CONFIGS = EXPERIMENTS.parent / "configs"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--repeat", type=int, default=1, help="timed evaluations (median)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. seed=1")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.repeat < 1:
        parser.error("--episodes and --repeat must be >= 1")
    overrides = list(args.overrides)
    if not any(o.startswith("experiment=") for o in overrides):
        overrides.insert(0, "experiment=table2")
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="train", overrides=[
            *overrides, f"eval_episodes={args.episodes}", "solver.eval_policy=plan"])
    task = drone_task(cfg)
    truth = task.cost_basis.true_constraints().numpy()
    eta = np.array([1.0] * task.reward_basis.dim + [-10.0])
    seconds, row, paths = [], None, []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        row, paths = task.evaluate_planned(task.base, eta, truth.astype(np.float64), truth,
                                           seed=0)
        seconds.append(time.perf_counter() - t0)
    steps = sum(len(p) - 1 for p in paths)
    median = statistics.median(seconds)
    print(json.dumps({
        "experiment": cfg.name, "episodes": args.episodes, "planner": task.planner_settings,
        "command_set": cfg.env.arena.dynamics.get("command_set", "box"),
        "SR": row["SR"], "CVR": row["CVR"], "median_s": round(median, 1),
        "all_s": [round(s, 1) for s in seconds], "env_steps": steps,
        "env_steps_per_s": round(steps / median, 2),
        "checksum": float(sum(p.sum() for p in paths))}), flush=True)


if __name__ == "__main__":
    main()
